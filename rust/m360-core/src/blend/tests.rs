//! Tests of the blends: weights against their definitions, the row blends against a smooth
//! field, Poisson against a dense solve.

use super::multigrid::Multigrid;
use super::poisson::cg::{solve_fused, solve_multigrid};
use super::poisson::system::{assemble, LayerSource, System, Target};
use super::rows::{prior_vote, prior_vote_lanes, RowSamples};
use super::weights::{frustum_weight, inscribed_half_fov, radial_weight, FRUSTUM_RAMP};
use super::*;
use crate::layout::Layout;
use crate::plan::Plan;
use crate::resample::{erp_to_tangents, tangents_to_erp, Sampling};
use crate::sphere::ErpGrid;

/// The blend of `tangents` with `method` through a plan, and its spread.
fn blend_to_vec(plan: &Plan, tangents: &[f32], method: Method) -> (Vec<f32>, Vec<f32>) {
    let n = plan.layout().erp_height * plan.layout().erp_width;
    let (mut disparity, mut spread) = (vec![0.0; n], vec![0.0; n]);
    plan.blend(tangents, &method, &mut disparity, Some(&mut spread))
        .expect("blend");
    (disparity, spread)
}

fn layout(erp_width: usize) -> Layout {
    Layout::icosahedron(erp_width, 0.3, None).expect("layout")
}

#[test]
#[expect(
    clippy::float_cmp,
    reason = "weights are exactly 0 or 1 there by construction"
)]
fn frustum_values_at_centre_border_and_ramp_start() {
    let cam = &layout(2048).cameras[0];
    let (w, h) = (cam.width as f64, cam.height as f64);
    let centre = ((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    assert_eq!(frustum_weight(cam, centre.0, centre.1), 1.0);
    for (x, y) in [
        (-0.5, centre.1),
        (w - 0.5, centre.1),
        (centre.0, -0.5),
        (-0.5, -0.5),
    ] {
        assert_eq!(frustum_weight(cam, x, y), 0.0);
    }
    // Along the diagonal from the corner (−½, −½): t/0.3 up to t = 0.3, then 1.
    for t in [0.05, 0.15, 0.29, 0.3, 0.31, 0.5] {
        let (x, y) = (-0.5 + t * w, -0.5 + t * h);
        let want = (t / FRUSTUM_RAMP).min(1.0);
        assert!((frustum_weight(cam, x, y) - want).abs() < 1e-12, "t = {t}");
    }
}

#[test]
#[expect(
    clippy::float_cmp,
    reason = "weights are exactly 0 or 1 there by construction"
)]
fn radial_values_on_the_axis_at_15_degrees_and_at_the_inscribed_edge() {
    let cam = &layout(2048).cameras[3];
    let edge = inscribed_half_fov(cam);
    // The icosahedron tangent point is 115.5 px from the nearer border of 346 rows:
    // atan(115.5 / f) with f = 400 / 2.362.
    assert!(
        (edge.to_degrees() - 34.3).abs() < 0.3,
        "{}",
        edge.to_degrees()
    );
    let at_angle = |deg: f64| {
        // A point at `deg` from the axis, straight to the right of the principal point.
        let x = cam.cx + cam.fx * deg.to_radians().tan();
        radial_weight(cam, x, cam.cy)
    };
    assert_eq!(radial_weight(cam, cam.cx, cam.cy), 1.0);
    assert_eq!(at_angle(14.9), 1.0);
    assert!((at_angle(15.0) - 1.0).abs() < 1e-9);
    let mid = f64::midpoint(15.0, edge.to_degrees());
    assert!((at_angle(mid) - 0.5).abs() < 1e-9);
    assert!(at_angle(edge.to_degrees()).abs() < 1e-9);
    assert_eq!(at_angle(edge.to_degrees() + 1.0), 0.0);
}

#[test]
fn nearest_maps_partition_the_sphere() {
    // Every ERP direction is claimed by exactly one face: the nn weights of the faces that
    // see a pixel sum to 1 (up to bilinear mixing at triangle edges).
    // Edge bands are ±1 tangent pixel wide: at 1024 about 5 % of the sphere.
    let plan = Plan::new(layout(1024));
    let weights = plan.weight_maps(Weighting::Nearest);
    let ones = vec![1.0f32; weights.maps().len()];
    let (mut total, mut exact) = (0usize, 0usize);
    let (mut row, mut sums) = (RowSamples::default(), Vec::new());
    for i in 0..plan.layout().erp_height {
        row.fill_from_taps(plan.erp_taps(), &ones, Some(weights), false, i);
        sums.clear();
        sums.resize(plan.layout().erp_width, 0.0f32);
        for run in &row.runs {
            for (j, t) in run.columns().zip(run.taps()) {
                sums[j] += row.weights[t];
            }
        }
        for &sum in &sums {
            total += 1;
            exact += usize::from((sum - 1.0).abs() < 1e-4);
            // Near the 12 vertices up to five faces mix: bounded, not exact.
            assert!((0.0..2.0).contains(&sum), "{sum}");
        }
    }
    assert!(exact as f64 > 0.93 * total as f64, "{exact} of {total}");
}

