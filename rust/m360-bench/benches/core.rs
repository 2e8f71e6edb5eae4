//! Criterion benchmarks of the core's hot paths at 2K (the per-image work; plan building once).
//!
//! `cargo bench -p m360-bench` (add `-- poisson` to run one group). The machine the project is
//! measured on is shared and has 2 cores: compare the solvers within one run, not across runs.
//! These replace the timing tests that used to sit, ignored, among the unit tests.

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};
use m360_core::align::{self, Overlaps};
use m360_core::blend::{poisson_blend_layers, Method, PoissonParams, PoissonSolver};
use m360_core::resample::ErpTaps;
use m360_core::{Layout, Plan};
use std::hint::black_box;

const WIDTH: usize = 2048;

/// A deterministic pseudo-random number in [0, 1) from a counter.
fn noise(i: usize) -> f64 {
    let mut x = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    x ^= x >> 31;
    x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    (x >> 11) as f64 / (1u64 << 53) as f64
}

/// A smooth disparity field on every tangent, with a per-tangent scale (what alignment fixes).
fn tangents(layout: &Layout) -> Vec<f32> {
    let (h, w) = layout.tangent_shape();
    let mut out = Vec::with_capacity(layout.cameras.len() * h * w);
    for (t, cam) in layout.cameras.iter().enumerate() {
        let scale = 0.8 + 0.4 * noise(t);
        for r in 0..h {
            for c in 0..w {
                let d = cam.pixel_direction(c as f64, r as f64);
                out.push((scale * (1.0 + 0.3 * d.x + 0.2 * d.y * d.z)) as f32);
            }
        }
    }
    out
}

fn plan_building(c: &mut Criterion) {
    let layout = Layout::icosahedron(WIDTH, 0.3, None).expect("layout");
    let mut group = c.benchmark_group("plan");
    group.sample_size(10);
    group.bench_function("erp taps", |b| {
        b.iter(|| black_box(ErpTaps::build(&layout)));
    });
    group.bench_function("overlaps 1%", |b| {
        b.iter(|| black_box(Overlaps::build(&layout, 0.01, 0.0)));
    });
    group.finish();
}

fn blends(c: &mut Criterion) {
    let plan = Plan::new(Layout::icosahedron(WIDTH, 0.3, None).expect("layout"));
    let values = tangents(plan.layout());
    let n = plan.layout().erp_height * plan.layout().erp_width;
    let mut group = c.benchmark_group("blend");
    group.sample_size(10);
    for method in [
        Method::Mean,
        Method::Nearest,
        Method::Frustum,
        Method::Consensus,
        Method::Poisson(PoissonParams::default()),
    ] {
        let (mut out, mut spread) = (vec![0.0f32; n], vec![0.0f32; n]);
        plan.blend(&values, &method, &mut out, None)
            .expect("warm-up");
        group.bench_function(method.name(), |b| {
            b.iter(|| {
                plan.blend(&values, &method, &mut out, Some(&mut spread))
                    .expect("blend");
            });
        });
    }
    group.finish();
}

/// The three conjugate-gradient solvers on the same system: three random layers on the 2K grid.
fn poisson_solvers(c: &mut Criterion) {
    let (h, w) = (WIDTH / 2, WIDTH);
    let n = h * w;
    let values: Vec<f32> = (0..3 * n).map(|i| (1.0 + 0.01 * noise(i)) as f32).collect();
    let weights: Vec<f32> = (0..3 * n).map(|i| noise(i + 7 * n) as f32).collect();
    let target: Vec<f32> = (0..n)
        .map(|i| (1.0 + 0.01 * noise(i + 11 * n)) as f32)
        .collect();
    let mut group = c.benchmark_group("poisson");
    group.sample_size(10);
    for solver in [
        PoissonSolver::Multigrid,
        PoissonSolver::Faer,
        PoissonSolver::Fused,
    ] {
        let params = PoissonParams {
            solver,
            ..PoissonParams::default()
        };
        let mut out = vec![0.0f64; n];
        group.bench_function(format!("{solver}"), |b| {
            b.iter(|| {
                poisson_blend_layers(&values, &weights, &target, h, w, &params, &mut out)
                    .expect("solve")
            });
        });
    }
    group.finish();
}

fn alignment(c: &mut Criterion) {
    let plan = Plan::new(Layout::icosahedron(WIDTH, 0.3, None).expect("layout"));
    let values = tangents(plan.layout());
    let options = align::Options::default();
    let overlaps = plan.overlaps(options.sample_fraction, options.pole_cap_deg);
    let mut group = c.benchmark_group("align");
    group.sample_size(10);
    group.bench_function("default (newton, 4x3 + 8x7)", |b| {
        b.iter_batched(
            || values.clone(),
            |mut maps| align::align(plan.layout(), &mut maps, &overlaps, &options).expect("align"),
            BatchSize::LargeInput,
        );
    });
    group.finish();
}

criterion_group!(benches, plan_building, blends, poisson_solvers, alignment);
criterion_main!(benches);
