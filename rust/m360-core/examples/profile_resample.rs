//! Times the resampling kernels without Python in the way: `cargo run --release --example profile_resample`.
use m360_core::blend::Method;
use m360_core::resample::{erp_to_tangents, tangents_to_erp, Sampling};
use m360_core::{Layout, Plan};
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn time(label: &str, mut f: impl FnMut()) {
    f();
    let runs = (0..7)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .collect();
    println!("{label:<28} {:8.4} s", median(runs));
}

fn main() {
    let width: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(2048);
    let t = Instant::now();
    let plan = Plan::new(Layout::icosahedron(width, 0.3, None).expect("layout"));
    plan.tangent_taps();
    println!(
        "{:<28} {:8.4} s",
        "build tangent taps",
        t.elapsed().as_secs_f64()
    );
    let t = Instant::now();
    plan.erp_taps();
    println!(
        "{:<28} {:8.4} s",
        "build erp taps",
        t.elapsed().as_secs_f64()
    );
    let layout = plan.layout();
    let erp: Vec<u8> = (0..layout.erp_height * layout.erp_width * 3)
        .map(|i| (i * 7 % 251) as u8)
        .collect();
    time("erp->tangents u8x3", || {
        let mut out = vec![0u8; 20 * layout.tangent_shape().0 * layout.tangent_shape().1 * 3];
        erp_to_tangents(plan.tangent_taps(), layout, &erp, 3, &mut out);
        std::hint::black_box(out);
    });
    let erpf: Vec<f32> = erp.iter().step_by(3).map(|&v| f32::from(v)).collect();
    time("erp->tangents f32x1", || {
        let mut out = vec![0f32; 20 * layout.tangent_shape().0 * layout.tangent_shape().1];
        erp_to_tangents(plan.tangent_taps(), layout, &erpf, 1, &mut out);
        std::hint::black_box(out);
    });
    let (h, w) = layout.tangent_shape();
    let tiles = vec![1.0f32; 20 * h * w];
    time("tangents->erp", || {
        let mut out = vec![0f32; 20 * layout.erp_height * layout.erp_width];
        tangents_to_erp(
            plan.erp_taps(),
            layout,
            &tiles,
            Sampling::Bilinear,
            &mut out,
        );
        std::hint::black_box(out);
    });
    time("blend mean", || {
        let n = layout.erp_height * layout.erp_width;
        let mut out = vec![0.0f32; n];
        plan.blend(&tiles, &Method::Mean, &mut out, None)
            .expect("mean blend");
        std::hint::black_box(out);
    });
}