/// A dense reference: assemble the same normal equations explicitly and solve by Gaussian
/// elimination (small grids only).
fn dense_solve(values: &[f32], weights: &[f32], target: &[f32], h: usize, w: usize) -> Vec<f64> {
    let n = h * w;
    let k = values.len() / n;
    let mut a = vec![0.0f64; n * n];
    let mut b = vec![0.0f64; n];
    let mut add_edge = |p: usize, q: usize| {
        for l in 0..k {
            let (vp, vq) = (values[l * n + p], values[l * n + q]);
            if !(vp.is_finite() && vq.is_finite()) {
                continue;
            }
            let wgt = 0.5 * (f64::from(weights[l * n + p]) + f64::from(weights[l * n + q]));
            let g = f64::from(vq) - f64::from(vp);
            a[p * n + p] += wgt;
            a[q * n + q] += wgt;
            a[p * n + q] -= wgt;
            a[q * n + p] -= wgt;
            b[p] -= wgt * g;
            b[q] += wgt * g;
        }
    };
    for i in 0..h {
        for j in 0..w {
            add_edge(i * w + j, i * w + (j + 1) % w);
            if i + 1 < h {
                add_edge(i * w + j, (i + 1) * w + j);
            }
        }
    }
    for p in 0..n {
        a[p * n + p] += PoissonParams::DEFAULT_LAM;
        b[p] += PoissonParams::DEFAULT_LAM * f64::from(target[p]);
    }
    // Gaussian elimination without pivoting: the matrix is SPD.
    for c in 0..n {
        for r in c + 1..n {
            let f = a[r * n + c] / a[c * n + c];
            if f != 0.0 {
                for cc in c..n {
                    a[r * n + cc] -= f * a[c * n + cc];
                }
                b[r] -= f * b[c];
            }
        }
    }
    let mut x = vec![0.0; n];
    for r in (0..n).rev() {
        let s: f64 = (r + 1..n).map(|c| a[r * n + c] * x[c]).sum();
        x[r] = (b[r] - s) / a[r * n + r];
    }
    x
}

