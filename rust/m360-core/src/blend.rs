//! Blending (paper §3.4, `DESIGN.md` §7): per-face weight maps, weighted blends, and the Poisson
//! gradient-domain blend solved by conjugate gradients preconditioned with a multigrid V-cycle
//! (see [`multigrid`]; Jacobi-preconditioned CG, ours or faer's, on request).
//!
//! Weights live on each tangent's own pixel grid (f32, N·h·w), computed from that face's own
//! intrinsics (reference bug B9 centred one set of weights at a fixed pixel for every face), and
//! are sampled at an ERP pixel with the same bilinear tap as the disparity. No ERP-sized per-face
//! stack is ever built (reference bug B10): the Poisson system is assembled row by row straight
//! from the taps and applied matrix-free.

use crate::camera::TangentCamera;
use crate::error::{CoreError, Result};
use crate::layout::Layout;
use crate::resample::{ErpTaps, Run, TapWeights};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::matrix_free::conjugate_gradient::{
    conjugate_gradient, conjugate_gradient_scratch, CgError, CgParams,
};
use faer::matrix_free::{InitialGuessStatus, LinOp, Precond};
use faer::{MatMut, MatRef, Par};
use rayon::prelude::*;
use std::time::Instant;

mod multigrid;
use multigrid::Multigrid;

/// Radial weights are 1 up to this angle from the optical axis (degrees).
pub const RADIAL_FULL_DEG: f64 = 15.0;
/// Frustum weights reach 1 this fraction of the way along each diagonal from a corner (so the
/// ramp is `FRUSTUM_RAMP`·width wide horizontally and `FRUSTUM_RAMP`·height vertically).
pub const FRUSTUM_RAMP: f64 = 0.3;
/// The paper's fidelity weight λ of the Poisson blend.
pub const POISSON_LAMBDA: f64 = 0.1;
/// Default relative residual ‖Ax − b‖/‖b‖ at which the Poisson solve stops.
pub const POISSON_TOLERANCE: f64 = 1e-6;

/// ERP rows per parallel work item of the Poisson assembly: each item re-samples one row above
/// and one below its own, so larger items waste less, smaller ones balance better.
const ROWS_PER_CHUNK: usize = 16;

/// Which per-face weight map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Weighting {
    /// 1 where this face's axis is the nearest axis to the pixel's ray (for the icosahedron: the
    /// un-padded face triangle), 0 elsewhere.
    Nearest,
    /// 1 everywhere.
    Mean,
    /// 1 within [`RADIAL_FULL_DEG`] of the optical axis, falling linearly to 0 at the image's
    /// inscribed half field of view (the widest cone about the axis that fits in the image).
    Radial,
    /// min(1, d_x / (r·width), d_y / (r·height)) with d the distance to the nearest image border
    /// (pixel edges) and r = [`FRUSTUM_RAMP`]: 1 in the centre, 0 at the border.
    Frustum,
}

/// Frustum weight of continuous pixel position (x, y) of `cam` (0 outside the image).
pub fn frustum_weight(cam: &TangentCamera, x: f64, y: f64) -> f64 {
    let (w, h) = (cam.width as f64, cam.height as f64);
    let dx = (x + 0.5).min(w - 0.5 - x);
    let dy = (y + 0.5).min(h - 0.5 - y);
    (dx / (FRUSTUM_RAMP * w))
        .min(dy / (FRUSTUM_RAMP * h))
        .clamp(0.0, 1.0)
}

/// Half-angle (radians) of the widest cone about the optical axis of `cam` inside its image.
pub fn inscribed_half_fov(cam: &TangentCamera) -> f64 {
    let (w, h) = (cam.width as f64, cam.height as f64);
    // The principal point is off-centre for the icosahedron: the nearest border decides.
    let tan = ((cam.cx + 0.5) / cam.fx)
        .min((w - 0.5 - cam.cx) / cam.fx)
        .min((cam.cy + 0.5) / cam.fy)
        .min((h - 0.5 - cam.cy) / cam.fy);
    tan.max(0.0).atan()
}

/// Radial weight of continuous pixel position (x, y) of `cam`.
pub fn radial_weight(cam: &TangentCamera, x: f64, y: f64) -> f64 {
    let full = RADIAL_FULL_DEG.to_radians();
    let edge = inscribed_half_fov(cam);
    let angle = cam.spherical_factor(x, y).clamp(-1.0, 1.0).acos();
    if angle <= full {
        1.0
    } else if edge <= full {
        0.0
    } else {
        ((edge - angle) / (edge - full)).clamp(0.0, 1.0)
    }
}

/// Weight maps of every face of `layout` (N·h·w, f32, row-major per face).
pub fn weight_maps(layout: &Layout, kind: Weighting) -> Vec<f32> {
    let (h, w) = layout.tangent_shape();
    let axes: Vec<_> = layout.cameras.iter().map(TangentCamera::axis).collect();
    let mut out = vec![0.0f32; layout.cameras.len() * h * w];
    out.par_chunks_mut(w)
        .enumerate()
        .for_each(|(face_row, row)| {
            let k = face_row / h;
            let cam = &layout.cameras[k];
            let r = (face_row % h) as f64;
            for (c, v) in row.iter_mut().enumerate() {
                let x = c as f64;
                *v = match kind {
                    Weighting::Mean => 1.0,
                    Weighting::Frustum => frustum_weight(cam, x, r) as f32,
                    Weighting::Radial => radial_weight(cam, x, r) as f32,
                    Weighting::Nearest => {
                        let d = cam.pixel_direction(x, r);
                        let own = axes[k].dot(&d);
                        // Ties go to the lower index, as the taps' nearness ranks do.
                        let nearest = axes
                            .iter()
                            .enumerate()
                            .all(|(m, a)| m == k || a.dot(&d) < own || (a.dot(&d) == own && k < m));
                        f32::from(u8::from(nearest))
                    }
                };
            }
        });
    out
}

/// One ERP row's samples, face by face: the row's runs and, per tap (in run order), the face's
/// value there (NaN = invalid), its blending weight (none stored: all 1) and its nearness rank
/// at its pixel (0 = nearest axis).
#[derive(Debug, Default)]
pub(crate) struct RowSamples {
    pub runs: Vec<Run>,
    pub values: Vec<f32>,
    pub weights: Vec<f32>,
    pub ranks: Vec<u8>,
}

impl RowSamples {
    /// The samples of ERP row `i` of tangent images through `taps`, with per-tap `weights`,
    /// and with ranks if `ranks` (only the nearest-face statistics need them).
    ///
    /// # Panics
    /// If `tangents` or `weights` do not belong to `taps`.
    pub(crate) fn fill_from_taps(
        &mut self,
        taps: &ErpTaps,
        tangents: &[f32],
        weights: Option<&TapWeights>,
        ranks: bool,
        i: usize,
    ) {
        self.runs.clear();
        self.runs.extend_from_slice(taps.runs(i));
        taps.sample(tangents, i, &mut self.values);
        self.ranks.clear();
        if ranks {
            taps.ranks(i, &mut self.ranks);
        }
        self.weights.clear();
        if let Some(w) = weights {
            assert_eq!(
                w.row(i).len(),
                self.values.len(),
                "tap weights of other taps"
            );
            self.weights.extend_from_slice(w.row(i));
        }
    }

    #[inline(always)]
    fn weight(&self, t: usize) -> f32 {
        if self.weights.is_empty() {
            1.0
        } else {
            self.weights[t]
        }
    }
}

/// Per-pixel statistics of the valid (finite) samples of one ERP row, accumulated run by run;
/// NaN where a pixel has none.
///
/// Sums are kept relative to each pixel's first valid sample (a shift close to the mean), so the
/// spread comes from the same single pass without the cancellation of Σv² − n·mean²; f32 is
/// exact enough for a handful of samples per pixel.
#[derive(Debug, Default)]
pub(crate) struct RowStats {
    extras: Extras,
    count: Vec<f32>,
    shift: Vec<f32>,
    shifted_sum: Vec<f32>,
    shifted_squares: Vec<f32>,
    weight_sum: Vec<f32>,
    weighted_sum: Vec<f32>,
    rank: Vec<u8>,
    /// The sample of the nearest valid face (with [`Extras::nearest`]).
    pub nearest: Vec<f32>,
    /// Unweighted mean.
    pub mean: Vec<f32>,
    /// Σ w·v / Σ w; the plain mean where every valid sample has weight 0 (radial weights vanish
    /// near the icosahedron's vertices, which lie 37.4° from the nearest axes, beyond the 34°
    /// inscribed half field of view).
    pub weighted: Vec<f32>,
    /// Population standard deviation, 0 with one sample (with [`Extras::spread`]).
    pub spread: Vec<f32>,
}

/// What [`RowStats`] computes beyond the mean and the weighted mean.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct Extras {
    /// The nearest valid face's sample (needs ranks).
    pub nearest: bool,
    /// The spread.
    pub spread: bool,
}

impl RowStats {
    /// Start a row `width` pixels wide.
    pub(crate) fn start(&mut self, width: usize, extras: Extras) {
        let reset = |v: &mut Vec<f32>, x: f32| {
            v.clear();
            v.resize(width, x);
        };
        self.extras = extras;
        reset(&mut self.count, 0.0);
        reset(&mut self.shifted_sum, 0.0);
        reset(&mut self.weight_sum, 0.0);
        reset(&mut self.weighted_sum, 0.0);
        // Set by each pixel's first valid sample before it is read.
        self.shift.resize(width, 0.0);
        if extras.spread {
            reset(&mut self.shifted_squares, 0.0);
        }
        if extras.nearest {
            reset(&mut self.nearest, f32::NAN);
            self.rank.clear();
            self.rank.resize(width, u8::MAX);
        }
    }

    /// Add the samples `values` of one run over `columns`, with their blending `weights` (none:
    /// all 1) and nearness `ranks` (read only for [`Extras::nearest`]).
    #[inline(always)]
    pub(crate) fn add_run(
        &mut self,
        columns: std::ops::Range<usize>,
        values: &[f32],
        weights: Option<&[f32]>,
        ranks: impl Iterator<Item = u8>,
    ) {
        match (weights, self.extras.spread) {
            (Some(w), true) => self.add::<true>(columns.clone(), values, w.iter().copied()),
            (Some(w), false) => self.add::<false>(columns.clone(), values, w.iter().copied()),
            (None, true) => self.add::<true>(columns.clone(), values, std::iter::repeat(1.0)),
            (None, false) => self.add::<false>(columns.clone(), values, std::iter::repeat(1.0)),
        }
        if self.extras.nearest {
            let best = self.rank[columns.clone()]
                .iter_mut()
                .zip(&mut self.nearest[columns]);
            for ((rank, nearest), (&v, r)) in best.zip(values.iter().zip(ranks)) {
                // Branch-free: which face is nearest varies from pixel to pixel.
                let nearer = v.is_finite() & (r < *rank);
                *rank = if nearer { r } else { *rank };
                *nearest = if nearer { v } else { *nearest };
            }
        }
    }

    #[inline(always)]
    fn add<const SPREAD: bool>(
        &mut self,
        columns: std::ops::Range<usize>,
        values: &[f32],
        weights: impl Iterator<Item = f32>,
    ) {
        let sums = self.count[columns.clone()]
            .iter_mut()
            .zip(&mut self.shift[columns.clone()])
            .zip(&mut self.shifted_sum[columns.clone()])
            .zip(&mut self.weight_sum[columns.clone()])
            .zip(&mut self.weighted_sum[columns.clone()]);
        let mut squares = if SPREAD {
            self.shifted_squares[columns].iter_mut()
        } else {
            [].iter_mut()
        };
        // Branch-free, so it vectorises: an invalid sample adds zeros.
        for (((((n, shift), sum), wsum), wv), (&v, w)) in sums.zip(values.iter().zip(weights)) {
            let ok = v.is_finite();
            *shift = if ok & (*n == 0.0) { v } else { *shift };
            let d = if ok { v - *shift } else { 0.0 };
            let (v, w) = if ok { (v, w) } else { (0.0, 0.0) };
            *n += f32::from(u8::from(ok));
            *sum += d;
            *wsum += w;
            *wv += w * v;
            if SPREAD {
                if let Some(sq) = squares.next() {
                    *sq += d * d;
                }
            }
        }
    }

    /// The per-pixel results, once every run is added.
    pub(crate) fn finish(&mut self) {
        let width = self.count.len();
        for v in [&mut self.mean, &mut self.weighted] {
            v.clear();
            v.resize(width, f32::NAN);
        }
        let sums = self.count.iter().zip(&self.shift).zip(&self.shifted_sum);
        let weighted = self.weight_sum.iter().zip(&self.weighted_sum);
        let outs = self.mean.iter_mut().zip(self.weighted.iter_mut());
        for ((((&n, &shift), &sum), (&wsum, &wv)), (mean, weighted)) in sums.zip(weighted).zip(outs)
        {
            if n > 0.0 {
                *mean = shift + sum / n;
                *weighted = if wsum > 0.0 { wv / wsum } else { *mean };
            }
        }
        if self.extras.spread {
            self.spread.clear();
            let parts = self
                .count
                .iter()
                .zip(&self.shifted_sum)
                .zip(&self.shifted_squares);
            self.spread.extend(parts.map(|((&n, &sum), &squares)| {
                let mean = sum / n; // NaN where no sample
                (squares / n - mean * mean).max(0.0).sqrt()
            }));
        }
    }

    /// The statistics of a whole row of samples.
    pub(crate) fn compute(&mut self, row: &RowSamples, width: usize, spread: bool) {
        let nearest = !row.ranks.is_empty();
        self.start(width, Extras { nearest, spread });
        let weights = (!row.weights.is_empty()).then_some(&row.weights[..]);
        for run in &row.runs {
            let ranks = row.ranks.get(run.taps()).unwrap_or_default();
            self.add_run(
                run.columns(),
                &row.values[run.taps()],
                weights.map(|w| &w[run.taps()]),
                ranks.iter().copied(),
            );
        }
        self.finish();
    }
}

/// Which statistic of the valid samples a blend outputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Statistic {
    Nearest,
    Mean,
    Weighted,
}

impl RowStats {
    fn get(&self, which: Statistic) -> &[f32] {
        match which {
            Statistic::Nearest => &self.nearest,
            Statistic::Mean => &self.mean,
            Statistic::Weighted => &self.weighted,
        }
    }
}

/// Blend every ERP row of per-tangent maps (N·h·w, NaN = invalid) into `disparity` (H·W) with
/// the statistic `which` of the valid samples, and their spread into `spread` (H·W) if given.
///
/// # Panics
/// If the outputs are not H·W long, or `tangents` or `weights` do not belong to `taps`.
pub(crate) fn blend_rows(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    weights: Option<&TapWeights>,
    which: Statistic,
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) {
    let ew = layout.erp_width;
    assert!(disparity.len() == layout.erp_height * ew);
    assert!(spread.as_ref().is_none_or(|s| s.len() == disparity.len()));
    disparity
        .par_chunks_mut(ew)
        .zip(optional_chunks(spread, ew, layout.erp_height))
        .enumerate()
        .for_each_init(
            || (Vec::new(), RowStats::default()),
            |(buffer, stats), (i, (out, out_spread))| {
                let nearest = which == Statistic::Nearest;
                let spread = out_spread.is_some();
                stats.start(ew, Extras { nearest, spread });
                let row_weights = weights.map(|w| w.row(i));
                taps.sample_runs(tangents, i, buffer, |run, values, ranks| {
                    let run_weights = row_weights.map(|w| &w[run.taps()]);
                    stats.add_run(run.columns(), values, run_weights, ranks);
                });
                stats.finish();
                out.copy_from_slice(stats.get(which));
                if let Some(out_spread) = out_spread {
                    out_spread.copy_from_slice(&stats.spread);
                }
            },
        );
}