/// Seeded pseudo-random numbers in [0, 1) (SplitMix64).
fn rng(seed: u64) -> impl FnMut() -> f64 {
    let mut s = seed;
    move || {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[test]
fn layered_poisson_matches_a_dense_solve() {
    let (h, w, k) = (6, 12, 3);
    let n = h * w;
    let mut r = rng(7);
    let mut values: Vec<f32> = (0..k * n).map(|_| (1.0 + r()) as f32).collect();
    let weights: Vec<f32> = (0..k * n).map(|_| r() as f32).collect();
    for v in values.iter_mut().step_by(5) {
        *v = f32::NAN;
    }
    let target: Vec<f32> = (0..n).map(|_| (1.0 + r()) as f32).collect();
    let params = PoissonParams {
        tolerance: 1e-12,
        ..Default::default()
    };
    let mut out = vec![0.0f64; n];
    let report =
        poisson_blend_layers(&values, &weights, &target, h, w, &params, &mut out).expect("solve");
    let want = dense_solve(&values, &weights, &target, h, w);
    // Edge weights are stored as f32 (half the memory at 8K): agreement to ~1e-7.
    for (a, b) in out.iter().zip(&want) {
        assert!((a - b).abs() < 1e-6 * b.abs(), "{a} vs {b}");
    }
    assert!(report.relative_residual <= 1e-12);
}

#[test]
fn fused_faer_and_multigrid_conjugate_gradients_agree() {
    let (h, w, k) = (16, 32, 4);
    let n = h * w;
    let mut r = rng(11);
    let values: Vec<f32> = (0..k * n).map(|_| (1.0 + r()) as f32).collect();
    let weights: Vec<f32> = (0..k * n).map(|_| r() as f32).collect();
    let target: Vec<f32> = (0..n).map(|_| (1.0 + r()) as f32).collect();
    let mut sols = Vec::new();
    for solver in [
        PoissonSolver::Fused,
        PoissonSolver::Faer,
        PoissonSolver::Multigrid,
    ] {
        let params = PoissonParams {
            tolerance: 1e-11,
            solver,
            ..Default::default()
        };
        let mut out = vec![0.0f64; n];
        let rep = poisson_blend_layers(&values, &weights, &target, h, w, &params, &mut out)
            .expect("solve");
        assert!(rep.relative_residual <= 1e-11 && rep.iterations > 0);
        sols.push(out);
    }
    for other in &sols[1..] {
        for (a, b) in sols[0].iter().zip(other) {
            assert!((a - b).abs() < 1e-8, "{a} vs {b}");
        }
    }
}

/// A layered problem with a few invalid samples and uncovered pixels (K·H·W values,
/// weights, H·W target).
fn layered_problem(h: usize, w: usize, k: usize, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let n = h * w;
    let mut r = rng(seed);
    let mut values: Vec<f32> = (0..k * n).map(|_| (1.0 + r()) as f32).collect();
    let weights: Vec<f32> = (0..k * n).map(|_| 2.0 * r() as f32).collect();
    let mut target: Vec<f32> = (0..n).map(|_| (1.0 + r()) as f32).collect();
    for v in values.iter_mut().step_by(7) {
        *v = f32::NAN;
    }
    // A few pixels no layer sees: decoupled unknowns with no fidelity.
    for p in [3 * w + 5, n / 2, n - 1] {
        for l in 0..k {
            values[l * n + p] = f32::NAN;
        }
        target[p] = f32::NAN;
    }
    (values, weights, target)
}

/// The normal equations of `k` layers on an h x w grid with a given target.
fn assemble_layers(
    values: &[f32],
    weights: &[f32],
    target: &[f32],
    k: usize,
    h: usize,
    w: usize,
) -> System {
    let source = LayerSource {
        values,
        weights,
        layers: k,
        height: h,
        width: w,
    };
    assemble(
        &source,
        h,
        w,
        PoissonParams::DEFAULT_LAM,
        Target::Given(target),
        None,
    )
}

#[test]
fn multigrid_cg_matches_a_dense_solve_over_several_levels() {
    let (h, w, k) = (32, 64, 3);
    let (values, weights, target) = layered_problem(h, w, k, 13);
    let system = assemble_layers(&values, &weights, &target, k, h, w);
    let mg = Multigrid::build(h, w, &system.right, &system.down, &system.diag);
    assert!(mg.levels() >= 3, "{} levels", mg.levels());
    let params = PoissonParams {
        tolerance: 1e-12,
        ..Default::default()
    };
    let mut out = vec![0.0f64; h * w];
    let report =
        poisson_blend_layers(&values, &weights, &target, h, w, &params, &mut out).expect("solve");
    assert!(report.relative_residual <= 1e-12);
    // The dense reference has x = 0 at the unseen pixels (no edges, no fidelity).
    let t0: Vec<f32> = target
        .iter()
        .map(|t| if t.is_finite() { *t } else { 0.0 })
        .collect();
    let want = dense_solve(&values, &weights, &t0, h, w);
    for (p, (a, b)) in out.iter().zip(&want).enumerate() {
        if target[p].is_finite() {
            assert!((a - b).abs() < 1e-6 * b.abs(), "pixel {p}: {a} vs {b}");
        } else {
            assert!(a.is_nan());
        }
    }
}

#[test]
fn the_v_cycle_is_symmetric_positive_definite_and_cuts_iterations() {
    let (h, w, k) = (64, 128, 3);
    let (values, weights, target) = layered_problem(h, w, k, 17);
    let system = assemble_layers(&values, &weights, &target, k, h, w);
    let mut mg = Multigrid::build(h, w, &system.right, &system.down, &system.diag);
    let n = h * w;
    let mut r = rng(19);
    let (u, v): (Vec<f64>, Vec<f64>) = (0..n).map(|_| (r() - 0.5, r() - 0.5)).unzip();
    let (mut mu, mut mv) = (vec![0.0f32; n], vec![0.0f32; n]);
    let umu = mg.apply(&system.right, &system.down, &u, &mut mu);
    let vmv = mg.apply(&system.right, &system.down, &v, &mut mv);
    let dot = |a: &[f64], b: &[f32]| a.iter().zip(b).map(|(a, b)| a * f64::from(*b)).sum::<f64>();
    let (vmu, umv) = (dot(&v, &mu), dot(&u, &mv));
    assert!(umu > 0.0 && vmv > 0.0);
    assert!(
        (vmu - umv).abs() <= 1e-5 * (umu * vmv).sqrt(),
        "{vmu} vs {umv}"
    );
    // The returned b·z is the dot product of the input with the output.
    assert!((umu - dot(&u, &mu)).abs() <= 1e-9 * umu.abs());
    // An order of magnitude fewer iterations than the Jacobi preconditioner.
    let start: Vec<f64> = target
        .iter()
        .map(|&t| if t.is_finite() { f64::from(t) } else { 0.0 })
        .collect();
    let params = PoissonParams {
        tolerance: 1e-8,
        ..Default::default()
    };
    let (mut x1, mut x2) = (start.clone(), start);
    let (its_mg, res_mg, _) = solve_multigrid(&system, &mut x1, &params).expect("mg");
    let (its_j, res_j, _) = solve_fused(&system, &mut x2, &params).expect("jacobi");
    assert!(res_mg <= 1e-8 && res_j <= 1e-8);
    assert!(
        its_mg * 4 <= its_j,
        "multigrid {its_mg} vs Jacobi {its_j} iterations"
    );
}

#[test]
fn an_odd_width_falls_back_to_jacobi_and_still_matches_the_dense_solve() {
    let (h, w, k) = (6, 13, 2);
    assert!(!Multigrid::supports(h, w));
    let (values, weights, target) = layered_problem(h, w, k, 23);
    let t0: Vec<f32> = target
        .iter()
        .map(|t| if t.is_finite() { *t } else { 0.0 })
        .collect();
    let params = PoissonParams {
        tolerance: 1e-12,
        ..Default::default()
    };
    let mut out = vec![0.0f64; h * w];
    poisson_blend_layers(&values, &weights, &target, h, w, &params, &mut out).expect("solve");
    let want = dense_solve(&values, &weights, &t0, h, w);
    for (p, (a, b)) in out.iter().zip(&want).enumerate() {
        assert!(
            !target[p].is_finite() || (a - b).abs() < 1e-6 * b.abs(),
            "{a} vs {b}"
        );
    }
}

#[test]
fn exact_tangents_come_back_exactly() {
    // Consistent gradients and target: the solution is the target itself (to the tolerance).
    let plan = Plan::new(layout(256));
    let l = plan.layout();
    let (h, w) = l.tangent_shape();
    let tangents: Vec<f32> = l
        .cameras
        .iter()
        .flat_map(|cam| {
            (0..h * w).map(move |p| {
                let d = cam.pixel_direction((p % w) as f64, (p / w) as f64);
                (2.0 + 0.5 * d.x + 0.3 * d.y * d.z) as f32
            })
        })
        .collect();
    let weights = plan.weight_maps(Weighting::Frustum);
    let n = l.erp_height * l.erp_width;
    let (mut mean, mut spread) = (vec![0.0f32; n], vec![0.0f32; n]);
    mean_blend(plan.erp_taps(), l, &tangents, &mut mean, Some(&mut spread));
    let mut out = vec![0.0f32; n];
    let report = poisson_blend(
        plan.erp_taps(),
        l,
        &tangents,
        weights,
        &PoissonParams::default(),
        &mut out,
        Some(&mut spread),
    )
    .expect("solve");
    assert!(report.relative_residual <= 1e-6);
    let worst = out
        .iter()
        .zip(&mean)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 5e-3, "worst {worst}");
}

#[test]
fn poisson_is_the_same_with_one_thread() {
    let plan = Plan::new(layout(256));
    let l = plan.layout();
    let (h, w) = l.tangent_shape();
    let mut r = rng(3);
    let tangents: Vec<f32> = (0..20 * h * w).map(|_| (1.0 + 0.1 * r()) as f32).collect();
    let n = l.erp_height * l.erp_width;
    let run = || {
        let (mut out, mut spread) = (vec![0.0f32; n], vec![0.0f32; n]);
        let p = Plan::new(layout(256));
        poisson_blend(
            p.erp_taps(),
            p.layout(),
            &tangents,
            p.weight_maps(Weighting::Frustum),
            &PoissonParams::default(),
            &mut out,
            Some(&mut spread),
        )
        .expect("solve");
        out
    };
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool")
        .install(run);
    let two = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .expect("pool")
        .install(run);
    assert!(one
        .iter()
        .zip(&two)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
}

// Resampling and the simple blends on a smooth field.

/// A smooth function of direction, so bilinear resampling of it is nearly exact.
fn field(d: &nalgebra::Vector3<f64>) -> f64 {
    2.0 + 0.5 * d.x + 0.3 * d.y * d.z + 0.2 * d.z
}

fn plan(erp_width: usize) -> Plan {
    Plan::new(Layout::icosahedron(erp_width, 0.3, None).expect("layout"))
}

fn tangent_field(plan: &Plan) -> Vec<f32> {
    let layout = plan.layout();
    let (h, w) = layout.tangent_shape();
    let mut t = Vec::with_capacity(layout.cameras.len() * h * w);
    for cam in &layout.cameras {
        for r in 0..h {
            for c in 0..w {
                t.push(field(&cam.pixel_direction(c as f64, r as f64)) as f32);
            }
        }
    }
    t
}

#[test]
fn erp_to_tangents_matches_direct_evaluation() {
    let plan = plan(512);
    let layout = plan.layout();
    let grid = ErpGrid::new(layout.erp_height, layout.erp_width);
    let erp: Vec<f32> = (0..layout.erp_height)
        .flat_map(|i| (0..layout.erp_width).map(move |j| (i, j)))
        .map(|(i, j)| field(&grid.direction(i, j)) as f32)
        .collect();
    let mut got = vec![0.0f32; 20 * layout.tangent_shape().0 * layout.tangent_shape().1];
    erp_to_tangents(plan.tangent_taps(), layout, &erp, 1, &mut got);
    let want = tangent_field(&plan);
    let worst = got
        .iter()
        .zip(&want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 2e-3, "worst error {worst}");
}

#[test]
fn every_direction_is_seen_by_two_to_five_faces() {
    let plan = plan(256);
    let counts = plan.erp_taps().counts();
    assert!(
        counts.iter().all(|&c| (2..=5).contains(&c)),
        "{:?}",
        counts.iter().max()
    );
}

#[test]
fn mean_and_nearest_reproduce_a_smooth_field() {
    let plan = plan(512);
    let layout = plan.layout();
    let grid = ErpGrid::new(layout.erp_height, layout.erp_width);
    let tangents = tangent_field(&plan);
    for mode in [Method::Mean, Method::Nearest] {
        let (disparity, _) = blend_to_vec(&plan, &tangents, mode);
        for (p, &v) in disparity.iter().enumerate() {
            let want = field(&grid.direction(p / layout.erp_width, p % layout.erp_width));
            assert!(
                (f64::from(v) - want).abs() < 2e-3,
                "{mode:?} pixel {p}: {v} vs {want}"
            );
        }
    }
}

#[test]
fn a_nan_neighbour_invalidates_a_sample_and_per_face_maps_agree() {
    let plan = plan(256);
    let layout = plan.layout();
    let mut tangents = tangent_field(&plan);
    let (h, w) = layout.tangent_shape();
    tangents[..h * w].fill(f32::NAN); // face 0 has no estimate at all
    let plane = layout.erp_height * layout.erp_width;
    let mut per_face = vec![0.0f32; 20 * plane];
    tangents_to_erp(
        plan.erp_taps(),
        layout,
        &tangents,
        Sampling::Bilinear,
        &mut per_face,
    );
    assert!(per_face[..plane].iter().all(|v| v.is_nan()));
    assert!(per_face[plane..].iter().any(|v| v.is_finite()));
    let (disparity, _) = blend_to_vec(&plan, &tangents, Method::Nearest);
    assert!(
        disparity.iter().all(|v| v.is_finite()),
        "other faces cover face 0"
    );
}

#[test]
fn parallel_equals_sequential() {
    let plan_a = plan(256);
    let tangents = tangent_field(&plan_a);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    let seq = pool.install(|| {
        let p = self::plan(256);
        blend_to_vec(&p, &tangents, Method::Mean).0
    });
    let par = blend_to_vec(&plan_a, &tangents, Method::Mean).0;
    assert!(seq
        .iter()
        .zip(&par)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
}

// The consensus blend.

/// An independent per-pixel evaluation of the consensus: the frustum weights and samples of each
/// face at an ERP pixel, reweighted as the documentation says, with σ taken from the blend.
fn consensus_at(samples: &[(f32, f32)], sigma: f32) -> f32 {
    let total: f32 = samples.iter().map(|s| s.1).sum();
    let mut m = if total > 0.0 {
        samples.iter().map(|s| s.0 * s.1).sum::<f32>() / total
    } else {
        samples.iter().map(|s| s.0).sum::<f32>() / samples.len() as f32
    };
    for _ in 0..rows::CONSENSUS_ROUNDS {
        let (mut num, mut den) = (0.0f32, 0.0f32);
        for &(v, p) in samples {
            let e = (v - m) / (2.385 * sigma);
            let r = p / (1.0 + e * e);
            num += r * v;
            den += r;
        }
        if den > 0.0 {
            m = num / den;
        }
    }
    m
}

#[test]
fn consensus_matches_a_direct_evaluation_and_votes_down_a_wrong_face() {
    let plan = plan(256);
    let l = plan.layout();
    let (h, w) = l.tangent_shape();
    let mut tangents = tangent_field(&plan);
    // Face 3 is 40 % too high everywhere: a content error its neighbours do not share.
    for v in &mut tangents[3 * h * w..4 * h * w] {
        *v *= 1.4;
    }
    let n = l.erp_height * l.erp_width;
    let (mut out, mut conf) = (vec![0.0f32; n], vec![0.0f32; n]);
    let taps = plan.erp_taps();
    let weights = plan.weight_maps(Weighting::Frustum);
    let sigma = consensus_blend(taps, l, &tangents, weights, &mut out, Some(&mut conf));
    assert!(sigma > 0.0 && sigma.is_finite());
    let (mut values, mut row_weights) = (Vec::new(), Vec::new());
    let (mut checked, mut voted) = (0, 0);
    let mut errors = Vec::new();
    for i in (0..l.erp_height).step_by(7) {
        taps.sample(&tangents, Sampling::DepthEdges, i, &mut values);
        weights.row_into(taps, i, &mut row_weights);
        for j in (0..l.erp_width).step_by(5) {
            let samples: Vec<(f32, f32)> = taps
                .runs(i)
                .iter()
                .filter(|r| r.columns().contains(&j))
                .map(|r| {
                    let t = r.taps().start + (j - r.start as usize);
                    (values[t], row_weights[t])
                })
                .filter(|s| s.0.is_finite())
                .collect();
            let expected = consensus_at(&samples, sigma);
            let got = out[i * l.erp_width + j];
            assert!(
                (got - expected).abs() <= 1e-4 * expected.abs(),
                "({i}, {j}): {got} vs {expected}"
            );
            checked += 1;
            // Where face 3 and at least two others see the pixel, the others win.
            let dir = crate::sphere::lonlat_direction(
                crate::sphere::column_longitude(j as f64, l.erp_width),
                crate::sphere::row_latitude(i as f64, l.erp_height),
            );
            let truth = field(&dir) as f32;
            let faces = taps.runs(i).iter().filter(|r| r.columns().contains(&j));
            if samples.len() >= 3 && faces.clone().any(|r| r.face == 3) {
                let frustum: f32 = samples.iter().map(|s| s.0 * s.1).sum::<f32>()
                    / samples
                        .iter()
                        .map(|s| s.1)
                        .sum::<f32>()
                        .max(f32::MIN_POSITIVE);
                voted += 1;
                errors.push(((got - truth).abs(), (frustum - truth).abs()));
                assert!(conf[i * l.erp_width + j] > 0.0);
            }
        }
    }
    assert!(checked > 500 && voted > 20, "{checked} {voted}");
    let median = |mut v: Vec<f32>| {
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    };
    let consensus_error = median(errors.iter().map(|e| e.0).collect());
    let frustum_error = median(errors.iter().map(|e| e.1).collect());
    assert!(
        consensus_error < 0.25 * frustum_error,
        "consensus {consensus_error}, frustum {frustum_error}"
    );
}

/// The weighted median of `samples` (value, weight): the smallest value whose cumulative weight
/// in increasing order reaches half the total (equal weights if they sum to 0).
fn weighted_median_at(samples: &[(f32, f32)]) -> f32 {
    let mut sorted = samples.to_vec();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: f32 = sorted.iter().map(|s| s.1).sum();
    let equal = total <= 0.0;
    let half = if equal { sorted.len() as f32 } else { total } / 2.0;
    let mut cumulative = 0.0;
    for (v, w) in sorted {
        cumulative += if equal { 1.0 } else { w };
        if cumulative >= half {
            return v;
        }
    }
    f32::NAN
}

#[test]
fn median_matches_a_direct_evaluation_and_ignores_a_wrong_face() {
    let plan = plan(256);
    let l = plan.layout();
    let (h, w) = l.tangent_shape();
    let mut tangents = tangent_field(&plan);
    for v in &mut tangents[3 * h * w..4 * h * w] {
        *v *= 1.4;
    }
    let (out, _) = blend_to_vec(&plan, &tangents, Method::Median);
    let (frustum, _) = blend_to_vec(&plan, &tangents, Method::Frustum);
    let taps = plan.erp_taps();
    let weights = plan.weight_maps(Weighting::Frustum);
    let (mut values, mut row_weights) = (Vec::new(), Vec::new());
    let (mut medians, mut ignored) = (0, 0);
    for i in (0..l.erp_height).step_by(5) {
        taps.sample(&tangents, Sampling::DepthEdges, i, &mut values);
        weights.row_into(taps, i, &mut row_weights);
        for j in (0..l.erp_width).step_by(3) {
            let samples: Vec<(usize, f32, f32)> = taps
                .runs(i)
                .iter()
                .filter(|r| r.columns().contains(&j))
                .map(|r| {
                    let t = r.taps().start + (j - r.start as usize);
                    (r.face as usize, values[t], row_weights[t])
                })
                .filter(|s| s.1.is_finite())
                .collect();
            let got = out[i * l.erp_width + j];
            let pairs: Vec<(f32, f32)> = samples.iter().map(|s| (s.1, s.2)).collect();
            if samples.len() >= 3 {
                assert_eq!(
                    got.to_bits(),
                    weighted_median_at(&pairs).to_bits(),
                    "({i}, {j})"
                );
                medians += 1;
                let wrong = samples.iter().find(|s| s.0 == 3);
                let total: f32 = pairs.iter().map(|s| s.1).sum();
                if let Some(&(_, v, wt)) = wrong {
                    if wt < 0.5 * total {
                        assert!(got.to_bits() != v.to_bits(), "({i}, {j}) took face 3");
                        ignored += 1;
                    }
                }
            } else {
                assert_eq!(got.to_bits(), frustum[i * l.erp_width + j].to_bits());
            }
        }
    }
    assert!(
        medians > 1000 && ignored > 50,
        "{medians} medians, {ignored} ignored"
    );
}

#[test]
fn weights_sampled_at_the_taps_match_the_maps_at_the_projected_positions() {
    // Oracle: for every (ERP pixel, face) pair of a row, project the pixel's direction into
    // the face and interpolate its weight map bilinearly in f64. The taps store positions in
    // fixed point (2^-15 pixel), so the two agree to far better than 1e-4.
    let plan = Plan::new(layout(256));
    let l = plan.layout();
    let (h, w) = l.tangent_shape();
    let grid = crate::sphere::ErpGrid::new(l.erp_height, l.erp_width);
    let taps = plan.erp_taps();
    for kind in [Weighting::Nearest, Weighting::Radial, Weighting::Frustum] {
        let maps = plan.weight_maps(kind);
        let mut row = Vec::new();
        let mut worst = 0.0f64;
        for i in (0..l.erp_height).step_by(3) {
            maps.row_into(taps, i, &mut row);
            for run in taps.runs(i) {
                let face = run.face as usize;
                let cam = &l.cameras[face];
                let map = &maps.maps()[face * h * w..(face + 1) * h * w];
                for (j, t) in run.columns().zip(run.taps()) {
                    let (x, y) = cam.project(&grid.direction(i, j)).expect("seen");
                    let (x0, y0) = (x.floor().max(0.0), y.floor().max(0.0));
                    let (c0, r0) = ((x0 as usize).min(w - 1), (y0 as usize).min(h - 1));
                    let (c1, r1) = ((c0 + 1).min(w - 1), (r0 + 1).min(h - 1));
                    let (fx, fy) = ((x - x0).clamp(0.0, 1.0), (y - y0).clamp(0.0, 1.0));
                    let at = |r: usize, c: usize| f64::from(map[r * w + c]);
                    let want = (1.0 - fy) * ((1.0 - fx) * at(r0, c0) + fx * at(r0, c1))
                        + fy * ((1.0 - fx) * at(r1, c0) + fx * at(r1, c1));
                    worst = worst.max((f64::from(row[t]) - want).abs());
                }
            }
        }
        assert!(worst < 1e-4, "{kind:?}: worst difference {worst}");
    }
}

/// The field on an ERP grid of `height` rows, times `wrong(d)`, as a prior.
fn prior_of_field(
    height: usize,
    wrong: impl Fn(&nalgebra::Vector3<f64>) -> f64,
) -> crate::align::Prior {
    let grid = ErpGrid::new(height, 2 * height);
    let mut values = Vec::with_capacity(2 * height * height);
    for r in 0..height {
        for c in 0..2 * height {
            let d = grid.direction(r, c);
            values.push((field(&d) * wrong(&d)) as f32);
        }
    }
    crate::align::Prior {
        values,
        confidence: None,
        height,
        width: 2 * height,
        absolute: false,
    }
}

/// With the paper's padding most pixels are seen by two faces, where a consensus cannot tell
/// which one is wrong: a right prior picks the right face, and a prior that no face agrees with
/// (a wrong region) changes nothing; without a prior the blend is exactly the consensus.
#[test]
fn the_prior_votes_among_disagreeing_faces_and_not_where_no_face_agrees() {
    let plan = plan(256);
    let l = plan.layout();
    let (h, w) = l.tangent_shape();
    let mut tangents = tangent_field(&plan);
    for v in &mut tangents[3 * h * w..4 * h * w] {
        *v *= 1.4;
    }
    let n = l.erp_height * l.erp_width;
    let (taps, weights) = (plan.erp_taps(), plan.weight_maps(Weighting::Frustum));
    let blend = |prior: Option<&crate::align::Prior>| {
        let mut out = vec![0.0f32; n];
        let vote = prior.map(|prior| PriorVote {
            prior,
            scale: 1.0,
            offset: 0.0,
        });
        consensus_blend_with_prior(taps, l, &tangents, weights, vote.as_ref(), &mut out, None);
        out
    };
    let plain = blend(None);
    let (consensus, _) = blend_to_vec(&plan, &tangents, Method::Consensus);
    assert!(plain
        .iter()
        .zip(&consensus)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    let right = blend(Some(&prior_of_field(64, |_| 1.0)));
    // 2.2 times the truth within 50° of face 3's axis: no face is near it, face 3 (1.4) is
    // nearer than the others; elsewhere a ±5 % wiggle gives the prior's vote its scale.
    let cam = &l.cameras[3];
    let axis = cam.pixel_direction((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let inside = |d: &nalgebra::Vector3<f64>| d.dot(&axis) > 50f64.to_radians().cos();
    let wrong = blend(Some(&prior_of_field(64, |d| {
        if inside(d) {
            2.2
        } else {
            1.0 + 0.05 * (7.0 * d.x + 5.0 * d.y).sin()
        }
    })));
    let grid = ErpGrid::new(l.erp_height, l.erp_width);
    let (mut fixed, mut kept) = (Vec::new(), Vec::new());
    for i in 0..l.erp_height {
        for j in 0..l.erp_width {
            let faces: Vec<u32> = taps
                .runs(i)
                .iter()
                .filter(|r| r.columns().contains(&j))
                .map(|r| r.face)
                .collect();
            if !faces.contains(&3) || faces.len() < 2 {
                continue;
            }
            let d = grid.direction(i, j);
            let truth = field(&d) as f32;
            let k = i * l.erp_width + j;
            // Where the wrong face moved the consensus (elsewhere its frustum weight is ~0).
            if (plain[k] - truth).abs() > 0.01 * truth {
                fixed.push(((right[k] - truth).abs(), (plain[k] - truth).abs()));
                if d.dot(&axis) > 45f64.to_radians().cos() {
                    kept.push((wrong[k] - plain[k]).abs() / plain[k]);
                }
            }
        }
    }
    let median = |mut v: Vec<f32>| {
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    };
    assert!(
        fixed.len() > 200 && kept.len() > 20,
        "{} {}",
        fixed.len(),
        kept.len()
    );
    let with_prior = median(fixed.iter().map(|e| e.0).collect());
    let without = median(fixed.iter().map(|e| e.1).collect());
    assert!(
        with_prior < 0.25 * without,
        "with the prior {with_prior}, without {without}"
    );
    let moved = kept.iter().copied().fold(0.0f32, f32::max);
    assert!(
        moved < 0.02,
        "a prior no face agrees with moved the blend by {moved}"
    );
}

/// The confidence combined with the prior's gap against a direct computation: the prior read
/// bilinearly at each ERP pixel centre (longitude wrapping, rows clamped), √(c² + gap²) where
/// both are known, c kept where the prior or the disparity is unknown, NaN kept.
#[test]
fn the_confidence_combines_the_prior_gap_as_defined() {
    let (hp, wp, eh, ew) = (4usize, 8usize, 6usize, 12usize);
    let mut values: Vec<f32> = (0..hp * wp).map(|i| 1.0 + 0.1 * (i % 7) as f32).collect();
    values[wp + 2] = f32::NAN;
    let prior = crate::align::Prior {
        values,
        confidence: None,
        height: hp,
        width: wp,
        absolute: false,
    };
    let vote = PriorVote {
        prior: &prior,
        scale: 1.5,
        offset: 0.25,
    };
    let disparity: Vec<f32> = (0..eh * ew)
        .map(|i| {
            if i == 7 {
                f32::NAN
            } else {
                2.0 + 0.05 * (i % 11) as f32
            }
        })
        .collect();
    let before: Vec<f32> = (0..eh * ew)
        .map(|i| {
            if i == 30 {
                f32::NAN
            } else {
                0.01 * (i % 5) as f32
            }
        })
        .collect();
    let mut confidence = before.clone();
    combine_confidence_with_prior(&vote, &disparity, &mut confidence, ew);
    let p = |r: usize, c: usize| f64::from(prior.values[r * wp + c % wp]);
    let mut unknown = 0;
    for i in 0..eh {
        let row = ((i as f64 + 0.5) * hp as f64 / eh as f64 - 0.5).clamp(0.0, (hp - 1) as f64);
        let r0 = (row.floor() as usize).min(hp - 2);
        let fy = row - r0 as f64;
        for j in 0..ew {
            let col = ((j as f64 + 0.5) * wp as f64 / ew as f64 - 0.5).rem_euclid(wp as f64);
            let c0 = col.floor() as usize;
            let fx = col - c0 as f64;
            let along = |r: usize| (1.0 - fx) * p(r, c0) + fx * p(r, c0 + 1);
            let at = 1.5 * ((1.0 - fy) * along(r0) + fy * along(r0 + 1)) + 0.25;
            let k = i * ew + j;
            let (c, d) = (f64::from(before[k]), f64::from(disparity[k]));
            let want = if (d - at).is_nan() {
                unknown += 1;
                c
            } else {
                c.hypot(d - at)
            };
            let got = f64::from(confidence[k]);
            assert!(
                (want.is_nan() && got.is_nan()) || (got - want).abs() <= 1e-5 * want.max(1.0),
                "pixel ({i}, {j}): {got} against {want}"
            );
        }
    }
    assert!(
        unknown > 1,
        "the prior's NaN and the disparity's reached pixels"
    );
}

/// The prior's vote on one row, written from its definition (docs/method.md, "Global prior"):
/// each valid sample's weight times max((1 − t) + t/(1 + e²), 1e-3), e = (v − P)·inv_c and t
/// the prior's trust times 1/(1 + (e_min/2)²) with e_min the pixel's nearest sample.
fn prior_vote_by_definition(
    row: &RowSamples,
    prior: &[f32],
    trust: &[f32],
    inv_c: f32,
) -> Vec<f32> {
    let mut nearest = vec![f32::INFINITY; prior.len()];
    for run in &row.runs {
        for (j, k) in run.columns().zip(run.taps()) {
            let e = (row.values[k] - prior[j]) * inv_c;
            if e.is_finite() {
                nearest[j] = nearest[j].min((e / 2.0).abs());
            }
        }
    }
    let mut weights = row.weights.clone();
    for run in &row.runs {
        for (j, k) in run.columns().zip(run.taps()) {
            let e = (row.values[k] - prior[j]) * inv_c;
            let t = trust[j] / (1.0 + nearest[j] * nearest[j]);
            if row.values[k].is_finite() {
                let e2 = if e.is_finite() { e * e } else { 0.0 };
                weights[k] *= ((1.0 - t) + t / (1.0 + e2)).max(1e-3);
            }
        }
    }
    weights
}

#[test]
fn the_prior_vote_is_the_same_on_every_instruction_set_and_as_defined() {
    // Rows of a real plan (several runs per row, up to five faces per pixel), values and the
    // prior random with holes (NaN) in both: the dispatched vote (AVX2 where the CPU has it)
    // against the baseline build's lanes, bit for bit, and against the definition.
    let plan = plan(512);
    let layout = plan.layout();
    let weights = plan.weight_maps(Weighting::Frustum);
    let mut next = rng(7);
    // Values in [1, 2), a share `holes` of them NaN.
    let mut values = |len: usize, holes: f64| -> Vec<f32> {
        (0..len)
            .map(|_| match next() {
                u if u < holes => f32::NAN,
                u => (1.0 + u) as f32,
            })
            .collect()
    };
    let tangents = values(weights.maps().len(), 0.02);
    let ew = layout.erp_width;
    let (mut row, mut checked, mut moved) = (RowSamples::default(), 0usize, 0usize);
    for i in (0..layout.erp_height).step_by(7) {
        row.fill_from_taps(plan.erp_taps(), &tangents, Some(weights), false, i);
        let prior = values(ew, 0.05);
        // Trust in [0, 1) where the prior is known, 0 elsewhere (as `PriorVote::row` gives it).
        let trust: Vec<f32> = prior
            .iter()
            .zip(values(ew, 0.0))
            .map(|(p, t)| if p.is_finite() { t - 1.0 } else { 0.0 })
            .collect();
        let inv_c = 8.0;
        let want = prior_vote_by_definition(&row, &prior, &trust, inv_c);
        let (mut lanes, mut dispatched) = (row.clone(), row.clone());
        let mut scratch = (trust.clone(), vec![0.0; ew]);
        prior_vote_lanes(&mut lanes, &prior, &mut scratch.0, &mut scratch.1, inv_c);
        let mut scratch = (trust.clone(), vec![0.0; ew]);
        prior_vote(
            &mut dispatched,
            &prior,
            &mut scratch.0,
            &mut scratch.1,
            inv_c,
        );
        for (k, (&a, &b)) in lanes.weights.iter().zip(&dispatched.weights).enumerate() {
            assert_eq!(a.to_bits(), b.to_bits(), "row {i} tap {k}: {a} vs {b}");
            if row.values[k].is_finite() {
                let c = want[k];
                assert!(
                    (a - c).abs() <= 1e-5 * c.abs(),
                    "row {i} tap {k}: {a} vs {c}"
                );
                checked += 1;
                moved += usize::from(a < 0.99 * row.weights[k]);
            }
        }
    }
    assert!(checked > 10_000, "{checked} samples checked");
    assert!(
        moved > checked / 10,
        "the vote moved {moved} of {checked} weights"
    );
}