/// `count` chunks of `size` of `data`, or `count` Nones: an output that may be skipped, to zip
/// with the chunks of one that may not.
fn optional_chunks(
    data: Option<&mut [f32]>,
    size: usize,
    count: usize,
) -> rayon::vec::IntoIter<Option<&mut [f32]>> {
    let chunks: Vec<Option<&mut [f32]>> = match data {
        Some(d) => d.chunks_mut(size).map(Some).collect(),
        None => (0..count).map(|_| None).collect(),
    };
    chunks.into_par_iter()
}

/// Weighted blend of per-tangent maps (N·h·w, NaN = invalid) with per-face `weights` (at the
/// taps, from [`ErpTaps::weights_of`]): `disparity` (H·W) gets Σ w·v / Σ w over the valid
/// samples (see [`RowStats::weighted`] for the fall-back), `spread` (H·W, if given) the
/// population standard deviation of the valid samples.
///
/// # Panics
/// If the outputs are not H·W long.
pub fn weighted_blend(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    weights: &TapWeights,
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) {
    let which = Statistic::Weighted;
    blend_rows(
        taps,
        layout,
        tangents,
        Some(weights),
        which,
        disparity,
        spread,
    );
}

// ---------------------------------------------------------------------------------------------
// Poisson blend.

/// The image the Poisson solution is held close to (the λ term).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fidelity {
    /// The nearest-face stitch D_NN (the paper's choice).
    Nearest,
    /// The frustum-weighted blend (the same weights as the gradient term).
    Frustum,
    /// The unweighted mean of the valid samples.
    Mean,
}

/// Which conjugate-gradient implementation solves the Poisson system (all matrix-free, f64,
/// deterministic for any thread count).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Solver {
    /// CG preconditioned by a geometric multigrid V-cycle on the ERP grid (f32, red-black
    /// Gauss–Seidel, 2×2 aggregation): about ten iterations at any size instead of about 80.
    /// The default. Grids of odd width fall back to [`Solver::Fused`].
    Multigrid,
    /// Jacobi-preconditioned CG with fused, parallel passes over the grid (three memory sweeps
    /// per iteration and fixed-order reductions).
    Fused,
    /// faer's `conjugate_gradient` with the same operator and the Jacobi preconditioner; faer's
    /// own vector operations run sequentially to stay deterministic.
    Faer,
}

/// Options of the Poisson blend.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoissonParams {
    /// Fidelity weight λ (> 0 keeps the system positive definite).
    pub lambda: f64,
    /// Fidelity target.
    pub fidelity: Fidelity,
    /// Stop when the true relative residual ‖Ax − b‖/‖b‖ is at most this.
    pub tolerance: f64,
    /// Most conjugate-gradient iterations in total.
    pub max_iterations: usize,
    /// The CG implementation.
    pub solver: Solver,
}

impl Default for PoissonParams {
    fn default() -> Self {
        Self {
            lambda: POISSON_LAMBDA,
            fidelity: Fidelity::Frustum,
            tolerance: POISSON_TOLERANCE,
            max_iterations: 2000,
            solver: Solver::Multigrid,
        }
    }
}

/// What the Poisson solve did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoissonReport {
    /// Conjugate-gradient iterations run (over every restart).
    pub iterations: usize,
    /// True relative residual ‖Ax − b‖/‖b‖ of the returned solution, recomputed in f64.
    pub relative_residual: f64,
    /// Relative residual of the warm start.
    pub initial_residual: f64,
    /// Seconds spent assembling the system.
    pub assemble_seconds: f64,
    /// Seconds spent in the solver.
    pub solve_seconds: f64,
    /// Number of unknowns (ERP pixels).
    pub unknowns: usize,
}

/// Something that yields the samples of an ERP row, face by face.
trait RowSource: Sync {
    fn fill(&self, i: usize, out: &mut RowSamples);
}

/// Samples through the plan's taps from tangent images.
struct TapSource<'a> {
    taps: &'a ErpTaps,
    tangents: &'a [f32],
    weights: &'a TapWeights,
    /// Whether the target needs the nearest face.
    ranks: bool,
}

impl RowSource for TapSource<'_> {
    fn fill(&self, i: usize, out: &mut RowSamples) {
        out.fill_from_taps(self.taps, self.tangents, Some(self.weights), self.ranks, i);
    }
}

/// Samples from K maps already on the ERP grid (K·H·W values and weights, NaN = invalid):
/// one full-row run per map, no ranks (the target is given).
struct LayerSource<'a> {
    values: &'a [f32],
    weights: &'a [f32],
    layers: usize,
    height: usize,
    width: usize,
}

impl RowSource for LayerSource<'_> {
    fn fill(&self, i: usize, out: &mut RowSamples) {
        let (plane, w) = (self.height * self.width, self.width);
        out.runs.clear();
        out.values.clear();
        out.weights.clear();
        out.ranks.clear();
        for k in 0..self.layers {
            let row = k * plane + i * w..k * plane + (i + 1) * w;
            out.runs.push(Run {
                face: k as u32,
                start: 0,
                len: w as u32,
                start_tap: (k * w) as u32,
            });
            out.values.extend_from_slice(&self.values[row.clone()]);
            out.weights.extend_from_slice(&self.weights[row]);
        }
    }
}

/// Weight W = Σ ω_a and weighted target gradient G = Σ ω_a·(D_a(q) − D_a(p)) of every edge
/// p → q of one ERP row, over the faces valid at both ends, with ω_a = (ω_a(p) + ω_a(q))/2
/// taken where the forward difference lives, at the edge's midpoint. (Taking ω_a(p) alone
/// would make the operator change when the image is flipped: the poles would no longer be
/// treated alike.)
#[derive(Debug, Default)]
struct RowEdges {
    weight: Vec<f64>,
    gradient: Vec<f64>,
}

impl RowEdges {
    fn reset(&mut self, width: usize) {
        for v in [&mut self.weight, &mut self.gradient] {
            v.clear();
            v.resize(width, 0.0);
        }
    }

    /// Add face term (value p, weight wp) → (value q, weight wq) to the edge at column `j`.
    #[inline(always)]
    fn add(&mut self, j: usize, (p, wp): (f32, f32), (q, wq): (f32, f32)) {
        if p.is_finite() && q.is_finite() {
            let w = 0.5 * (wp as f64 + wq as f64);
            self.weight[j] += w;
            self.gradient[j] += w * (q as f64 - p as f64);
        }
    }

    /// The edges from each pixel of `row` to its right neighbour (column W−1 wraps to 0).
    fn horizontal(&mut self, row: &RowSamples, width: usize) {
        self.reset(width);
        let at = |t: usize| (row.values[t], row.weight(t));
        for run in &row.runs {
            let taps = run.taps();
            for (j, t) in run.columns().zip(taps.clone()).take(taps.len() - 1) {
                self.add(j, at(t), at(t + 1));
            }
            if run.columns().end == width {
                // The run goes on at column 0 of the same row, if the face sees it there.
                let wrap = row.runs.iter().find(|r| r.face == run.face && r.start == 0);
                if let Some(next) = wrap {
                    self.add(width - 1, at(taps.end - 1), at(next.start_tap as usize));
                }
            }
        }
    }

    /// The edges from each pixel of `upper` to the one below it in `lower`.
    fn vertical(&mut self, upper: &RowSamples, lower: &RowSamples, width: usize) {
        self.reset(width);
        for a in &upper.runs {
            for b in lower.runs.iter().filter(|b| b.face == a.face) {
                let (lo, hi) = (a.start.max(b.start), (a.start + a.len).min(b.start + b.len));
                for j in lo..hi {
                    let ta = (a.start_tap + j - a.start) as usize;
                    let tb = (b.start_tap + j - b.start) as usize;
                    self.add(
                        j as usize,
                        (upper.values[ta], upper.weight(ta)),
                        (lower.values[tb], lower.weight(tb)),
                    );
                }
            }
        }
    }
}

fn target_of(stats: &RowStats, j: usize, fidelity: Fidelity) -> f64 {
    f64::from(match fidelity {
        Fidelity::Nearest => stats.nearest[j],
        Fidelity::Frustum => stats.weighted[j],
        Fidelity::Mean => stats.mean[j],
    })
}

/// The assembled normal equations (λ_p I + L_W) x = λ_p t + div G on an H×W ERP grid.
///
/// L_W is the weighted graph Laplacian of the ERP 4-neighbour grid: horizontal edges wrap in
/// longitude (column W−1 → 0), vertical edges join rows i and i+1 and never cross a pole, so
/// rows 0 and H−1 are treated alike (reference bug B7 had a Dirichlet row below the bottom only).
/// Pixels no face sees get the decoupled equation x = 0 and become NaN.
#[derive(Debug)]
struct System {
    height: usize,
    width: usize,
    /// Weight of the edge from each pixel to its right neighbour (wrapping).
    right: Vec<f32>,
    /// Weight of the edge from each pixel to the one below (0 on the last row).
    down: Vec<f32>,
    /// Diagonal λ_p + Σ incident edge weights (1 at unseen pixels).
    diag: Vec<f64>,
    /// Right-hand side.
    rhs: Vec<f64>,
    /// Fidelity target, NaN at unseen pixels.
    target: Vec<f64>,
}

/// Where the fidelity target comes from.
#[derive(Clone, Copy)]
enum Target<'a> {
    /// Computed from each pixel's samples.
    FromSamples(Fidelity),
    /// Given on the ERP grid (H·W, NaN = none).
    Given(&'a [f32]),
}

fn assemble(
    source: &dyn RowSource,
    height: usize,
    width: usize,
    lambda: f64,
    target_spec: Target<'_>,
    spread: Option<&mut [f32]>,
) -> System {
    let n = height * width;
    let mut right = vec![0.0f32; n];
    let mut down = vec![0.0f32; n];
    let mut rhs = vec![0.0f64; n];
    let mut target = vec![0.0f64; n];
    let chunk = ROWS_PER_CHUNK * width;
    right
        .par_chunks_mut(chunk)
        .zip(down.par_chunks_mut(chunk))
        .zip(rhs.par_chunks_mut(chunk))
        .zip(target.par_chunks_mut(chunk))
        .zip(optional_chunks(
            spread,
            chunk,
            height.div_ceil(ROWS_PER_CHUNK),
        ))
        .enumerate()
        .for_each(|(c, ((((right, down), div), target), mut spread))| {
            let i0 = c * ROWS_PER_CHUNK;
            let rows = right.len() / width;
            let (mut cur, mut next) = (RowSamples::default(), RowSamples::default());
            let mut stats = RowStats::default();
            let (mut across, mut below, mut above) = (
                RowEdges::default(),
                RowEdges::default(),
                RowEdges::default(),
            );
            source.fill(i0, &mut cur);
            // Edges entering this row from above (none on row 0).
            above.reset(width);
            if i0 > 0 {
                let mut prev = RowSamples::default();
                source.fill(i0 - 1, &mut prev);
                above.vertical(&prev, &cur, width);
            }
            for r in 0..rows {
                let i = i0 + r;
                across.horizontal(&cur, width);
                if i + 1 < height {
                    source.fill(i + 1, &mut next);
                    below.vertical(&cur, &next, width);
                } else {
                    below.reset(width);
                }
                stats.compute(&cur, width, spread.is_some());
                let row = r * width..(r + 1) * width;
                let (right, down) = (&mut right[row.clone()], &mut down[row.clone()]);
                let (div, target) = (&mut div[row.clone()], &mut target[row.clone()]);
                if let Some(spread) = spread.as_deref_mut() {
                    spread[row.clone()].copy_from_slice(&stats.spread);
                }
                for j in 0..width {
                    right[j] = across.weight[j] as f32;
                    down[j] = below.weight[j] as f32;
                    target[j] = match target_spec {
                        Target::FromSamples(f) => target_of(&stats, j, f),
                        Target::Given(t) => t[i * width + j] as f64,
                    };
                    let left = (j + width - 1) % width;
                    div[j] = across.gradient[left] - across.gradient[j] + above.gradient[j]
                        - below.gradient[j];
                }
                std::mem::swap(&mut above, &mut below);
                std::mem::swap(&mut cur, &mut next);
            }
        });
    // diag and rhs need the left and upper neighbours' edges: a second, cheap pass.
    let mut diag = vec![0.0f64; n];
    diag.par_chunks_mut(width)
        .zip(rhs.par_chunks_mut(width))
        .enumerate()
        .for_each(|(i, (diag, rhs))| {
            let base = i * width;
            for j in 0..width {
                let p = base + j;
                let t = target[p];
                if !t.is_finite() {
                    diag[j] = 1.0;
                    rhs[j] = 0.0;
                    continue;
                }
                let left = base + (j + width - 1) % width;
                let mut d = lambda + right[p] as f64 + right[left] as f64 + down[p] as f64;
                if i > 0 {
                    d += down[p - width] as f64;
                }
                diag[j] = d;
                rhs[j] += lambda * t;
            }
        });
    System {
        height,
        width,
        right,
        down,
        diag,
        rhs,
        target,
    }
}

impl System {
    /// y = A x, parallel over rows (each y element written once: deterministic).
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        let w = self.width;
        y.par_chunks_mut(CG_ROWS * w)
            .enumerate()
            .for_each(|(c, y)| {
                self.apply_rows(x, y, c * CG_ROWS);
            });
    }

    /// Rows `i0..` of y = A x into `y` (whole rows); returns the partial sum of x·y over them.
    /// Whole-row slices with the longitude wrap peeled off, so the loops vectorise.
    #[inline]
    fn apply_rows(&self, x: &[f64], y: &mut [f64], i0: usize) -> f64 {
        let (h, w) = (self.height, self.width);
        let mut dot = 0.0;
        for (r, y) in y.chunks_mut(w).enumerate() {
            let i = i0 + r;
            let row = i * w..(i + 1) * w;
            let (right, diag, xr) = (&self.right[row.clone()], &self.diag[row.clone()], &x[row]);
            if w < 3 {
                for j in 0..w {
                    let (l, rr) = ((j + w - 1) % w, (j + 1) % w);
                    y[j] = diag[j] * xr[j] - right[j] as f64 * xr[rr] - right[l] as f64 * xr[l];
                }
            } else {
                y[0] = diag[0] * xr[0] - right[0] as f64 * xr[1] - right[w - 1] as f64 * xr[w - 1];
                for (((y, (d, xc)), (r, rl)), (xl, xn)) in y[1..w - 1]
                    .iter_mut()
                    .zip(diag[1..w - 1].iter().zip(&xr[1..w - 1]))
                    .zip(right[1..w - 1].iter().zip(&right[..w - 2]))
                    .zip(xr[..w - 2].iter().zip(&xr[2..]))
                {
                    *y = d * xc - *r as f64 * xn - *rl as f64 * xl;
                }
                y[w - 1] = diag[w - 1] * xr[w - 1]
                    - right[w - 1] as f64 * xr[0]
                    - right[w - 2] as f64 * xr[w - 2];
            }
            // Vertical neighbours; no edge across either pole.
            if i + 1 < h {
                let (dn_w, dn_x) = (&self.down[i * w..(i + 1) * w], &x[(i + 1) * w..(i + 2) * w]);
                for ((y, e), v) in y.iter_mut().zip(dn_w).zip(dn_x) {
                    *y -= *e as f64 * v;
                }
            }
            if i > 0 {
                let (up_w, up_x) = (&self.down[(i - 1) * w..i * w], &x[(i - 1) * w..i * w]);
                for ((y, e), v) in y.iter_mut().zip(up_w).zip(up_x) {
                    *y -= *e as f64 * v;
                }
            }
            dot += xr.iter().zip(y.iter()).map(|(x, y)| x * y).sum::<f64>();
        }
        dot
    }

    /// ‖A x − b‖ / ‖b‖ with a fixed-order reduction (row partial sums added in row order).
    /// A x exists only one row at a time: no grid-sized scratch.
    fn relative_residual(&self, x: &[f64]) -> f64 {
        let w = self.width;
        let (r, n) = ordered_sum2((0..self.height).into_par_iter().map_init(
            || vec![0.0f64; w],
            |ax, i| {
                self.apply_rows(x, ax, i);
                ax.iter()
                    .zip(&self.rhs[i * w..(i + 1) * w])
                    .fold((0.0, 0.0), |(r, n), (a, b)| {
                        (r + (a - b) * (a - b), n + b * b)
                    })
            },
        ));
        if n == 0.0 {
            r.sqrt()
        } else {
            (r / n).sqrt()
        }
    }
}

/// Copy of column 0 of `m` as a contiguous slice (borrowed when it already is one).
fn column(m: MatRef<'_, f64>) -> std::borrow::Cow<'_, [f64]> {
    match m.col(0).try_as_col_major() {
        Some(c) => std::borrow::Cow::Borrowed(c.as_slice()),
        None => std::borrow::Cow::Owned(m.col(0).iter().copied().collect()),
    }
}

fn write_column(mut out: MatMut<'_, f64>, f: impl FnOnce(&mut [f64])) {
    if let Some(c) = out.as_mut().col_mut(0).try_as_col_major_mut() {
        f(c.as_slice_mut());
    } else {
        let mut tmp = vec![0.0; out.nrows()];
        f(&mut tmp);
        for (i, v) in tmp.into_iter().enumerate() {
            out[(i, 0)] = v;
        }
    }
}

/// The system matrix as a faer operator, applied matrix-free (5 non-zeros per row are never
/// stored: 4 bytes of weight per edge instead of ~60 bytes of CSR per pixel).
impl LinOp<f64> for System {
    fn apply_scratch(&self, _rhs_ncols: usize, _par: Par) -> faer::dyn_stack::StackReq {
        faer::dyn_stack::StackReq::EMPTY
    }
    fn nrows(&self) -> usize {
        self.diag.len()
    }
    fn ncols(&self) -> usize {
        self.diag.len()
    }
    fn apply(&self, out: MatMut<'_, f64>, rhs: MatRef<'_, f64>, _par: Par, _: &mut MemStack) {
        debug_assert_eq!(rhs.ncols(), 1);
        let x = column(rhs);
        write_column(out, |y| System::apply(self, &x, y));
    }
    fn conj_apply(&self, out: MatMut<'_, f64>, rhs: MatRef<'_, f64>, par: Par, s: &mut MemStack) {
        LinOp::apply(self, out, rhs, par, s);
    }
}

/// Jacobi (diagonal) preconditioner: with λ = 0.1 the system is well conditioned, and scaling
/// by the diagonal evens out the 1–5-fold overlap of the faces.
#[derive(Debug)]
struct Jacobi<'a>(&'a [f64]);

impl Jacobi<'_> {
    fn scale(&self, x: &[f64], y: &mut [f64]) {
        y.par_chunks_mut(1 << 14)
            .zip(x.par_chunks(1 << 14))
            .zip(self.0.par_chunks(1 << 14))
            .for_each(|((y, x), d)| {
                for ((y, x), d) in y.iter_mut().zip(x).zip(d) {
                    *y = x / d;
                }
            });
    }
}

impl LinOp<f64> for Jacobi<'_> {
    fn apply_scratch(&self, _rhs_ncols: usize, _par: Par) -> faer::dyn_stack::StackReq {
        faer::dyn_stack::StackReq::EMPTY
    }
    fn nrows(&self) -> usize {
        self.0.len()
    }
    fn ncols(&self) -> usize {
        self.0.len()
    }
    fn apply(&self, out: MatMut<'_, f64>, rhs: MatRef<'_, f64>, _par: Par, _: &mut MemStack) {
        let x = column(rhs);
        write_column(out, |y| self.scale(&x, y));
    }
    fn conj_apply(&self, out: MatMut<'_, f64>, rhs: MatRef<'_, f64>, par: Par, s: &mut MemStack) {
        LinOp::apply(self, out, rhs, par, s);
    }
}

impl Precond<f64> for Jacobi<'_> {
    fn apply_in_place_scratch(&self, _rhs_ncols: usize, _par: Par) -> faer::dyn_stack::StackReq {
        faer::dyn_stack::StackReq::EMPTY
    }
    fn apply_in_place(&self, rhs: MatMut<'_, f64>, _par: Par, _: &mut MemStack) {
        write_column(rhs, |y| {
            y.par_chunks_mut(1 << 14)
                .zip(self.0.par_chunks(1 << 14))
                .for_each(|(y, d)| y.iter_mut().zip(d).for_each(|(y, d)| *y /= d));
        });
    }
    fn conj_apply_in_place(&self, rhs: MatMut<'_, f64>, par: Par, s: &mut MemStack) {
        self.apply_in_place(rhs, par, s);
    }
}

/// Solve the system by Jacobi-preconditioned conjugate gradients (faer), warm-started from `x`.
///
/// faer's own vector operations run with `Par::Seq`: its parallel dot products split by thread
/// count, which would make the result depend on it; the operator and the preconditioner (most
/// of the work) run on the rayon pool with per-element writes, so the solve is bit-identical for
/// any number of threads. faer's recursive residual drifts from the true one, so the true
/// relative residual is recomputed and the solve restarted from its own result while it is above
/// the tolerance.
fn solve_faer(system: &System, x: &mut [f64], params: &PoissonParams) -> Result<(usize, f64, f64)> {
    let n = x.len();
    let par = Par::Seq;
    let precond = Jacobi(&system.diag);
    let initial = system.relative_residual(x);
    let mut residual = initial;
    let mut iterations = 0usize;
    let mut buffer = MemBuffer::new(conjugate_gradient_scratch(&precond, system, 1, par));
    // At most a few restarts: each one starts from a residual CG has already reduced.
    for _ in 0..8 {
        if residual <= params.tolerance || iterations >= params.max_iterations {
            break;
        }
        let cg = CgParams {
            initial_guess: InitialGuessStatus::MaybeNonZero,
            // Aim a little below the target so the true residual usually passes first time.
            rel_tolerance: params.tolerance * 0.5,
            max_iters: params.max_iterations - iterations,
            ..Default::default()
        };
        let stack = MemStack::new(&mut buffer);
        let out = MatMut::from_column_major_slice_mut(x, n, 1);
        let rhs = MatRef::from_column_major_slice(&system.rhs, n, 1);
        match conjugate_gradient(out, &precond, system, rhs, cg, |_| {}, par, stack) {
            Ok(info) => iterations += info.iter_count.max(1),
            Err(CgError::NoConvergence { .. }) => iterations = params.max_iterations,
            Err(e) => {
                return Err(CoreError::Solver(format!(
                    "conjugate gradient failed on the Poisson system: {e:?}"
                )))
            }
        }
        residual = system.relative_residual(x);
    }
    finish(residual, iterations, initial, params)
}

/// Rows per work item of the fused CG passes; partial sums are kept per item and added in item
/// order, so the reductions do not depend on the number of threads.
const CG_ROWS: usize = 8;

/// Jacobi-preconditioned CG written as three fused sweeps per iteration:
/// 1. `Ap = A p` and the partial sums of `pᵀAp`;
/// 2. `x += α p`, `r −= α Ap`, and the partial sums of `rᵀz` (z = r / diag) and `rᵀr`;
/// 3. `p = z + β p`.
///
/// faer's CG makes about seven separate passes over the vectors per iteration; on this
/// memory-bound problem the fused form measured about twice as fast. The stopping test uses the
/// recursive residual; the true residual is recomputed afterwards and the solve restarted from
/// its own result if that drifted above the tolerance.
fn solve_fused(
    system: &System,
    x: &mut [f64],
    params: &PoissonParams,
) -> Result<(usize, f64, f64)> {
    let n = x.len();
    let w = system.width;
    let chunk = CG_ROWS * w;
    // The preconditioner as a product: two divisions per pixel per iteration cost as much as
    // the memory traffic of a whole sweep.
    let inv_diag: Vec<f64> = system.diag.par_iter().map(|d| 1.0 / d).collect();
    let diag = &inv_diag;
    let b = &system.rhs;
    let b_norm = ordered_sum(b.par_chunks(chunk).map(|c| c.iter().map(|v| v * v).sum())).sqrt();
    let initial = system.relative_residual(x);
    if b_norm == 0.0 {
        x.fill(0.0);
        return Ok((0, 0.0, initial));
    }
    let mut r = vec![0.0f64; n];
    let mut p = vec![0.0f64; n];
    let mut ap = vec![0.0f64; n];
    let mut iterations = 0usize;
    let mut residual = initial;
    for _ in 0..8 {
        if residual <= params.tolerance || iterations >= params.max_iterations {
            break;
        }
        // r = b − A x, p = z = r / diag.
        system.apply(x, &mut r);
        let mut rz = ordered_sum(
            r.par_chunks_mut(chunk)
                .zip(p.par_chunks_mut(chunk))
                .zip(b.par_chunks(chunk))
                .zip(diag.par_chunks(chunk))
                .map(|(((r, p), b), d)| {
                    let mut s = 0.0;
                    for (((r, p), b), d) in r.iter_mut().zip(p.iter_mut()).zip(b).zip(d) {
                        *r = b - *r;
                        *p = *r * d;
                        s += *r * *p;
                    }
                    s
                }),
        );
        // A little below the target: the recursive residual drifts slightly from the true one.
        let threshold = 0.8 * params.tolerance * b_norm;
        while iterations < params.max_iterations {
            let pap = ordered_sum(
                ap.par_chunks_mut(chunk)
                    .enumerate()
                    .map(|(c, ap)| system.apply_rows(&p, ap, c * CG_ROWS)),
            );
            if !(pap > 0.0 && pap.is_finite()) {
                return Err(CoreError::Solver(format!(
                    "the Poisson system is not positive definite (pᵀAp = {pap:e})"
                )));
            }
            let alpha = rz / pap;
            let (rz_new, rr) = ordered_sum2(
                x.par_chunks_mut(chunk)
                    .zip(r.par_chunks_mut(chunk))
                    .zip(p.par_chunks(chunk))
                    .zip(ap.par_chunks(chunk))
                    .zip(diag.par_chunks(chunk))
                    .map(|((((x, r), p), ap), d)| {
                        let (mut rz, mut rr) = (0.0, 0.0);
                        for ((((x, r), p), ap), d) in
                            x.iter_mut().zip(r.iter_mut()).zip(p).zip(ap).zip(d)
                        {
                            *x += alpha * p;
                            *r -= alpha * ap;
                            let r2 = *r * *r;
                            rz += r2 * d;
                            rr += r2;
                        }
                        (rz, rr)
                    }),
            );
            iterations += 1;
            if rr.sqrt() <= threshold {
                break;
            }
            let beta = rz_new / rz;
            rz = rz_new;
            p.par_chunks_mut(chunk)
                .zip(r.par_chunks(chunk))
                .zip(diag.par_chunks(chunk))
                .for_each(|((p, r), d)| {
                    for ((p, r), d) in p.iter_mut().zip(r).zip(d) {
                        *p = r * d + beta * *p;
                    }
                });
        }
        residual = system.relative_residual(x);
    }
    finish(residual, iterations, initial, params)
}

/// Sum of per-chunk partial sums in chunk order (deterministic for any thread count).
fn ordered_sum(parts: impl IndexedParallelIterator<Item = f64>) -> f64 {
    parts.collect::<Vec<f64>>().iter().sum()
}

fn ordered_sum2(parts: impl IndexedParallelIterator<Item = (f64, f64)>) -> (f64, f64) {
    parts
        .collect::<Vec<(f64, f64)>>()
        .iter()
        .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1))
}

fn finish(
    residual: f64,
    iterations: usize,
    initial: f64,
    params: &PoissonParams,
) -> Result<(usize, f64, f64)> {
    if !(residual.is_finite() && residual <= params.tolerance) {
        return Err(CoreError::Solver(format!(
            "the Poisson blend did not converge: relative residual {residual:.3e} after \
             {iterations} iterations (tolerance {:.1e}); raise max_iterations or the tolerance",
            params.tolerance
        )));
    }
    Ok((iterations, residual, initial))
}

/// CG preconditioned by one multigrid V-cycle per iteration (see [`multigrid`]), with the
/// same fused f64 passes and restarts as [`solve_fused`]; z = M r is kept in f32.
fn solve_multigrid(
    system: &System,
    x: &mut [f64],
    params: &PoissonParams,
) -> Result<(usize, f64, f64)> {
    let (h, w) = (system.height, system.width);
    if !Multigrid::supports(h, w) {
        return solve_fused(system, x, params);
    }
    let n = x.len();
    let chunk = CG_ROWS * w;
    let b = &system.rhs;
    let b_norm = ordered_sum(b.par_chunks(chunk).map(|c| c.iter().map(|v| v * v).sum())).sqrt();
    let initial = system.relative_residual(x);
    if b_norm == 0.0 {
        x.fill(0.0);
        return Ok((0, 0.0, initial));
    }
    let mut mg = Multigrid::build(h, w, &system.right, &system.down, &system.diag);
    let (right, down) = (&system.right[..], &system.down[..]);
    let mut r = vec![0.0f64; n];
    let mut p = vec![0.0f64; n];
    let mut ap = vec![0.0f64; n];
    let mut z = vec![0.0f32; n];
    let mut iterations = 0usize;
    let mut residual = initial;
    for _ in 0..8 {
        if residual <= params.tolerance || iterations >= params.max_iterations {
            break;
        }
        system.apply(x, &mut r);
        r.par_chunks_mut(chunk)
            .zip(b.par_chunks(chunk))
            .for_each(|(r, b)| r.iter_mut().zip(b).for_each(|(r, b)| *r = b - *r));
        let mut rz = mg.apply(right, down, &r, &mut z);
        p.par_iter_mut()
            .zip(z.par_iter())
            .for_each(|(p, &z)| *p = z as f64);
        let threshold = 0.8 * params.tolerance * b_norm;
        while iterations < params.max_iterations {
            let pap = ordered_sum(
                ap.par_chunks_mut(chunk)
                    .enumerate()
                    .map(|(c, ap)| system.apply_rows(&p, ap, c * CG_ROWS)),
            );
            if !(pap > 0.0 && pap.is_finite() && rz > 0.0) {
                return Err(CoreError::Solver(format!(
                    "the preconditioned Poisson system is not positive definite (pᵀAp = {pap:e}, \
                     rᵀz = {rz:e})"
                )));
            }
            let alpha = rz / pap;
            let rr = ordered_sum(
                x.par_chunks_mut(chunk)
                    .zip(r.par_chunks_mut(chunk))
                    .zip(p.par_chunks(chunk))
                    .zip(ap.par_chunks(chunk))
                    .map(|(((x, r), p), ap)| {
                        let mut rr = 0.0;
                        for (((x, r), p), ap) in x.iter_mut().zip(r.iter_mut()).zip(p).zip(ap) {
                            *x += alpha * p;
                            *r -= alpha * ap;
                            rr += *r * *r;
                        }
                        rr
                    }),
            );
            iterations += 1;
            if rr.sqrt() <= threshold {
                break;
            }
            let rz_new = mg.apply(right, down, &r, &mut z);
            let beta = rz_new / rz;
            rz = rz_new;
            p.par_chunks_mut(chunk)
                .zip(z.par_chunks(chunk))
                .for_each(|(p, z)| {
                    for (p, &z) in p.iter_mut().zip(z) {
                        *p = z as f64 + beta * *p;
                    }
                });
        }
        residual = system.relative_residual(x);
    }
    finish(residual, iterations, initial, params)
}

fn solve(system: &System, x: &mut [f64], params: &PoissonParams) -> Result<(usize, f64, f64)> {
    match params.solver {
        Solver::Multigrid => solve_multigrid(system, x, params),
        Solver::Fused => solve_fused(system, x, params),
        Solver::Faer => solve_faer(system, x, params),
    }
}

fn solve_assembled(
    system: System,
    params: &PoissonParams,
    assemble_seconds: f64,
    out: &mut [f32],
    out_f64: Option<&mut [f64]>,
) -> Result<PoissonReport> {
    let t0 = Instant::now();
    let mut x: Vec<f64> = system
        .target
        .par_iter()
        .map(|&t| if t.is_finite() { t } else { 0.0 })
        .collect();
    let (iterations, relative_residual, initial_residual) = solve(&system, &mut x, params)?;
    out.par_iter_mut()
        .zip(x.par_iter())
        .zip(system.target.par_iter())
        .for_each(|((o, &v), t)| *o = if t.is_finite() { v as f32 } else { f32::NAN });
    if let Some(o) = out_f64 {
        o.par_iter_mut()
            .zip(x.par_iter())
            .zip(system.target.par_iter())
            .for_each(|((o, &v), t)| *o = if t.is_finite() { v } else { f64::NAN });
    }
    Ok(PoissonReport {
        iterations,
        relative_residual,
        initial_residual,
        assemble_seconds,
        solve_seconds: t0.elapsed().as_secs_f64(),
        unknowns: x.len(),
    })
}

fn check_params(params: &PoissonParams) -> Result<()> {
    if !(params.lambda.is_finite() && params.lambda > 0.0) {
        return Err(CoreError::InvalidOption(format!(
            "Poisson fidelity weight lambda={} must be finite and > 0",
            params.lambda
        )));
    }
    if !(params.tolerance.is_finite() && params.tolerance > 0.0 && params.tolerance < 1.0) {
        return Err(CoreError::InvalidOption(format!(
            "Poisson tolerance {} must be in (0, 1)",
            params.tolerance
        )));
    }
    Ok(())
}

/// Poisson blend of per-tangent maps (N·h·w, NaN = invalid) through the plan's taps, with
/// per-face gradient weights `weights` (the frustum maps): minimises
/// Σ_a Σ_x ω_a(x)‖∇B(x) − ∇D_a(x)‖² + λ Σ_x (B(x) − T(x))² with T the fidelity target.
/// `disparity` (H·W) gets B (NaN where no face is valid), `spread` (if given) the overlap
/// disagreement.
///
/// ∇ is the forward difference on the ERP grid; for the edge x → x' the face term is
/// ω̄_a·((B(x') − B(x)) − (D_a(x') − D_a(x)))² with ω̄_a = (ω_a(x) + ω_a(x'))/2, counted for the
/// faces valid at both ends.
pub fn poisson_blend(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    weights: &TapWeights,
    params: &PoissonParams,
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) -> Result<PoissonReport> {
    check_params(params)?;
    let t0 = Instant::now();
    let source = TapSource {
        taps,
        tangents,
        weights,
        ranks: params.fidelity == Fidelity::Nearest,
    };
    let (h, w) = (layout.erp_height, layout.erp_width);
    let system = assemble(
        &source,
        h,
        w,
        params.lambda,
        Target::FromSamples(params.fidelity),
        spread,
    );
    let assemble_seconds = t0.elapsed().as_secs_f64();
    solve_assembled(system, params, assemble_seconds, disparity, None)
}

/// The same Poisson blend for K maps already on an H×W ERP grid: `values` and `weights` are
/// K·H·W (NaN value = invalid), `target` H·W is the fidelity image (NaN = no fidelity and no
/// unknown there, allowed only where no layer is valid; `params.fidelity` is ignored).
/// Returns B in f64 (NaN where `target` is NaN).
pub fn poisson_blend_layers(
    values: &[f32],
    weights: &[f32],
    target: &[f32],
    height: usize,
    width: usize,
    params: &PoissonParams,
    out: &mut [f64],
) -> Result<PoissonReport> {
    check_params(params)?;
    let n = height * width;
    if n == 0
        || !values.len().is_multiple_of(n)
        || weights.len() != values.len()
        || target.len() != n
    {
        return Err(CoreError::ShapeMismatch {
            what: "Poisson layers",
            expected: vec![values.len() / n.max(1), height, width],
            actual: vec![values.len(), weights.len(), target.len()],
        });
    }
    let k = values.len() / n;
    let orphan =
        (0..n).find(|&p| !target[p].is_finite() && (0..k).any(|l| values[l * n + p].is_finite()));
    if let Some(p) = orphan {
        return Err(CoreError::InvalidOption(format!(
            "the Poisson target is NaN at pixel (row {}, column {}) where a layer is valid",
            p / width,
            p % width
        )));
    }
    let t0 = Instant::now();
    let source = LayerSource {
        values,
        weights,
        layers: k,
        height,
        width,
    };
    let system = assemble(
        &source,
        height,
        width,
        params.lambda,
        Target::Given(target),
        None,
    );
    let assemble_seconds = t0.elapsed().as_secs_f64();
    let mut scratch = vec![0.0f32; n];
    solve_assembled(system, params, assemble_seconds, &mut scratch, Some(out))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::Plan;

    fn layout(erp_width: usize) -> Layout {
        Layout::icosahedron(erp_width, 0.3, None).expect("layout")
    }

    #[test]
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
        let mid = (15.0 + edge.to_degrees()) / 2.0;
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
        let maps = weight_maps(plan.layout(), Weighting::Nearest);
        let ones = vec![1.0f32; maps.len()];
        let tap_weights = plan.erp_taps().weights_of(&maps);
        let (mut total, mut exact) = (0usize, 0usize);
        let (mut row, mut sums) = (RowSamples::default(), Vec::new());
        for i in 0..plan.layout().erp_height {
            row.fill_from_taps(plan.erp_taps(), &ones, Some(&tap_weights), false, i);
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
    fn dense_solve(
        values: &[f32],
        weights: &[f32],
        target: &[f32],
        h: usize,
        w: usize,
    ) -> Vec<f64> {
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
                let wgt = 0.5 * (weights[l * n + p] as f64 + weights[l * n + q] as f64);
                let g = vq as f64 - vp as f64;
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
            a[p * n + p] += POISSON_LAMBDA;
            b[p] += POISSON_LAMBDA * target[p] as f64;
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
        let report = poisson_blend_layers(&values, &weights, &target, h, w, &params, &mut out)
            .expect("solve");
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
        for solver in [Solver::Fused, Solver::Faer, Solver::Multigrid] {
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
        assemble(&source, h, w, POISSON_LAMBDA, Target::Given(target), None)
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
        let report = poisson_blend_layers(&values, &weights, &target, h, w, &params, &mut out)
            .expect("solve");
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
        let dot = |a: &[f64], b: &[f32]| a.iter().zip(b).map(|(a, b)| a * *b as f64).sum::<f64>();
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
            .map(|&t| if t.is_finite() { t as f64 } else { 0.0 })
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
        let weights = plan.tap_weights(Weighting::Frustum);
        let n = l.erp_height * l.erp_width;
        let (mut mean, mut spread) = (vec![0.0f32; n], vec![0.0f32; n]);
        crate::stitch::blend(
            plan.erp_taps(),
            l,
            &tangents,
            crate::stitch::Blend::Mean,
            &mut mean,
            Some(&mut spread),
        );
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
                p.tap_weights(Weighting::Frustum),
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

    /// On-CPU seconds of all threads of this process (Linux), steadier than wall time on a busy
    /// machine.
    fn cpu_seconds() -> f64 {
        let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
            return f64::NAN;
        };
        tasks
            .filter_map(|t| std::fs::read_to_string(t.ok()?.path().join("schedstat")).ok())
            .filter_map(|s| s.split_whitespace().next()?.parse::<f64>().ok())
            .sum::<f64>()
            * 1e-9
    }

    /// Three random layers (values near 1, weights in [0, 1)) and a target on an h x w grid:
    /// the input of the timing tests below.
    fn random_layers(h: usize, w: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let n = h * w;
        let mut r = rng(5);
        let values: Vec<f32> = (0..3 * n).map(|_| (1.0 + 0.01 * r()) as f32).collect();
        let weights: Vec<f32> = (0..3 * n).map(|_| r() as f32).collect();
        let target: Vec<f32> = (0..n).map(|_| (1.0 + 0.01 * r()) as f32).collect();
        (values, weights, target)
    }

    /// Median on-CPU seconds of the tap walks at 2K (weighted and plain blends, Poisson assembly);
    /// run with `cargo test --release -- --ignored --nocapture tap_walks`.
    #[test]
    #[ignore = "timing, not a check"]
    fn tap_walks_at_2k() {
        let width = std::env::var("M360_TAP_WIDTH").map_or(2048, |v| v.parse().expect("width"));
        let plan = Plan::new(layout(width));
        let l = plan.layout();
        let (h, w) = l.tangent_shape();
        let mut r = rng(9);
        let tangents: Vec<f32> = (0..20 * h * w).map(|_| (1.0 + 0.1 * r()) as f32).collect();
        let weights = plan.tap_weights(Weighting::Frustum);
        let n = l.erp_height * l.erp_width;
        let (mut out, mut spread) = (vec![0.0f32; n], vec![0.0f32; n]);
        // On-CPU seconds of all threads: steadier than wall time on a shared machine.
        let median = |f: &mut dyn FnMut()| {
            let mut t: Vec<f64> = (0..9)
                .map(|_| {
                    let t0 = cpu_seconds();
                    f();
                    cpu_seconds() - t0
                })
                .collect();
            t.sort_by(f64::total_cmp);
            t[4]
        };
        let t_frustum = median(&mut || {
            weighted_blend(
                plan.erp_taps(),
                l,
                &tangents,
                weights,
                &mut out,
                Some(&mut spread),
            )
        });
        let t_mean = median(&mut || {
            crate::stitch::blend(
                plan.erp_taps(),
                l,
                &tangents,
                crate::stitch::Blend::Mean,
                &mut out,
                Some(&mut spread),
            )
        });
        let source = TapSource {
            taps: plan.erp_taps(),
            tangents: &tangents,
            weights,
            ranks: false,
        };
        let t_assemble = median(&mut || {
            let s = assemble(
                &source,
                l.erp_height,
                l.erp_width,
                0.1,
                Target::FromSamples(Fidelity::Frustum),
                Some(&mut spread),
            );
            assert_eq!(s.rhs.len(), n);
        });
        let runs: usize = (0..l.erp_height)
            .map(|i| plan.erp_taps().runs(i).len())
            .sum();
        eprintln!("{} taps in {runs} runs", plan.erp_taps().len());
        let t_sample = median(&mut || {
            (0..l.erp_height)
                .into_par_iter()
                .for_each_init(Vec::new, |buf, i| {
                    plan.erp_taps().sample(&tangents, i, buf);
                })
        });
        let t_fill = median(&mut || {
            (0..l.erp_height)
                .into_par_iter()
                .for_each_init(RowSamples::default, |row, i| {
                    row.fill_from_taps(plan.erp_taps(), &tangents, Some(weights), false, i);
                })
        });
        let mut rows: Vec<RowSamples> = (0..l.erp_height)
            .map(|i| {
                let mut row = RowSamples::default();
                row.fill_from_taps(plan.erp_taps(), &tangents, Some(weights), false, i);
                row
            })
            .collect();
        let t_stats = median(&mut || {
            rows.par_iter_mut()
                .for_each_init(RowStats::default, |stats, row| {
                    stats.compute(row, l.erp_width, true);
                })
        });
        eprintln!(
            "frustum {t_frustum:.4} s, mean {t_mean:.4} s, assemble {t_assemble:.4} s, \
             sampling alone {t_sample:.4} s, fill {t_fill:.4} s, stats {t_stats:.4} s"
        );
    }

    /// Times the pieces of the multigrid-preconditioned solve at 2K in on-CPU seconds (all
    /// threads); run with `RAYON_NUM_THREADS=1 cargo test --release -- --ignored --nocapture
    /// multigrid_pieces`.
    #[test]
    #[ignore = "timing, not a check"]
    fn multigrid_pieces_at_2k() {
        let (h, w) = (1024, 2048);
        let n = h * w;
        let (values, weights, target) = random_layers(h, w);
        let source = LayerSource {
            values: &values,
            weights: &weights,
            layers: 3,
            height: h,
            width: w,
        };
        let time = |f: &mut dyn FnMut()| {
            let t = cpu_seconds();
            f();
            cpu_seconds() - t
        };
        let mut system = None;
        let t_assemble = time(&mut || {
            system = Some(assemble(
                &source,
                h,
                w,
                POISSON_LAMBDA,
                Target::Given(&target),
                None,
            ));
        });
        let system = system.expect("assembled");
        let mut mg = None;
        let t_build = time(&mut || {
            mg = Some(Multigrid::build(
                h,
                w,
                &system.right,
                &system.down,
                &system.diag,
            ));
        });
        let mut mg = mg.expect("built");
        let mut z = vec![0.0f32; n];
        let mut y = vec![0.0f64; n];
        let reps = 10;
        let t_v = time(&mut || {
            for _ in 0..reps {
                mg.apply(&system.right, &system.down, &system.rhs, &mut z);
            }
        }) / reps as f64;
        let t_a = time(&mut || {
            for _ in 0..reps {
                system.apply(&system.rhs, &mut y);
            }
        }) / reps as f64;
        let mut x: Vec<f64> = target.iter().map(|&t| t as f64).collect();
        let (mut its, mut res) = (0, 0.0);
        let t_mg = time(&mut || {
            (its, res, _) =
                solve_multigrid(&system, &mut x, &PoissonParams::default()).expect("mg");
        });
        let mut x: Vec<f64> = target.iter().map(|&t| t as f64).collect();
        let (mut its_j, mut res_j) = (0, 0.0);
        let t_j = time(&mut || {
            (its_j, res_j, _) =
                solve_fused(&system, &mut x, &PoissonParams::default()).expect("cg");
        });
        println!(
            "2K, CPU s: assemble {t_assemble:.3}, MG build {t_build:.3} ({} \
             levels), V-cycle {t_v:.4}, A·x {t_a:.4}; MG-CG {its} it {t_mg:.3} res {res:.1e}; \
             Jacobi-CG {its_j} it {t_j:.3} res {res_j:.1e}",
            mg.levels()
        );
    }

    /// Measures faer's sparse Cholesky (AMD ordering, supernodal) on the 2K system against the
    /// fused CG; run with `cargo test --release -- --ignored --nocapture cholesky`.
    #[test]
    #[ignore = "timing, not a check"]
    fn cholesky_versus_cg_at_2k() {
        use faer::linalg::solvers::Solve;
        use faer::sparse::{SparseColMat, Triplet};
        let (h, w) = (1024, 2048);
        let n = h * w;
        let (values, weights, target) = random_layers(h, w);
        let system = assemble_layers(&values, &weights, &target, 3, h, w);
        let t0 = Instant::now();
        let mut triplets = Vec::with_capacity(3 * n);
        for p in 0..n {
            let (i, j) = (p / w, p % w);
            triplets.push(Triplet::new(p, p, system.diag[p]));
            let right = i * w + (j + 1) % w;
            triplets.push(Triplet::new(
                p.max(right),
                p.min(right),
                -(system.right[p] as f64),
            ));
            if i + 1 < h {
                triplets.push(Triplet::new(p + w, p, -(system.down[p] as f64)));
            }
        }
        let a = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &triplets).expect("csc");
        let t_build = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let llt = a.sp_cholesky(faer::Side::Lower).expect("llt");
        let t_factor = t1.elapsed().as_secs_f64();
        let t2 = Instant::now();
        let x = llt.solve(MatRef::from_column_major_slice(&system.rhs, n, 1));
        let t_solve = t2.elapsed().as_secs_f64();
        let xs: Vec<f64> = (0..n).map(|p| x[(p, 0)]).collect();
        let t3 = Instant::now();
        let mut y: Vec<f64> = target.iter().map(|&t| t as f64).collect();
        let (its, res, _) = solve_fused(&system, &mut y, &PoissonParams::default()).expect("cg");
        let t_cg = t3.elapsed().as_secs_f64();
        println!(
            "2K: CSC build {t_build:.2}s, symbolic+numeric Cholesky {t_factor:.2}s, solve \
             {t_solve:.2}s, residual {:.1e}; fused CG {its} it {t_cg:.2}s residual {res:.1e}",
            system.relative_residual(&xs)
        );
    }
}
