//! Global deformable alignment of per-tangent disparity (paper §3.3; docs/method.md, "Alignment").
//!
//! Each tangent a gets grids of scale s and offset o (nodes on the image corners, bilinear in
//! between) so that D̃_a = s·D_a + o agrees with its neighbours where they overlap. The energy is
//! a data term over sampled overlap pairs, a smoothness term over grid edges and a 1/s term that
//! keeps the scales from collapsing; [`Energy::Paper`] is the paper's formula literally,
//! [`Energy::Normalized`] the well-posed variant whose terms do not depend on the grid size.
//!
//! Unknowns are laid out node-interleaved: `x[2·node] = s`, `x[2·node + 1] = o`, with
//! `node = tangent·(cols·rows) + row·cols + col`, so the (s, o) pair of a node is one 2×2 block
//! of the Hessian.

use crate::error::{CoreError, Result};
use crate::layout::Layout;
use crate::options::{check_iterations, check_positive, check_range, choice, MAX_POLE_CAP_DEG};
use crate::sphere::direction_to_pixel;
use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, Mat, MatMut, Par, Side, Spec};
use pattern::{Couplings, Pattern};
use rayon::prelude::*;
use std::ops::Range;
use std::sync::{Arc, Mutex, PoisonError};

mod pattern;
mod prior;
mod transform;
use prior::{Consensus, Fusion};
pub use prior::{Prior, PriorFit, PriorSamples, TRUSTED_SPREAD, UNTRUSTED_SPREAD};
pub use transform::MapValues;
use transform::{FactorTable, Transform, Transformed};

/// Which energy to minimise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Energy {
    /// Resolution-independent (the default): the data term averaged over samples, the
    /// smoothness a discrete Dirichlet energy ∫|∇s|² + |∇o|² per tangent (edges weighted by
    /// their aspect), the scale term a mean of 1/s over the nodes. Refining the grid does not
    /// change the balance.
    Normalized,
    /// The paper literally: (1/z_a) Σ r² + λ_s/(N·m·n) Σ_edges (Δs² + Δo²) + λ_c Σ 1/s.
    Paper,
}

choice!(
    Energy,
    "energy",
    [(Energy::Normalized, "normalized"), (Energy::Paper, "paper")]
);

impl Energy {
    /// Default (smoothness, scale_weight) term weights. The paper's are λ_s = 40, λ_c = 0.007;
    /// the normalized energy's were chosen by measurement on synthetic rooms
    /// (benches/bench_align.py).
    #[must_use]
    pub fn default_weights(self) -> (f64, f64) {
        match self {
            Self::Normalized => (1.0, 0.01),
            Self::Paper => (40.0, 0.007),
        }
    }

    /// Default data-term loss: Cauchy for the normalized energy (content errors of one tangent
    /// measured to halve the AbsRel, benches/bench_align.py), least squares for the paper's.
    #[must_use]
    pub fn default_loss(self) -> Loss {
        match self {
            Self::Normalized => Loss::Cauchy,
            Self::Paper => Loss::Squared,
        }
    }

    /// Default offset space: perspective for the normalized energy, the paper's spherical.
    #[must_use]
    pub fn default_offsets(self) -> Offsets {
        match self {
            Self::Normalized => Offsets::Perspective,
            Self::Paper => Offsets::Spherical,
        }
    }

    /// The (cols, rows) grids of `align="multiscale"`, coarse to fine. The paper's energy gets
    /// the paper's 4x3 → 8x7 → 16x14. With the normalized energy a third 16x14 level buys
    /// little on synthetic rooms (median AbsRel 0.023 → 0.021 over 2K–8K in
    /// benches/bench_align.py) for about twice the alignment time (its Newton system has 8,960
    /// unknowns with heavy fill from overlapping tangents), so the default stops at 8x7.
    #[must_use]
    pub fn default_schedule(self) -> &'static [(usize, usize)] {
        match self {
            Self::Normalized => &[(4, 3), (8, 7)],
            Self::Paper => &[(4, 3), (8, 7), (16, 14)],
        }
    }
}

/// In which disparity the per-tangent offset o acts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Offsets {
    /// D̃ = s·D + o/|q| — the offset acts on perspective disparity, where a network's affine
    /// ambiguity lives (spherical = perspective/|q|), so a per-tangent affine error of the
    /// network is exactly a constant (s, o) field.
    Perspective,
    /// D̃ = s·D + o on spherical disparity, as the paper writes it.
    Spherical,
}

choice!(
    Offsets,
    "offsets",
    [
        (Offsets::Perspective, "perspective"),
        (Offsets::Spherical, "spherical"),
    ]
);

/// The loss on each overlap residual of the data term.
///
/// A robust loss is minimised by iteratively reweighted least squares: after each solve every
/// sample gets the weight ψ(r)/r of its residual r, with the residuals' scale σ = 1.4826·median|r|
/// (the MAD, robust to up to half the samples being wrong), and the level is solved again from
/// where it stands, [`ROBUST_ROUNDS`] times. A content error of one tangent (a region the network
/// got too near or too far, which its neighbours do not share) then stops pulling the grids of
/// its neighbours: its samples' weights fall towards 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Loss {
    /// Cauchy: ρ(r) = c²/2·ln(1 + (r/c)²), weight 1/(1 + (r/c)²), c = 2.385·σ (95 % efficiency
    /// on gaussian residuals); outliers lose their pull entirely. The normalized energy's default.
    Cauchy,
    /// Huber: quadratic up to k = 1.345·σ, linear beyond, weight min(1, k/|r|); outliers keep a
    /// bounded pull.
    Huber,
    /// Plain least squares r², as the paper (the paper energy's default).
    Squared,
}

choice!(
    Loss,
    "loss",
    [
        (Loss::Cauchy, "cauchy"),
        (Loss::Huber, "huber"),
        (Loss::Squared, "squared"),
    ]
);

/// Whether the prior is first moved towards the tangents' own low frequencies where they agree
/// with each other well enough (`PriorSamples::fused` in `align/prior.rs`; docs/method.md, "The
/// tangents' own low frequencies").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PriorFusion {
    /// By the tangents' measured spread: in full where they agree to 0.4 %, not at all where
    /// they disagree by 1.2 % or more (every real network measured so far).
    Auto,
    /// Never: the prior's low frequencies are taken as they are (a prior known to be more
    /// accurate than any tangent, such as a LiDAR scan).
    Off,
}

choice!(
    PriorFusion,
    "prior_fusion",
    [(PriorFusion::Auto, "auto"), (PriorFusion::Off, "off")]
);

/// Reweighting rounds of a robust loss per level (each a full solve, warm-started): measured on
/// synthetic rooms with content errors (benches/bench_align.py), the weights settle by the third.
pub const ROBUST_ROUNDS: usize = 3;
/// Robust rounds of a level with the prior where its consensus is deep (`DEEP_CONSENSUS`).
/// Its samples carry the robustness there: their consensus weights judge the prior against every
/// tangent, the schedule's first level (without the prior) has had its [`ROBUST_ROUNDS`], and
/// the prior-only level judges once more. On the 4 rooms of `benches/bench_prior.py` (default
/// layout, 2K / 4K), 3, 2 and 1 rounds gave the same content errors (0.0124 / 0.0124) and affine
/// errors (0.0097 / 0.0090, 0.0089, 0.0089), the wrong prior 0.0274 / 0.0258, 0.0275 / 0.0261,
/// 0.0280 / 0.0262 (no prior: 0.0282 / 0.0251); the 12 real 1K photos gained as much from a
/// real prior with 1 as with 3. A round costs about 14 ms at any resolution.
pub const PRIOR_ROBUST_ROUNDS: usize = 1;
/// Other tangents that see a prior sample's direction, on average, for its consensus to stand in
/// for the robust rounds: 4.6 on the default layout, 2.8 on the paper's padding, where one round
/// let a wrong prior through (`tests/test_prior.py`: 0.0025 without a prior, 0.0032 with 3
/// rounds, 0.0033 with 2, 0.0046 with 1). The once-subdivided icosahedron (80 tangents) sees
/// them 10.3 deep, and there one round and three gave the same medians on the 4 rooms of
/// `benches/bench_prior.py` at 2K (content errors 0.0112 both, affine 0.0098 both, the wrong
/// prior 0.0128 against 0.0126; no prior 0.0196).
const DEEP_CONSENSUS: f64 = 3.5;

/// Residual scale floor of the prior term (standardised units: the prior's mean absolute
/// deviation is 1): disagreements within 1 % of the prior's spread are its resampling, not
/// an error to outvote.
const MIN_PRIOR_SCALE: f64 = 1e-2;

/// Residual scale floor (standardised units): exact tangents have residuals near rounding, and a
/// scale of 0 would weigh every sample 0.
const MIN_ROBUST_SCALE: f64 = 1e-4;

impl Loss {
    /// IRLS weight of residual `r` at residual scale `sigma` (> 0).
    #[inline]
    #[must_use]
    pub fn weight(self, r: f64, sigma: f64) -> f64 {
        match self {
            Self::Cauchy => {
                let u = r / (2.385 * sigma);
                1.0 / (1.0 + u * u)
            }
            Self::Huber => {
                let k = 1.345 * sigma;
                if r.abs() <= k {
                    1.0
                } else {
                    k / r.abs()
                }
            }
            Self::Squared => 1.0,
        }
    }
}

/// Weights and shape of one alignment level.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LevelParams {
    /// Grid nodes per tangent, horizontally (m ≥ 2).
    pub cols: usize,
    /// Grid nodes per tangent, vertically (n ≥ 2).
    pub rows: usize,
    /// Which energy.
    pub energy: Energy,
    /// Weight of the smoothness term (paper: 40).
    pub smoothness: f64,
    /// Weight of the 1/s term (paper: 0.007).
    pub scale_weight: f64,
    /// Where the offset acts.
    pub offsets: Offsets,
}

impl LevelParams {
    /// Grid cells per tangent.
    #[must_use]
    pub fn cells(&self) -> usize {
        (self.cols - 1) * (self.rows - 1)
    }
}

/// Which solver.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Solver {
    /// Newton's method with the exact Hessian, factorised by faer's sparse Cholesky (the
    /// default: converges in a few steps).
    Newton,
    /// Limited-memory BFGS with a backtracking Armijo line search (the paper's choice).
    Lbfgs,
}

choice!(
    Solver,
    "solver",
    [(Solver::Newton, "newton"), (Solver::Lbfgs, "lbfgs")]
);

impl Solver {
    /// Iteration cap per level when none is given: Newton converges long before its cap;
    /// L-BFGS stops after the paper's 50.
    #[must_use]
    pub fn default_iterations(self) -> usize {
        match self {
            Self::Newton => 100,
            Self::Lbfgs => 50,
        }
    }
}

/// How a level's solve ended.
#[derive(Debug, Clone, PartialEq)]
pub struct SolveReport {
    /// Iterations taken.
    pub iterations: usize,
    /// Energy at the start (identity fields) and at the end.
    pub initial_energy: f64,
    /// Energy at the end.
    pub energy: f64,
    /// Max-norm of the gradient at the end.
    pub gradient_norm: f64,
    /// Whether the gradient criterion held at the end.
    pub converged: bool,
    /// Number of overlap samples used.
    pub samples: usize,
}

/// Overlap samples of a layout: pixel `pa` of tangent `a` lands at (xb, yb) in tangent `b > a`.
///
/// A deterministic pseudo-random `fraction` of the pixels of each tangent is kept (a hash of
/// tangent and pixel index), so the same layout and options always give the same samples.
/// Tangents larger than [`SAMPLE_BUDGET_PIXELS`] keep `fraction` of that many pixels: the
/// number of samples per overlapping pair, and so the alignment's cost, stops growing with the
/// resolution (the unknowns do not grow either).
#[derive(Debug, Clone, Default)]
pub struct Overlaps {
    a: Vec<u16>,
    b: Vec<u16>,
    pa: Vec<u32>,
    xb: Vec<f32>,
    yb: Vec<f32>,
}

/// Tangent pixels whose `fraction` is the sample budget of larger tangents: those of the
/// paper's layout at ERP width 2048 (400 × 346), so up to that size nothing changes.
pub const SAMPLE_BUDGET_PIXELS: usize = 400 * 346;

impl Overlaps {
    /// Samples of `layout` keeping `fraction` of the pixels, excluding directions within
    /// `pole_cap_deg` degrees of either pole.
    #[must_use]
    pub fn build(layout: &Layout, fraction: f64, pole_cap_deg: f64) -> Self {
        let (h, w) = layout.tangent_shape();
        let budget = (SAMPLE_BUDGET_PIXELS as f64 / (h * w) as f64).min(1.0);
        let threshold = (fraction.clamp(0.0, 1.0) * budget * u64::MAX as f64) as u64;
        let max_abs_lat = (90.0 - pole_cap_deg).to_radians();
        let (eh, ew) = (layout.erp_height, layout.erp_width);
        let per_face: Vec<Overlaps> = (0..layout.cameras.len())
            .into_par_iter()
            .map(|a| {
                let cam_a = &layout.cameras[a];
                let mut out = Overlaps::default();
                for p in 0..h * w {
                    if splitmix64(((a as u64) << 32) | p as u64) > threshold {
                        continue;
                    }
                    let d = cam_a.pixel_direction((p % w) as f64, (p / w) as f64);
                    if pole_cap_deg > 0.0 {
                        let (_, row) = direction_to_pixel(&d, eh, ew);
                        let lat = std::f64::consts::FRAC_PI_2
                            - std::f64::consts::PI * (row + 0.5) / eh as f64;
                        if lat.abs() > max_abs_lat {
                            continue;
                        }
                    }
                    for (b, cam_b) in layout.cameras.iter().enumerate().skip(a + 1) {
                        if let Some((x, y)) = cam_b.project(&d) {
                            if cam_b.contains(x, y) {
                                out.a.push(a as u16);
                                out.b.push(b as u16);
                                out.pa.push(p as u32);
                                out.xb.push(x.clamp(0.0, (w - 1) as f64) as f32);
                                out.yb.push(y.clamp(0.0, (h - 1) as f64) as f32);
                            }
                        }
                    }
                }
                out
            })
            .collect();
        let mut all = Overlaps::default();
        for part in per_face {
            all.a.extend(part.a);
            all.b.extend(part.b);
            all.pa.extend(part.pa);
            all.xb.extend(part.xb);
            all.yb.extend(part.yb);
        }
        all
    }

    /// (a, b, pa, xb, yb): what a plan file stores (see [`crate::plan_cache`]).
    pub(crate) fn parts(&self) -> [&[u8]; 5] {
        [
            bytemuck::cast_slice(&self.a),
            bytemuck::cast_slice(&self.b),
            bytemuck::cast_slice(&self.pa),
            bytemuck::cast_slice(&self.xb),
            bytemuck::cast_slice(&self.yb),
        ]
    }

    /// Samples from the arrays of [`Overlaps::parts`]; the caller has checked them.
    pub(crate) fn from_parts(
        a: Vec<u16>,
        b: Vec<u16>,
        pa: Vec<u32>,
        xb: Vec<f32>,
        yb: Vec<f32>,
    ) -> Self {
        Self { a, b, pa, xb, yb }
    }

    /// Number of samples.
    #[must_use]
    pub fn len(&self) -> usize {
        self.a.len()
    }

    /// Sample k: (tangent a, pixel index in a, tangent b).
    #[must_use]
    pub fn sample(&self, k: usize) -> (usize, usize, usize) {
        (self.a[k] as usize, self.pa[k] as usize, self.b[k] as usize)
    }

    /// Whether there are no samples.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.a.is_empty()
    }
}

#[cfg(test)]
mod sample_budget_tests {
    use super::*;

    /// Up to the budget's tangent size the samples are `fraction` of the overlap pixels; beyond
    /// it their number stays that of the budget, whatever the resolution.
    #[test]
    fn samples_per_pair_stop_growing_with_the_resolution() {
        let count = |erp: usize| {
            let layout = Layout::icosahedron(erp, 0.3, None).expect("layout");
            let (h, w) = layout.tangent_shape();
            (Overlaps::build(&layout, 0.01, 0.0).len(), h * w)
        };
        let (small, small_pixels) = count(1024);
        let (reference, reference_pixels) = count(2048);
        let (large, _) = count(4096);
        assert_eq!(reference_pixels, SAMPLE_BUDGET_PIXELS);
        // Below the budget: a fixed fraction of the pixels, so about 4x from 1K to 2K.
        let ratio = reference as f64 / small as f64;
        let expected = reference_pixels as f64 / small_pixels as f64;
        assert!(
            (ratio / expected - 1.0).abs() < 0.05,
            "{ratio} vs {expected}"
        );
        // Above it: the same number within sampling noise.
        let ratio = large as f64 / reference as f64;
        assert!(
            (ratio - 1.0).abs() < 0.03,
            "{large} samples at 4K, {reference} at 2K"
        );
    }
}

/// A well-mixed 64-bit hash (SplitMix64 finaliser): deterministic sampling without an RNG.
fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Median and mean absolute deviation from it of the finite values; None if there are none.
///
/// The median is the element of rank ⌊len/2⌋ in `f32::total_cmp` order, found by a radix
/// select: a histogram of the top 16 bits of the order-preserving keys picks the bin holding
/// that rank, and only the bin's values are partially sorted.
fn median_and_spread(values: &[f32]) -> Option<(f64, f64)> {
    // The key of total_cmp order: flip all bits of negatives, only the sign bit of positives.
    let key = |v: f32| {
        let bits = v.to_bits();
        bits ^ (((bits as i32) >> 31) as u32 | 0x8000_0000)
    };
    let mut histogram = vec![0u32; 1 << 16];
    let mut count = 0usize;
    for &v in values.iter().filter(|v| v.is_finite()) {
        histogram[(key(v) >> 16) as usize] += 1;
        count += 1;
    }
    if count == 0 {
        return None;
    }
    let mut rank = count / 2;
    let mut bin = 0;
    while rank >= histogram[bin] as usize {
        rank -= histogram[bin] as usize;
        bin += 1;
    }
    let mut in_bin: Vec<f32> = values
        .iter()
        .copied()
        .filter(|&v| v.is_finite() && (key(v) >> 16) as usize == bin)
        .collect();
    let (_, &mut median, _) = in_bin.select_nth_unstable_by(rank, f32::total_cmp);
    let median = f64::from(median);
    let spread = values
        .iter()
        .filter(|v| v.is_finite())
        .map(|&v| (f64::from(v) - median).abs())
        .sum::<f64>()
        / count as f64;
    Some((median, spread))
}

/// The factor multiplying the offset at tangent pixel (x, y) of `cam`: 1/|q| for perspective
/// offsets, 1 for spherical ones.
#[inline]
fn offset_factor(offsets: Offsets, cam: &crate::TangentCamera, x: f64, y: f64) -> f64 {
    match offsets {
        Offsets::Spherical => 1.0,
        Offsets::Perspective => cam.spherical_factor(x, y),
    }
}

/// [`standardize`] takes its statistics on every k-th tangent row, k = ⌊h / this⌋ (see there).
const STANDARDIZE_ROWS: usize = 400;

/// Standardise each tangent in place to (d − median)/mean|d − median| over its finite values,
/// measured in the space where offsets act (`offsets`: perspective values are d·|q|), so that
/// standardising is itself one of the affine maps the alignment can represent.
/// Returns the (median, spread) used per tangent. A constant tangent (zero spread: a network
/// that failed on a featureless tile) is only shifted to median 0 (its spread is returned as 0):
/// its
/// disagreement with its neighbours is left to the robust loss and the blend, not an error.
///
/// # Errors
/// [`CoreError::Degenerate`] naming a tangent without finite values.
pub fn standardize(layout: &Layout, maps: &mut [f32], offsets: Offsets) -> Result<Vec<(f64, f64)>> {
    let mut transform = Transform::new(layout, offsets);
    let stats = standardize_stats(layout, maps, transform.factors())?;
    transform.standardize(stats.clone());
    transform.apply(maps);
    Ok(stats)
}

/// The (median, spread) per tangent [`standardize`] uses, without applying them.
fn standardize_stats(
    layout: &Layout,
    maps: &[f32],
    factors: &FactorTable,
) -> Result<Vec<(f64, f64)>> {
    let (h, w) = layout.tangent_shape();
    // The statistics read every k-th row, k = ⌊h / STANDARDIZE_ROWS⌋ (every row up to 4K): they
    // only set the units, and reading every row of an 8K tangent stack cost more than a level's
    // solve.
    let row_stride = (h / STANDARDIZE_ROWS).max(1);
    let stats: Vec<Option<(f64, f64)>> = maps
        .par_chunks(h * w)
        .enumerate()
        .map(|(t, map)| {
            let mut f_row = vec![0.0; w];
            let mut values = Vec::with_capacity(h.div_ceil(row_stride) * w);
            for (y, row) in map.chunks_exact(w).enumerate().step_by(row_stride) {
                factors.row(t, y, &mut f_row);
                values.extend(
                    row.iter()
                        .zip(&f_row)
                        .map(|(&v, f)| (f64::from(v) / f) as f32),
                );
            }
            median_and_spread(&values)
        })
        .collect();
    let mut out = Vec::with_capacity(stats.len());
    for (t, s) in stats.into_iter().enumerate() {
        match s {
            Some((m, spread)) if spread > 0.0 && spread.is_finite() => out.push((m, spread)),
            Some((m, _)) => out.push((m, 0.0)),
            None => {
                return Err(CoreError::Degenerate(format!(
                    "tangent {t} has no valid pixel (all NaN or masked)"
                )))
            }
        }
    }
    Ok(out)
}

/// Bilinear weights of the top-left, top-right, bottom-left and bottom-right corners.
#[inline]
fn bilinear_weights(fx: f64, fy: f64) -> [f64; 4] {
    [
        (1.0 - fx) * (1.0 - fy),
        fx * (1.0 - fy),
        (1.0 - fx) * fy,
        fx * fy,
    ]
}

/// Bilinear node weights of a continuous pixel position in a `cols`×`rows` grid spanning an
/// image of `w`×`h` pixels: the top-left node (col, row) and the fractions.
#[inline]
fn grid_cell(
    x: f64,
    y: f64,
    w: usize,
    h: usize,
    cols: usize,
    rows: usize,
) -> (usize, usize, f64, f64) {
    let gx = x / (w - 1) as f64 * (cols - 1) as f64;
    let gy = y / (h - 1) as f64 * (rows - 1) as f64;
    let c0 = (gx.max(0.0) as usize).min(cols - 2);
    let r0 = (gy.max(0.0) as usize).min(rows - 2);
    (c0, r0, gx - c0 as f64, gy - r0 as f64)
}

/// One valid overlap sample, compactly: its residual is
/// r = Σ_j wa_j·(da·s + fa·o)(a-node j) − Σ_j wb_j·(db·s + fb·o)(b-node j) with wa, wb the
/// bilinear weights of the fractions in the a-cell and the b-cell.
#[derive(Debug, Clone, Copy)]
struct Sample {
    /// Top-left grid node of the a-cell and of the b-cell.
    node_a: u32,
    node_b: u32,
    /// Fractions (x, y) within the a-cell and the b-cell.
    frac_a: [f64; 2],
    frac_b: [f64; 2],
    /// Disparity and offset factor in a (at the pixel) and in b (bilinear).
    da: f64,
    fa: f64,
    db: f64,
    fb: f64,
}

impl Sample {
    /// The 8 nodes: a's cell corners (top-left, top-right, bottom-left, bottom-right), then b's.
    #[inline]
    fn nodes(&self, cols: usize) -> [u32; 8] {
        let (a, b, c) = (self.node_a, self.node_b, cols as u32);
        [a, a + 1, a + c, a + c + 1, b, b + 1, b + c, b + c + 1]
    }

    /// Residual coefficients on the 8 nodes' s and on their o.
    #[inline]
    fn coefficients(&self) -> ([f64; 8], [f64; 8]) {
        let wa = bilinear_weights(self.frac_a[0], self.frac_a[1]);
        let wb = bilinear_weights(self.frac_b[0], self.frac_b[1]);
        let mut coef_s = [0.0; 8];
        let mut coef_o = [0.0; 8];
        for j in 0..4 {
            coef_s[j] = wa[j] * self.da;
            coef_o[j] = wa[j] * self.fa;
            coef_s[4 + j] = -wb[j] * self.db;
            coef_o[4 + j] = -wb[j] * self.fb;
        }
        (coef_s, coef_o)
    }
}

/// One prior sample: its residual is r = Σ_j w_j·(d·s + f·o)(node j) − (α·p + β), with w the
/// bilinear weights of the fractions in the tangent's cell and (α, β) the prior node.
#[derive(Debug, Clone, Copy)]
struct PriorSample {
    /// Top-left grid node of the cell.
    node: u32,
    /// Fractions (x, y) within the cell.
    frac: [f64; 2],
    /// Tangent disparity (low-passed) and offset factor at the pixel.
    d: f64,
    f: f64,
    /// Standardised prior value.
    p: f64,
}

impl PriorSample {
    /// The 5 nodes: the cell's corners, then the prior node.
    #[inline]
    fn nodes(&self, cols: usize, prior_node: u32) -> [u32; 5] {
        let (a, c) = (self.node, cols as u32);
        [a, a + 1, a + c, a + c + 1, prior_node]
    }

    /// Residual coefficients on the 5 nodes' first (s, α) and second (o, β) unknowns.
    #[inline]
    fn coefficients(&self) -> ([f64; 5], [f64; 5]) {
        let w = bilinear_weights(self.frac[0], self.frac[1]);
        (
            [
                w[0] * self.d,
                w[1] * self.d,
                w[2] * self.d,
                w[3] * self.d,
                -self.p,
            ],
            [
                w[0] * self.f,
                w[1] * self.f,
                w[2] * self.f,
                w[3] * self.f,
                -1.0,
            ],
        )
    }
}

/// Another tangent's view of a prior sample's direction: its cell, fractions, disparity and
/// offset factor there (for the consensus that judges the prior, not in the energy).
#[derive(Debug, Clone, Copy)]
struct PriorView {
    node: u32,
    frac: [f64; 2],
    d: f64,
    f: f64,
}

/// The prior term of a level: λ/K · Σ_k c_k·ω_k·r_k² over its K samples, with c the prior's
/// confidence and ω the IRLS weight (Cauchy, its own residual scale).
#[derive(Debug, Clone)]
struct PriorTerm {
    samples: Vec<PriorSample>,
    /// Index of each sample in the [`PriorSamples`] it came from (those its tangent has no value
    /// at are left out).
    source: Vec<u32>,
    /// Sample k's views by the other tangents: `views[view_start[k]..view_start[k + 1]]`.
    view_start: Vec<u32>,
    /// Trust-grid cell of each sample ([`prior::TRUST_ROWS`]).
    cell: Vec<u32>,
    views: Vec<PriorView>,
    /// Confidence of each sample.
    confidence: Vec<f64>,
    /// IRLS weight of each sample (1 until reweighted).
    weights: Vec<f64>,
    /// λ/K.
    scale: f64,
    /// Index of the (α, β) node.
    node: u32,
}

impl PriorTerm {
    fn residual(&self, k: usize, x: &[f64], cols: usize) -> f64 {
        let sample = &self.samples[k];
        let nd = sample.nodes(cols, self.node);
        let (cs, co) = sample.coefficients();
        (0..5)
            .map(|j| {
                let i = 2 * nd[j] as usize;
                cs[j] * x[i] + co[j] * x[i + 1]
            })
            .sum()
    }

    /// The residual of sample k's direction closest to 0 over the tangents that see it (its
    /// own and its views): small when any tangent agrees with the prior there. A prior that all
    /// tangents contradict is wrong there; one that only its own tangent contradicts is right.
    fn consensus_residual(&self, k: usize, x: &[f64], cols: usize) -> f64 {
        let mut best = self.residual(k, x, cols);
        let at = 2 * self.node as usize;
        let target = x[at] * self.samples[k].p + x[at + 1];
        let range = self.view_start[k] as usize..self.view_start[k + 1] as usize;
        for view in &self.views[range] {
            let w = bilinear_weights(view.frac[0], view.frac[1]);
            let (a, c) = (view.node as usize, cols);
            let r = [a, a + 1, a + c, a + c + 1]
                .iter()
                .zip(&w)
                .map(|(&n, &wj)| wj * (view.d * x[2 * n] + view.f * x[2 * n + 1]))
                .sum::<f64>()
                - target;
            if r.abs() < best.abs() {
                best = r;
            }
        }
        best
    }
}

/// One level's problem: valid samples with their nodes and coefficients, the grid edges, and
/// the assembled quadratic part of the energy.
///
/// The residual of sample k is `r_k = Σ_j coef_s[k][j]·s[node[k][j]] + coef_o[k][j]·o[node[k][j]]`
/// over its 8 nodes (4 in a with positive weights, 4 in b with negative ones).
///
/// Every term but Σ 1/s is quadratic in x, so the energy is ½·xᵀHx + scale_weight·Σ 1/s with H
/// fixed per level: H is assembled once from the samples, and a solver iteration costs sparse
/// products with H, whose size depends on the grid, not on the number of samples (which grows
/// with the resolution while the unknowns do not). Only [`Problem::energy`] visits the samples.
#[derive(Debug, Clone)]
pub struct Problem {
    params: LevelParams,
    tangents: usize,
    samples: Vec<Sample>,
    /// Index of each sample in the [`Overlaps`] it came from.
    origin: Vec<u32>,
    /// Per-sample weight of the data term (1 until [`Problem::reweight`]).
    weights: Vec<f64>,
    /// Σ weights: the data term is the weighted mean of r² (with all weights 1, the plain mean).
    weight_total: f64,
    /// (node p, node q, weight): smoothness adds weight·((s_p − s_q)² + (o_p − o_q)²).
    edges: Vec<(u32, u32, f64)>,
    /// Weight of Σ 1/s.
    scale_weight: f64,
    /// Weight of Σ o²: fixes the global offset, which no other term sees (see `GAUGE`).
    gauge_weight: f64,
    /// The prior term, if any: its (α, β) are the node after the tangents' nodes.
    prior: Option<PriorTerm>,
    /// (α₀, κ) of a term κ·(α − α₀)² that holds the prior's slope (the prior-only level's,
    /// [`Problem::hold_prior_slope`]).
    slope_anchor: Option<(f64, f64)>,
    /// Weight per tangent node of (s − 1)² + o², which keeps a level's fields near identity (the
    /// prior-only level's, [`Problem::damp_fields`]); 0 elsewhere.
    damping: f64,
    /// Hessian of the quadratic terms (data, smoothness, gauge, prior, anchor, damping),
    /// symmetric, in compressed rows of 2×2 node blocks on `pattern`, block `[ss, so, os, oo]`
    /// row-major over (s, o) of the row's node × (s, o) of the column's.
    pattern: Arc<Pattern>,
    blocks: Vec<[f64; 4]>,
    /// The data samples grouped by their cells, and the prior samples by theirs: a function of
    /// the samples alone, found at the first assembly and kept for the reassembly after each
    /// reweighting.
    data_groups: Groups,
    prior_groups: Groups,
}

/// Sample indices grouped by a key: `order` holds them sorted by (key, index), group g is
/// `order[ends[g − 1]..ends[g]]`.
#[derive(Debug, Clone, Default)]
struct Groups {
    order: Vec<u32>,
    ends: Vec<usize>,
}

impl Groups {
    fn by_key(mut keyed: Vec<(u64, u32)>) -> Self {
        keyed.par_sort_unstable();
        let mut ends = Vec::new();
        for (i, pair) in keyed.windows(2).enumerate() {
            if pair[0].0 != pair[1].0 {
                ends.push(i + 1);
            }
        }
        if !keyed.is_empty() {
            ends.push(keyed.len());
        }
        Self {
            order: keyed.into_iter().map(|(_, k)| k).collect(),
            ends,
        }
    }

    fn is_empty(&self) -> bool {
        self.ends.is_empty()
    }

    /// The groups, in key order.
    fn slices(&self) -> Vec<&[u32]> {
        let mut start = 0;
        self.ends
            .iter()
            .map(|&end| {
                let group = &self.order[start..end];
                start = end;
                group
            })
            .collect()
    }
}

/// The data and smoothness terms are unchanged by adding one constant to every offset, and no
/// term fixes it; this tiny pull of the offsets towards 0 (standardised maps have median 0)
/// makes the minimum unique and the Newton system positive definite, without measurably moving
/// the solution.
const GAUGE: f64 = 1e-9;

/// Largest spread of the four bilinear neighbours of a b-sample, in standardised units (the
/// mean absolute deviation of each tangent is 1), for the sample to be used.
const EDGE_RANGE: f64 = 0.1;

impl Problem {
    /// The problem of aligning `maps` (N·h·w, NaN = invalid) with `params` over `overlaps`.
    /// Samples whose a-pixel or any of the four b-neighbours is invalid are dropped.
    #[must_use]
    pub fn new(layout: &Layout, maps: &[f32], overlaps: &Overlaps, params: LevelParams) -> Self {
        Self::from_values(layout, maps, overlaps, params)
    }

    /// [`Problem::new`] reading the maps through `maps` (a slice, or maps as a transform would
    /// leave them: only the samples' pixels are read).
    #[must_use]
    pub fn from_values<M: MapValues + ?Sized>(
        layout: &Layout,
        maps: &M,
        overlaps: &Overlaps,
        params: LevelParams,
    ) -> Self {
        Self::with_prior(layout, maps, overlaps, params, None)
    }

    /// [`Problem::from_values`] with the prior term of `prior` = (samples, weight λ) when
    /// given (its (α, β) node comes after the tangents' nodes).
    #[must_use]
    pub fn with_prior<M: MapValues + ?Sized>(
        layout: &Layout,
        maps: &M,
        overlaps: &Overlaps,
        params: LevelParams,
        prior: Option<(&PriorSamples, f64)>,
    ) -> Self {
        let mut problem = Self::unassembled(layout, maps, overlaps, params, prior, true);
        problem.assemble();
        problem
    }

    /// [`Problem::with_prior`] without the Hessian: for a caller that reweights (and so
    /// assembles) before anything reads it. Without `views` the prior samples' views by the
    /// other tangents are not found (they serve only the consensus that judges the prior: a
    /// prior-only level takes its weights from the level before, [`LevelPrior::trust`]).
    #[expect(
        clippy::too_many_lines,
        reason = "sample filter, edges and weights of one problem read best together"
    )]
    fn unassembled<M: MapValues + ?Sized>(
        layout: &Layout,
        maps: &M,
        overlaps: &Overlaps,
        params: LevelParams,
        prior: Option<(&PriorSamples, f64)>,
        views: bool,
    ) -> Self {
        let (h, w) = layout.tangent_shape();
        let n = layout.cameras.len();
        let (cols, rows) = (params.cols, params.rows);
        let per = cols * rows;
        let tp = h * w;
        // Rayon's collect keeps the index order, so the samples are in overlap order.
        let (origin, samples): (Vec<u32>, Vec<Sample>) = (0..overlaps.len())
            .into_par_iter()
            .filter_map(|k| {
                let (a, b) = (overlaps.a[k] as usize, overlaps.b[k] as usize);
                let pa = overlaps.pa[k] as usize;
                let da = maps.value(a * tp + pa);
                let (xb, yb) = (f64::from(overlaps.xb[k]), f64::from(overlaps.yb[k]));
                let x0 = (xb as usize).min(w - 2);
                let y0 = (yb as usize).min(h - 2);
                let (fx, fy) = (xb - x0 as f64, yb - y0 as f64);
                let base = b * tp + y0 * w + x0;
                let corners = [
                    maps.value(base),
                    maps.value(base + 1),
                    maps.value(base + w),
                    maps.value(base + w + 1),
                ];
                if !da.is_finite() || corners.iter().any(|v| !v.is_finite()) {
                    return None;
                }
                // Bilinear interpolation across a depth edge is no measurement of either side:
                // such samples would dominate the squared data term with resampling error.
                // (Not in the paper, so not with its energy.)
                let (lo, hi) = corners
                    .iter()
                    .fold((f32::MAX, f32::MIN), |(l, u), &v| (l.min(v), u.max(v)));
                if params.energy == Energy::Normalized && f64::from(hi - lo) > EDGE_RANGE {
                    return None;
                }
                let c = corners.map(f64::from);
                let db: f64 = bilinear_weights(fx, fy)
                    .iter()
                    .zip(&c)
                    .map(|(w, v)| w * v)
                    .sum();
                let (ca, ra, ax, ay) =
                    grid_cell((pa % w) as f64, (pa / w) as f64, w, h, cols, rows);
                let (cb, rb, bx, by) = grid_cell(xb, yb, w, h, cols, rows);
                Some((
                    k as u32,
                    Sample {
                        node_a: (a * per + ra * cols + ca) as u32,
                        node_b: (b * per + rb * cols + cb) as u32,
                        frac_a: [ax, ay],
                        frac_b: [bx, by],
                        da: f64::from(da),
                        fa: offset_factor(
                            params.offsets,
                            &layout.cameras[a],
                            (pa % w) as f64,
                            (pa / w) as f64,
                        ),
                        db,
                        fb: offset_factor(params.offsets, &layout.cameras[b], xb, yb),
                    },
                ))
            })
            .unzip();

        // Smoothness edges between 4-neighbours, and the term weights.
        let (hx, hy) = (1.0 / (cols - 1) as f64, 1.0 / (rows - 1) as f64);
        let (w_h, w_v, scale_weight) = match params.energy {
            Energy::Paper => {
                let per_edge = params.smoothness / (n * per) as f64;
                (per_edge, per_edge, params.scale_weight)
            }
            Energy::Normalized => (
                params.smoothness / n as f64 * hy / hx,
                params.smoothness / n as f64 * hx / hy,
                params.scale_weight / (n * per) as f64,
            ),
        };
        let mut edges = Vec::with_capacity(n * per * 2);
        for t in 0..n {
            for r in 0..rows {
                for c in 0..cols {
                    let p = (t * per + r * cols + c) as u32;
                    if c + 1 < cols {
                        edges.push((p, p + 1, w_h));
                    }
                    if r + 1 < rows {
                        edges.push((p, p + cols as u32, w_v));
                    }
                }
            }
        }
        let prior = prior.map(|(ps, weight)| {
            let node = (n * per) as u32;
            let built: Vec<(u32, PriorSample, f64, Vec<PriorView>, u32)> = (0..ps.len())
                .into_par_iter()
                .filter_map(|k| {
                    let d = ps.tangent_value(k, maps, tp);
                    if !d.is_finite() {
                        return None;
                    }
                    let t = ps.tangent[k] as usize;
                    let p = ps.pixel[k] as usize;
                    let (x, y) = ((p % w) as f64, (p / w) as f64);
                    let (c, r, fx, fy) = grid_cell(x, y, w, h, cols, rows);
                    let range = if views {
                        ps.view_start[k] as usize..ps.view_start[k + 1] as usize
                    } else {
                        0..0
                    };
                    let views = range
                        .filter_map(|v| {
                            let b = ps.view_tangent[v] as usize;
                            let [xb, yb] = ps.view_xy[v].map(f64::from);
                            // The raw corners kept at the build, through this level's
                            // transform (the values `maps.value` would read).
                            let db = ps.view_value(v, maps, w, h)?;
                            let (cb, rb, bx, by) = grid_cell(xb, yb, w, h, cols, rows);
                            Some(PriorView {
                                node: (b * per + rb * cols + cb) as u32,
                                frac: [bx, by],
                                d: db,
                                f: offset_factor(params.offsets, &layout.cameras[b], xb, yb),
                            })
                        })
                        .collect();
                    Some((
                        k as u32,
                        PriorSample {
                            node: (t * per + r * cols + c) as u32,
                            frac: [fx, fy],
                            d: f64::from(d),
                            f: offset_factor(params.offsets, &layout.cameras[t], x, y),
                            p: ps.value[k],
                        },
                        ps.confidence[k],
                        views,
                        ps.cell[k],
                    ))
                })
                .collect();
            let mut samples = Vec::with_capacity(built.len());
            let mut confidence = Vec::with_capacity(built.len());
            let mut view_start = vec![0u32];
            let mut views = Vec::new();
            let mut cell = Vec::with_capacity(built.len());
            let mut source = Vec::with_capacity(built.len());
            for (k, sample, conf, sample_views, c) in built {
                source.push(k);
                samples.push(sample);
                cell.push(c);
                confidence.push(conf);
                views.extend(sample_views);
                view_start.push(views.len() as u32);
            }
            PriorTerm {
                source,
                view_start,
                views,
                cell,
                weights: vec![1.0; samples.len()],
                scale: weight / samples.len().max(1) as f64,
                samples,
                confidence,
                node,
            }
        });
        Self {
            prior,
            params,
            tangents: n,
            weights: vec![1.0; samples.len()],
            weight_total: samples.len() as f64,
            samples,
            origin,
            edges,
            scale_weight,
            gauge_weight: GAUGE,
            slope_anchor: None,
            damping: 0.0,
            pattern: Arc::default(),
            blocks: Vec::new(),
            data_groups: Groups::default(),
            prior_groups: Groups::default(),
        }
    }

    /// The data term's Hessian contributions: per group of samples sharing their a-cell and
    /// b-cell, the 8 nodes and the dense 16×16 block (2/z)·Σ ω·c·cᵀ.
    fn data_blocks(&self) -> Vec<([u32; 8], [f64; 256])> {
        let cols = self.params.cols;
        let two_over_z = 2.0 / self.weight_total.max(f64::MIN_POSITIVE);
        self.data_groups
            .slices()
            .par_iter()
            .map(|group| {
                // Upper triangle only; mirrored below.
                let mut block = [0.0; 256];
                for &k in *group {
                    let (coef_s, coef_o) = self.samples[k as usize].coefficients();
                    let weight = self.weights[k as usize];
                    let mut c = [0.0; 16];
                    for j in 0..8 {
                        c[2 * j] = coef_s[j];
                        c[2 * j + 1] = coef_o[j];
                    }
                    for (u, &cu) in c.iter().enumerate() {
                        let cu = weight * cu;
                        for (b, &cv) in block[16 * u + u..16 * u + 16].iter_mut().zip(&c[u..]) {
                            *b += cu * cv;
                        }
                    }
                }
                for u in 0..16 {
                    for v in u..16 {
                        block[16 * u + v] *= two_over_z;
                        block[16 * v + u] = block[16 * u + v];
                    }
                }
                (self.samples[group[0] as usize].nodes(cols), block)
            })
            .collect()
    }

    /// Assemble the Hessian H of the quadratic terms.
    ///
    /// Samples whose a-cell and b-cell are the same share all 8 nodes (the top-left nodes,
    /// entries 0 and 4, identify the group), so each group's 16×16 block Σ c·cᵀ is summed
    /// densely (in sample order, in parallel over groups) and scattered once.
    fn assemble(&mut self) {
        let nodes_total = self.len() / 2;
        if self.data_groups.is_empty() && !self.samples.is_empty() {
            self.data_groups = Groups::by_key(
                self.samples
                    .par_iter()
                    .enumerate()
                    .map(|(k, sample)| {
                        let key = (u64::from(sample.node_a) << 32) | u64::from(sample.node_b);
                        (key, k as u32)
                    })
                    .collect(),
            );
        }
        if let Some(prior) = self.prior.as_ref().filter(|_| self.prior_groups.is_empty()) {
            self.prior_groups = Groups::by_key(
                prior
                    .samples
                    .iter()
                    .enumerate()
                    .map(|(k, sample)| (u64::from(sample.node), k as u32))
                    .collect(),
            );
        }
        let group_blocks = self.data_blocks();
        let prior_blocks = self.prior_blocks();
        // The pattern depends only on the samples' cells, the prior nodes and the edges, not
        // on the weights: found once, reused when a reweighting reassembles.
        if self.pattern.is_empty() {
            self.pattern = Pattern::of(Couplings {
                nodes: nodes_total,
                data: group_blocks.iter().map(|(nd, _)| *nd).collect(),
                prior: self.prior_cells(),
                edges: self.edges.iter().map(|&(p, q, _)| [p, q]).collect(),
            });
        }
        let pattern = &self.pattern;
        let mut blocks = vec![[0.0f64; 4]; pattern.col.len()];
        // A dense block over `count` nodes (2·count unknowns, row-major), scattered into the
        // 2×2 node blocks at positions `at` (count × count, row-major).
        let mut scatter = |at: &[u32], count: usize, block: &[f64]| {
            let width = 2 * count;
            for u in 0..count {
                for v in 0..count {
                    let target = &mut blocks[at[count * u + v] as usize];
                    let (r, c) = (2 * u, 2 * v);
                    target[0] += block[width * r + c];
                    target[1] += block[width * r + c + 1];
                    target[2] += block[width * (r + 1) + c];
                    target[3] += block[width * (r + 1) + c + 1];
                }
            }
        };
        for ((_, block), at) in group_blocks.iter().zip(pattern.data_at.chunks_exact(64)) {
            scatter(at, 8, block);
        }
        for (nd, block) in &prior_blocks {
            let at = 25 * self.prior_cell(nd[0]);
            scatter(&pattern.prior_at[at..at + 25], 5, block);
        }
        for (&(_, _, wgt), at) in self.edges.iter().zip(&pattern.edge_at) {
            for (&i, sign) in at.iter().zip([1.0, 1.0, -1.0, -1.0]) {
                let target = &mut blocks[i as usize];
                target[0] += sign * 2.0 * wgt;
                target[3] += sign * 2.0 * wgt;
            }
        }
        for &i in &pattern.diagonal_at {
            blocks[i as usize][3] += 2.0 * self.gauge_weight;
        }
        if let (Some(prior), Some((_, kappa))) = (&self.prior, self.slope_anchor) {
            blocks[pattern.diagonal_at[prior.node as usize] as usize][0] += 2.0 * kappa;
        }
        if self.damping > 0.0 {
            for &i in &pattern.diagonal_at[..self.scale_nodes()] {
                blocks[i as usize][0] += 2.0 * self.damping;
                blocks[i as usize][3] += 2.0 * self.damping;
            }
        }
        self.blocks = blocks;
    }

    /// The prior term's couplings: every grid cell's 5 nodes (its corners, then the prior's),
    /// tangent by tangent, row by row, whether or not a prior sample falls in it. The pattern
    /// then depends on the grid alone, not on where the prior has holes (NaN, confidence 0,
    /// masked tangents): priors that differ there reuse the kept pattern and Newton analyses
    /// (with per-image holes each stitch added a pattern and twenty analyses, and a process's
    /// memory grew by 150 MB at 2K before the caches' bounds held it). Empty without a prior.
    fn prior_cells(&self) -> Vec<[u32; 5]> {
        let Some(prior) = &self.prior else {
            return Vec::new();
        };
        let (cols, rows) = (self.params.cols as u32, self.params.rows as u32);
        let mut cells = Vec::with_capacity(self.tangents * self.params.cells());
        for t in 0..self.tangents as u32 {
            for cy in 0..rows - 1 {
                for cx in 0..cols - 1 {
                    let a = t * cols * rows + cy * cols + cx;
                    cells.push([a, a + 1, a + cols, a + cols + 1, prior.node]);
                }
            }
        }
        cells
    }

    /// The index in [`Problem::prior_cells`] of the cell whose top-left node is `corner`.
    fn prior_cell(&self, corner: u32) -> usize {
        let (cols, rows) = (self.params.cols, self.params.rows);
        let (t, node) = (
            corner as usize / (cols * rows),
            corner as usize % (cols * rows),
        );
        t * self.params.cells() + (node / cols) * (cols - 1) + node % cols
    }

    /// The prior term's Hessian contributions: per group of samples sharing a cell, the 5 nodes
    /// and the dense 10×10 block 2·λ/K·Σ c·ω·aaᵀ (in sample order, in parallel over groups).
    fn prior_blocks(&self) -> Vec<([u32; 5], [f64; 100])> {
        let Some(prior) = &self.prior else {
            return Vec::new();
        };
        let cols = self.params.cols;
        self.prior_groups
            .slices()
            .par_iter()
            .map(|group| {
                let mut block = [0.0; 100];
                for &k in *group {
                    let k = k as usize;
                    let (cs, co) = prior.samples[k].coefficients();
                    let weight = 2.0 * prior.scale * prior.confidence[k] * prior.weights[k];
                    let mut c = [0.0; 10];
                    for j in 0..5 {
                        c[2 * j] = cs[j];
                        c[2 * j + 1] = co[j];
                    }
                    for (u, &cu) in c.iter().enumerate() {
                        let cu = weight * cu;
                        for (b, &cv) in block[10 * u..10 * u + 10].iter_mut().zip(&c) {
                            *b += cu * cv;
                        }
                    }
                }
                (
                    prior.samples[group[0] as usize].nodes(cols, prior.node),
                    block,
                )
            })
            .collect()
    }

    /// Number of grid nodes of the tangents (the nodes with a scale s).
    #[must_use]
    pub fn scale_nodes(&self) -> usize {
        self.tangents * self.params.cols * self.params.rows
    }

    /// Number of unknowns (2 per node: the tangents' nodes, then the prior's (α, β) if any).
    #[must_use]
    pub fn len(&self) -> usize {
        2 * (self.scale_nodes() + usize::from(self.prior.is_some()))
    }

    /// Number of prior samples in the problem (0 without a prior).
    #[must_use]
    pub fn prior_samples(&self) -> usize {
        self.prior.as_ref().map_or(0, |p| p.samples.len())
    }

    /// The tangents' consensus at each of the `len` prior samples the problem was built from,
    /// by their index there (None where the sample's own tangent has no value): its own value
    /// and its views', as the problem's maps read them. None without a prior. Built without
    /// views ([`Problem::unassembled`]) it holds the own values alone.
    fn prior_consensus(&self, len: usize) -> Option<Vec<Option<Consensus>>> {
        let prior = self.prior.as_ref()?;
        let mut consensus = vec![None; len];
        for (k, (sample, &i)) in prior.samples.iter().zip(&prior.source).enumerate() {
            let range = prior.view_start[k] as usize..prior.view_start[k + 1] as usize;
            let views = prior.views[range].iter().map(|v| v.d);
            consensus[i as usize] = Some(Consensus::of(std::iter::once(sample.d).chain(views)));
        }
        Some(consensus)
    }

    /// Per prior sample the problem was built from (by its index there; None where fewer than
    /// two tangents see its trust cell's neighbourhood), the variance of the tangents' consensus
    /// at low frequency: each tangent's deviation from the samples' consensus, averaged over the
    /// trust cell and its 8 neighbours (the fusion's low-pass, [`prior::PriorSamples::fused`]), so
    /// that pixel noise averages out and a smooth error of its own does not; then
    /// Σ D_t²/(n(n − 1)) over the n tangents there, the variance of a mean of n independent
    /// errors estimated from their spread. In standardised units.
    fn consensus_variance(&self, len: usize) -> Option<Vec<Option<f64>>> {
        let prior = self.prior.as_ref()?;
        let per = (self.params.cols * self.params.rows) as u32;
        // Per tangent, the cells of the samples it sees and its deviation there.
        let (mut cells, mut deviations) =
            (vec![vec![]; self.tangents], vec![vec![]; self.tangents]);
        for (k, sample) in prior.samples.iter().enumerate() {
            let range = prior.view_start[k] as usize..prior.view_start[k + 1] as usize;
            let views = &prior.views[range];
            if views.is_empty() {
                continue;
            }
            let values =
                std::iter::once((sample.node, sample.d)).chain(views.iter().map(|v| (v.node, v.d)));
            let mean = values.clone().map(|(_, d)| d).sum::<f64>() / (views.len() + 1) as f64;
            for (node, d) in values {
                let t = (node / per) as usize;
                cells[t].push(prior.cell[k]);
                deviations[t].push(d - mean);
            }
        }
        let means: Vec<CellMeans> = cells
            .iter()
            .zip(&deviations)
            .map(|(c, d)| CellMeans::weighted(c, d, &vec![1.0; d.len()]))
            .collect();
        let variance: Vec<Option<f64>> = (0..prior::TRUST_ROWS * 2 * prior::TRUST_ROWS)
            .map(|cell| {
                let devs: Vec<f64> = means.iter().filter_map(|m| m.around(cell)).collect();
                let n = devs.len() as f64;
                (n >= 2.0).then(|| devs.iter().map(|d| d * d).sum::<f64>() / (n * (n - 1.0)))
            })
            .collect();
        let mut out = vec![None; len];
        for (k, &i) in prior.source.iter().enumerate() {
            out[i as usize] = variance[prior.cell[k] as usize];
        }
        Some(out)
    }

    /// The prior samples' values replaced by `values`, indexed as the samples the problem was
    /// built from (the fused prior's, [`PriorSamples::fused`]).
    fn set_prior_values(&mut self, values: &[f64]) {
        if let Some(prior) = self.prior.as_mut() {
            for (sample, &i) in prior.samples.iter_mut().zip(&prior.source) {
                sample.p = values[i as usize];
            }
        }
    }

    /// The prior samples' confidences replaced by `values` (as [`Self::set_prior_values`]).
    fn set_prior_confidence(&mut self, values: &[f64]) {
        if let Some(prior) = self.prior.as_mut() {
            for (c, &i) in prior.confidence.iter_mut().zip(&prior.source) {
                *c = values[i as usize];
            }
        }
    }

    /// Residual of every prior sample at `x`, in sample order (empty without a prior).
    #[must_use]
    pub fn prior_residuals(&self, x: &[f64]) -> Vec<f64> {
        let cols = self.params.cols;
        self.prior.as_ref().map_or_else(Vec::new, |prior| {
            (0..prior.samples.len())
                .into_par_iter()
                .map(|k| prior.residual(k, x, cols))
                .collect()
        })
    }

    /// (α, β) fitted to the tangents' values at the prior samples as the fields `x` leave them
    /// (x's own α, β ignored), robustly (Cauchy IRLS with the prior's confidence) and
    /// symmetrically (`symmetric_line`). None without a prior or when the fit is degenerate.
    #[must_use]
    pub fn fit_prior_affine(&self, x: &[f64]) -> Option<(f64, f64)> {
        let prior = self.prior.as_ref()?;
        let mut z = x.to_vec();
        let at = 2 * prior.node as usize;
        z[at] = 0.0;
        z[at + 1] = 0.0;
        // With α = β = 0 the residual is the tangent's value.
        let values = self.prior_residuals(&z);
        let p: Vec<f64> = prior.samples.iter().map(|s| s.p).collect();
        symmetric_line(&p, &values, &prior.confidence)
    }

    /// Hold the prior's slope α near `alpha`: adds κ·(α − α₀)² with κ = `SLOPE_ANCHOR`·λ (takes
    /// effect at the next assembly). For the prior-only level, where nothing determines α: its
    /// fields can follow any α·P + β, and a free α shrank towards the least-squares slope there,
    /// flattening the tangents on real networks (docs/method.md, "On real networks").
    pub fn hold_prior_slope(&mut self, alpha: f64) {
        if let Some(prior) = &self.prior {
            let kappa = SLOPE_ANCHOR * prior.scale * prior.samples.len() as f64;
            self.slope_anchor = Some((alpha, kappa));
        }
    }

    /// Keep the fields near identity (the maps as the levels before left them): adds
    /// μ·Σ ((s − 1)² + o²) over the tangents' nodes with μ = `relative`·λ / nodes, so that at
    /// `relative` = 1 it weighs about as much as the prior term at a node (takes effect at the
    /// next assembly). For the prior-only level (docs/method.md, "Global prior").
    pub fn damp_fields(&mut self, relative: f64) {
        if let Some(prior) = &self.prior {
            let lambda = prior.scale * prior.samples.len() as f64;
            self.damping = relative * lambda / self.scale_nodes().max(1) as f64;
        }
    }

    /// The prior samples' IRLS weights (empty without a prior).
    #[must_use]
    pub fn prior_weights(&self) -> &[f64] {
        self.prior.as_ref().map_or(&[], |p| &p.weights)
    }

    /// Judge every prior sample at `x` and reassemble: its weight is the Cauchy IRLS weight of
    /// its consensus residual (the smallest over the tangents that see its direction: a prior
    /// region is outvoted only when no tangent agrees with it) at their own scale
    /// σ = 1.4826·median|r| (at least `MIN_PRIOR_SCALE`), at most its neighbourhood's mean
    /// plus `NEIGHBOURHOOD_SLACK`, and 0 below `HARD_TRUST`: a sample is trusted or not.
    /// Returns σ (0 without a prior).
    pub fn reweight_prior(&mut self, x: &[f64]) -> f64 {
        let sigma = self.set_prior_weights(x);
        self.assemble();
        sigma
    }

    /// [`Problem::reweight_prior`] without reassembling (for a caller that reweights the data
    /// term next, which reassembles once for both).
    fn set_prior_weights(&mut self, x: &[f64]) -> f64 {
        let (weights, sigma) = self.prior_trust(x);
        if let Some(prior) = self.prior.as_mut() {
            prior.weights = weights;
        }
        sigma
    }

    /// The weights [`Problem::set_prior_weights`] gives the prior samples at `x`, and σ.
    fn prior_trust(&self, x: &[f64]) -> (Vec<f64>, f64) {
        let Some(prior) = self.prior.as_ref() else {
            return (Vec::new(), 0.0);
        };
        let cols = self.params.cols;
        let residuals: Vec<f64> = (0..prior.samples.len())
            .into_par_iter()
            .map(|k| prior.consensus_residual(k, x, cols))
            .collect();
        let sigma = robust_scale(&residuals).max(MIN_PRIOR_SCALE);
        let weights: Vec<f64> = residuals
            .iter()
            .map(|&r| Loss::Cauchy.weight(r, sigma))
            .collect();
        let mut weights = spread_trust(prior, &weights);
        // Priors are wrong on whole regions: a sample is trusted no more than its neighbourhood
        // (plus a slack), so the edges of a wrong region, where single samples happen to agree
        // with the tangents, do not pull the level along; and a sample the consensus doubts
        // does not pull at all (a Cauchy weight never reaches 0: a fifth of the sphere wrong by
        // 30 % kept pulling the schedule's levels at weights of 0.2-0.4, docs/method.md).
        let cells = CellMeans::of(prior, &weights, |_| true);
        for (w, &cell) in weights.iter_mut().zip(&prior.cell) {
            let cap = cells
                .around(cell as usize)
                .map_or(1.0, |m| m + NEIGHBOURHOOD_SLACK);
            *w = w.min(cap);
            if *w < HARD_TRUST {
                *w = 0.0;
            }
        }
        (weights, sigma)
    }

    /// The robust rounds of this level: [`ROBUST_ROUNDS`], or [`PRIOR_ROBUST_ROUNDS`] with a
    /// prior whose samples other tangents see [`DEEP_CONSENSUS`] deep on average.
    fn robust_rounds(&self) -> usize {
        let deep = self.prior.as_ref().is_some_and(|prior| {
            let views = prior.views.len() as f64;
            views >= DEEP_CONSENSUS * prior.samples.len() as f64
        });
        if deep {
            PRIOR_ROBUST_ROUNDS
        } else {
            ROBUST_ROUNDS
        }
    }

    /// Whether the problem has no unknowns.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Number of valid overlap samples.
    #[must_use]
    pub fn samples(&self) -> usize {
        self.samples.len()
    }

    /// The problem's terms, for inspection and independent checks: per sample the 8 nodes and
    /// the residual coefficients on their s and o; the smoothness edges (p, q, weight); the
    /// weights of Σ 1/s and of the gauge Σ o².
    #[allow(clippy::type_complexity)]
    pub fn terms(
        &self,
    ) -> (
        Vec<[u32; 8]>,
        Vec<[f64; 8]>,
        Vec<[f64; 8]>,
        &[(u32, u32, f64)],
        f64,
        f64,
    ) {
        let nodes = self
            .samples
            .iter()
            .map(|s| s.nodes(self.params.cols))
            .collect();
        let (coef_s, coef_o) = self.samples.iter().map(Sample::coefficients).unzip();
        (
            nodes,
            coef_s,
            coef_o,
            &self.edges,
            self.scale_weight,
            self.gauge_weight,
        )
    }

    /// The data-term weight of each sample (all 1 until [`Problem::reweight`]).
    #[must_use]
    pub fn weights(&self) -> &[f64] {
        &self.weights
    }

    /// Index of each sample in the [`Overlaps`] the problem was built from.
    #[must_use]
    pub fn origins(&self) -> &[u32] {
        &self.origin
    }

    /// Residual of every sample at `x`, in sample order.
    #[must_use]
    pub fn residuals(&self, x: &[f64]) -> Vec<f64> {
        (0..self.samples())
            .into_par_iter()
            .map(|k| self.residual(k, x))
            .collect()
    }

    /// Set every sample's weight to `loss`'s IRLS weight of its residual at `x`, with the scale
    /// σ = 1.4826·median|r| (at least `MIN_ROBUST_SCALE`), and reassemble the Hessian.
    /// Returns σ.
    pub fn reweight(&mut self, x: &[f64], loss: Loss) -> f64 {
        let residuals = self.residuals(x);
        let sigma = robust_scale(&residuals);
        self.set_weights(residuals.iter().map(|&r| loss.weight(r, sigma)).collect());
        sigma
    }

    /// Set the data term's per-sample weights (≥ 0, one per sample) and reassemble.
    ///
    /// # Panics
    /// If `weights` does not have one entry per sample.
    pub fn set_weights(&mut self, weights: Vec<f64>) {
        assert_eq!(weights.len(), self.samples(), "one weight per sample");
        // Sequential sum: the same for any thread count.
        self.weight_total = weights.iter().sum();
        self.weights = weights;
        self.assemble();
    }

    /// Identity fields: s = 1, o = 0.
    #[must_use]
    pub fn identity(&self) -> Vec<f64> {
        (0..self.len())
            .map(|i| if i % 2 == 0 { 1.0 } else { 0.0 })
            .collect()
    }

    /// Residual of sample k.
    #[inline]
    fn residual(&self, k: usize, x: &[f64]) -> f64 {
        let sample = &self.samples[k];
        let nd = sample.nodes(self.params.cols);
        let (cs, co) = sample.coefficients();
        (0..8)
            .map(|j| {
                let i = 2 * nd[j] as usize;
                cs[j] * x[i] + co[j] * x[i + 1]
            })
            .sum()
    }

    /// Energy at `x`, and its gradient into `grad` when given. Any s ≤ 0 gives +∞.
    ///
    /// The data term is summed over the samples' residuals (not as ½·xᵀHx, whose rounding
    /// error is relative to the terms' size rather than to the energy), reduced over fixed
    /// chunks in index order, so the result does not depend on the number of threads.
    #[must_use]
    pub fn energy(&self, x: &[f64], grad: Option<&mut [f64]>) -> f64 {
        const CHUNK: usize = 4096;
        let scale_len = 2 * self.scale_nodes();
        if x[..scale_len].iter().step_by(2).any(|&s| s <= 0.0) {
            return f64::INFINITY;
        }
        let samples = self.samples();
        let partial: Vec<f64> = (0..samples.div_ceil(CHUNK))
            .into_par_iter()
            .map(|c| {
                (c * CHUNK..((c + 1) * CHUNK).min(samples))
                    .map(|k| self.weights[k] * self.residual(k, x).powi(2))
                    .sum()
            })
            .collect();
        let mut energy = partial.iter().sum::<f64>() / self.weight_total.max(f64::MIN_POSITIVE);
        for &(p, q, wgt) in &self.edges {
            let (p, q) = (2 * p as usize, 2 * q as usize);
            let (ds, dof) = (x[p] - x[q], x[p + 1] - x[q + 1]);
            energy += wgt * (ds * ds + dof * dof);
        }
        // The 1/s barrier, the offsets' gauge and (prior-only level) the damping towards
        // identity, in one walk over the nodes.
        for node in x[..scale_len].chunks_exact(2) {
            let (s, o) = (node[0], node[1]);
            energy += self.scale_weight / s
                + self.gauge_weight * o * o
                + self.damping * ((s - 1.0) * (s - 1.0) + o * o);
        }
        if let Some(prior) = &self.prior {
            let cols = self.params.cols;
            let count = prior.samples.len();
            let partial: Vec<f64> = (0..count.div_ceil(CHUNK))
                .into_par_iter()
                .map(|c| {
                    (c * CHUNK..((c + 1) * CHUNK).min(count))
                        .map(|k| {
                            prior.confidence[k]
                                * prior.weights[k]
                                * prior.residual(k, x, cols).powi(2)
                        })
                        .sum()
                })
                .collect();
            energy += prior.scale * partial.iter().sum::<f64>();
            let beta = x[2 * prior.node as usize + 1];
            energy += self.gauge_weight * beta * beta;
            if let Some((alpha0, kappa)) = self.slope_anchor {
                let alpha = x[2 * prior.node as usize];
                energy += kappa * (alpha - alpha0) * (alpha - alpha0);
            }
        }
        if let Some(g) = grad {
            self.gradient(x, g);
        }
        energy
    }

    /// The gradient at `x` (all s > 0): H·x minus scale_weight/s² on the s entries.
    fn gradient(&self, x: &[f64], grad: &mut [f64]) {
        self.hessian_product(x, grad);
        let scale_len = 2 * self.scale_nodes();
        for (g, node) in grad[..scale_len]
            .chunks_exact_mut(2)
            .zip(x[..scale_len].chunks_exact(2))
        {
            // H·x holds the damping's 2μ·s; its gradient is 2μ·(s − 1).
            g[0] -= self.scale_weight / (node[0] * node[0]) + 2.0 * self.damping;
        }
        // H·x holds the anchor's 2κ·α; its gradient is 2κ·(α − α₀).
        if let (Some(prior), Some((alpha0, kappa))) = (&self.prior, self.slope_anchor) {
            grad[2 * prior.node as usize] -= 2.0 * kappa * alpha0;
        }
    }

    /// Move `x` along its ray to the energy's minimum there, t·x, and return the change.
    ///
    /// Every term but Σ 1/s is homogeneous of degree 2 in x (the residuals have no constant
    /// part), so along the ray E(t·x) = t²·Q + B/t with Q = ½·xᵀHx and B the 1/s term, least at
    /// t = (B/2Q)^⅓. That ray is the global scale, which only the weak 1/s term fixes: Newton's
    /// quadratic model misses how its curvature changes along it and converged there only
    /// linearly (3–4 steps on the 8 × 7 level where 2 now suffice; docs/method.md, "Solvers").
    /// Not with the slope anchor, which is not homogeneous, nor farther than a factor 2: 0 and
    /// `x` as it is.
    fn rescale_to_ray_minimum(&self, x: &mut [f64]) -> f64 {
        if self.slope_anchor.is_some() || self.damping > 0.0 || self.scale_weight <= 0.0 {
            return 0.0;
        }
        let mut hx = vec![0.0; x.len()];
        self.hessian_product(x, &mut hx);
        let q = 0.5 * dot(x, &hx);
        let scale_len = 2 * self.scale_nodes();
        let b = self.scale_weight
            * x[..scale_len]
                .iter()
                .step_by(2)
                .map(|s| 1.0 / s)
                .sum::<f64>();
        if !(q > 0.0 && b > 0.0) {
            return 0.0;
        }
        let t = (b / (2.0 * q)).cbrt();
        // Farther than 2× the data hardly fix the scale (a tangent without samples, whose s
        // only the barrier holds, wants s → ∞): the jump would feed that runaway until the
        // Hessian lost its last pivot (seen on 144-px layouts); Newton's own steps go there.
        if !(0.5..=2.0).contains(&t) {
            return 0.0;
        }
        for v in x.iter_mut() {
            *v *= t;
        }
        t * t * q + b / t - q - b
    }

    /// out = H·v for the quadratic terms' Hessian H, in parallel over fixed chunks of rows
    /// (each row summed in its own order: the result does not depend on the thread count).
    fn hessian_product(&self, v: &[f64], out: &mut [f64]) {
        const CHUNK: usize = 256;
        out.par_chunks_mut(2 * CHUNK)
            .enumerate()
            .for_each(|(c, part)| {
                for (i, row) in part.chunks_exact_mut(2).enumerate() {
                    let p = c * CHUNK + i;
                    let range = self.pattern.start[p]..self.pattern.start[p + 1];
                    let (mut ys, mut yo) = (0.0, 0.0);
                    for (b, &q) in self.blocks[range.clone()]
                        .iter()
                        .zip(&self.pattern.col[range])
                    {
                        let (vs, vo) = (v[2 * q as usize], v[2 * q as usize + 1]);
                        ys += b[0] * vs + b[1] * vo;
                        yo += b[2] * vs + b[3] * vo;
                    }
                    row[0] = ys;
                    row[1] = yo;
                }
            });
    }
}

/// Only prior samples whose weight is at least this are trusted, the others weigh 0 (|r| within
/// 1.2 σ of the consensus, half the Cauchy scale c = 2.385 σ): measured on synthetic rooms with
/// a prior 30 % wrong on a fifth of the sphere (benches/bench_prior.py), on the prior-only level
/// ½ let it follow a third of the wrong region, 0.8 kept the gain on content errors and lost
/// that.
const HARD_TRUST: f64 = 0.8;

/// A prior sample's weight is at most its trust cell's neighbourhood mean plus this. Measured
/// when only the prior-only level judged this way, on 4 synthetic rooms at 4K with the prior
/// 30 % wrong on a fifth of the sphere (`benches/bench_prior.py`, slopes held, the level's
/// smoothness at 1/100): no cap 0.0300 (no prior: 0.0251), slack 0.3 0.0249, 0.2 0.0241, 0.1
/// 0.0226; under content errors with a right prior 0.0132, 0.0133, 0.0135, 0.0137. With the
/// smoothness at 3/1000 (below), 0.3 let the wrong prior reach 0.0274 at 4K (the goal: no
/// prior + 0.002) and 0.2 0.0258.
const NEIGHBOURHOOD_SLACK: f64 = 0.2;

/// The slope anchor's weight κ, per unit of the prior weight λ: a hundred times the prior
/// term's own curvature in α (about λ·mean p² with p standardised), so α stays within about 1 %.
const SLOPE_ANCHOR: f64 = 100.0;

/// Where only one tangent sees a prior sample's direction, its residual cannot tell whether the
/// prior or the tangent is wrong: such samples take the mean weight of the samples that other
/// tangents also see in their 6° cell and its 8 neighbours (1 when there are none), so a prior
/// region that overlapping tangents outvoted stays outvoted between them, and a tangent's
/// content error where it alone sees the sphere is corrected by a prior trusted around it.
fn spread_trust(prior: &PriorTerm, weights: &[f64]) -> Vec<f64> {
    let seen = |k: usize| prior.view_start[k + 1] > prior.view_start[k];
    let cells = CellMeans::of(prior, weights, seen);
    weights
        .iter()
        .enumerate()
        .map(|(k, &w)| {
            if seen(k) {
                w
            } else {
                cells.around(prior.cell[k] as usize).unwrap_or(1.0)
            }
        })
        .collect()
}

/// Sums and counts of sample weights per trust cell ([`prior::TRUST_ROWS`] rows, twice as many
/// columns, the ERP grid of the samples' directions).
struct CellMeans {
    sum: Vec<f64>,
    count: Vec<f64>,
}

impl CellMeans {
    /// Of the sample weights `weights`, over the samples k with `include(k)`.
    fn of(prior: &PriorTerm, weights: &[f64], include: impl Fn(usize) -> bool) -> Self {
        let counted: Vec<f64> = (0..weights.len())
            .map(|k| if include(k) { 1.0 } else { 0.0 })
            .collect();
        Self::weighted(&prior.cell, weights, &counted)
    }

    /// Of `values` at samples in cells `cells`, each counted with its weight in `weights`.
    fn weighted(cells: &[u32], values: &[f64], weights: &[f64]) -> Self {
        let count = prior::TRUST_ROWS * 2 * prior::TRUST_ROWS;
        let (mut sum, mut total) = (vec![0.0; count], vec![0.0; count]);
        for ((&cell, &v), &w) in cells.iter().zip(values).zip(weights) {
            sum[cell as usize] += w * v;
            total[cell as usize] += w;
        }
        Self { sum, count: total }
    }

    /// The mean weight over `cell` and its 8 neighbours (wrapping in longitude, cut at the
    /// poles); None when they hold no sample.
    fn around(&self, cell: usize) -> Option<f64> {
        let (rows, cols) = (prior::TRUST_ROWS, 2 * prior::TRUST_ROWS);
        let (r, c) = ((cell / cols) as isize, (cell % cols) as isize);
        let (mut s, mut n) = (0.0, 0.0);
        for rr in (r - 1).max(0)..=(r + 1).min(rows as isize - 1) {
            for dc in -1..=1 {
                let i = rr as usize * cols + (c + dc).rem_euclid(cols as isize) as usize;
                s += self.sum[i];
                n += self.count[i];
            }
        }
        (n > 0.0).then(|| s / n)
    }
}

/// The line v ≈ α·p + β through weighted points, robustly and symmetrically: Cauchy IRLS
/// (from the weights `confidence`, its own scale) on the least-squares line picks the points to
/// trust, then the slope is the ratio of their weighted spreads, with the sign of their
/// covariance (the geometric-mean, or reduced major axis, line), so fitting p on v gives 1/α.
/// The least-squares slope itself is shrunk by the correlation of the two: with a prior the
/// tangents barely agree with (real networks: correlation 0.3–0.8) it gave α of 0.03–0.2 in
/// standardised units, a nearly flat target that the prior-only level then flattened the
/// tangents to (docs/method.md, "On real networks"). The spreads alone would be inflated by
/// outliers, which the least-squares IRLS downweights first.
/// None when the points have no weight or p no spread.
fn symmetric_line(p: &[f64], v: &[f64], confidence: &[f64]) -> Option<(f64, f64)> {
    let mut weights = confidence.to_vec();
    let moments = |weights: &[f64]| {
        let sw: f64 = weights.iter().sum();
        let mp = weights.iter().zip(p).map(|(w, x)| w * x).sum::<f64>() / sw;
        let mv = weights.iter().zip(v).map(|(w, y)| w * y).sum::<f64>() / sw;
        let (mut cpp, mut cvv, mut cpv) = (0.0, 0.0, 0.0);
        for ((&w, &pk), &vk) in weights.iter().zip(p).zip(v) {
            let (dp, dv) = (pk - mp, vk - mv);
            cpp += w * dp * dp;
            cvv += w * dv * dv;
            cpv += w * dp * dv;
        }
        (sw > 0.0 && cpp > 1e-12 * sw).then_some((mp, mv, cpp, cvv, cpv))
    };
    for _ in 0..ROBUST_ROUNDS + 2 {
        let (mp, mv, cpp, _, cpv) = moments(&weights)?;
        let alpha = cpv / cpp;
        let residuals: Vec<f64> = p
            .iter()
            .zip(v)
            .map(|(pk, vk)| vk - mv - alpha * (pk - mp))
            .collect();
        let sigma = robust_scale(&residuals).max(MIN_PRIOR_SCALE);
        for ((w, c), r) in weights.iter_mut().zip(confidence).zip(&residuals) {
            *w = c * Loss::Cauchy.weight(*r, sigma);
        }
    }
    let (mp, mv, cpp, cvv, cpv) = moments(&weights)?;
    let alpha = if cpv < 0.0 { -1.0 } else { 1.0 } * (cvv / cpp).sqrt();
    Some((alpha, mv - alpha * mp))
}

/// σ = 1.4826·median|r| (at least [`MIN_ROBUST_SCALE`]; 1 without residuals).
fn robust_scale(residuals: &[f64]) -> f64 {
    let mut magnitudes: Vec<f64> = residuals.iter().map(|r| r.abs()).collect();
    if magnitudes.is_empty() {
        return 1.0;
    }
    let mid = magnitudes.len() / 2;
    let (_, &mut median, _) = magnitudes.select_nth_unstable_by(mid, f64::total_cmp);
    (1.4826 * median).max(MIN_ROBUST_SCALE)
}

/// Median of |values| (0 when empty).
fn median_abs(values: &[f64]) -> f64 {
    let mut magnitudes: Vec<f64> = values.iter().map(|r| r.abs()).collect();
    if magnitudes.is_empty() {
        return 0.0;
    }
    let mid = magnitudes.len() / 2;
    let (_, &mut median, _) = magnitudes.select_nth_unstable_by(mid, f64::total_cmp);
    median
}

/// Stopping rule shared by both solvers: the gradient's max-norm is below `tolerance` times
/// max(1, |E|) (energies are O(1): the maps are standardised).
fn gradient_small(grad: &[f64], energy: f64, tolerance: f64) -> bool {
    max_abs(grad) <= tolerance * energy.abs().max(1.0)
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |m, x| m.max(x.abs()))
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Backtracking Armijo line search along `dir` from `x` (gradient `g`); returns the new point
/// and its energy change, or None if no step decreases the energy.
///
/// The change is evaluated exactly from one product H·dir: with t the step,
/// E(x + t·d) − E(x) = t·gᵀd + ½t²·dᵀHd + Σ c·t²·d_s²/(s²·(s + t·d_s)) over the s entries (the
/// 1/s term's remainder after its linear part). Unlike a difference of two evaluated energies
/// it has no cancellation, so the search still sees decreases far below the energy's rounding.
fn line_search(problem: &Problem, x: &[f64], g: &[f64], dir: &[f64]) -> Option<(Vec<f64>, f64)> {
    let slope = dot(g, dir);
    if slope >= 0.0 || slope.is_nan() {
        return None;
    }
    // Largest step that keeps every scale positive (the 1/s term is a barrier at 0).
    let mut step: f64 = 1.0;
    let scale_len = 2 * problem.scale_nodes();
    for i in (0..scale_len).step_by(2) {
        if dir[i] < 0.0 {
            step = step.min(0.95 * x[i] / -dir[i]);
        }
    }
    let mut hd = vec![0.0; x.len()];
    problem.hessian_product(dir, &mut hd);
    let curvature = dot(dir, &hd);
    let c = problem.scale_weight;
    for _ in 0..60 {
        let barrier: f64 = x[..scale_len]
            .chunks_exact(2)
            .zip(dir[..scale_len].chunks_exact(2))
            .map(|(xn, dn)| {
                let (s, ds) = (xn[0], dn[0]);
                c * step * step * ds * ds / (s * s * (s + step * ds))
            })
            .sum();
        let change = step * slope + 0.5 * step * step * curvature + barrier;
        if change <= 1e-4 * step * slope {
            let trial = x.iter().zip(dir).map(|(xi, di)| xi + step * di).collect();
            return Some((trial, change));
        }
        step *= 0.5;
    }
    None
}

/// Minimise `problem` from `x0` with `solver`, at most `max_iterations` iterations, stopping when
/// the gradient's max-norm is below `tolerance`·max(1, |E|).
///
/// # Errors
/// [`CoreError::NonFinite`] for a non-finite energy or step, [`CoreError::NotPositiveDefinite`]
/// when Newton's Hessian cannot be factorised.
pub fn solve(
    problem: &Problem,
    x0: &[f64],
    solver: Solver,
    max_iterations: usize,
    tolerance: f64,
) -> Result<(Vec<f64>, SolveReport)> {
    let n = problem.len();
    let mut x = x0.to_vec();
    let mut g = vec![0.0; n];
    let mut e = problem.energy(&x, Some(&mut g));
    if !e.is_finite() {
        return Err(CoreError::NonFinite {
            what: "alignment energy at the start",
        });
    }
    let initial_energy = e;
    let mut iterations = 0;
    let mut newton = match solver {
        Solver::Newton => Some(Newton::new(problem)?),
        Solver::Lbfgs => None,
    };
    #[expect(
        clippy::items_after_statements,
        reason = "L-BFGS's memory, next to its use"
    )]
    const MEMORY: usize = 10;
    let mut history: Vec<(Vec<f64>, Vec<f64>, f64)> = Vec::new(); // (s_k, y_k, 1/(y·s))
    while iterations < max_iterations && !gradient_small(&g, e, tolerance) {
        let dir = match newton.as_mut() {
            Some(system) => system.step(problem, &x, &g)?,
            None => lbfgs_direction(&g, &history),
        };
        let Some((mut x_new, mut change)) = line_search(problem, &x, &g, &dir) else {
            break; // no decrease possible at this precision: the minimum is reached
        };
        if newton.is_some() {
            change += problem.rescale_to_ray_minimum(&mut x_new);
        }
        let mut g_new = vec![0.0; n];
        problem.gradient(&x_new, &mut g_new);
        let e_new = e + change;
        if newton.is_none() {
            let s: Vec<f64> = x_new.iter().zip(&x).map(|(a, b)| a - b).collect();
            let y: Vec<f64> = g_new.iter().zip(&g).map(|(a, b)| a - b).collect();
            let ys = dot(&y, &s);
            if ys > 1e-300 {
                if history.len() == MEMORY {
                    history.remove(0);
                }
                history.push((s, y, 1.0 / ys));
            }
        }
        x = x_new;
        e = e_new;
        g = g_new;
        iterations += 1;
    }
    let converged = gradient_small(&g, e, tolerance);
    Ok((
        x,
        SolveReport {
            iterations,
            initial_energy,
            energy: e,
            gradient_norm: max_abs(&g),
            converged,
            samples: problem.samples(),
        },
    ))
}

/// L-BFGS two-loop recursion: an approximation of −H⁻¹g from the stored curvature pairs.
fn lbfgs_direction(g: &[f64], history: &[(Vec<f64>, Vec<f64>, f64)]) -> Vec<f64> {
    let mut q = g.to_vec();
    let mut alphas = Vec::with_capacity(history.len());
    for (s, y, rho) in history.iter().rev() {
        let alpha = rho * dot(s, &q);
        for (qi, yi) in q.iter_mut().zip(y) {
            *qi -= alpha * yi;
        }
        alphas.push(alpha);
    }
    let gamma = history
        .last()
        .map_or(1.0, |(s, y, _)| dot(s, y) / dot(y, y).max(1e-300));
    for qi in &mut q {
        *qi *= gamma;
    }
    for ((s, y, rho), alpha) in history.iter().zip(alphas.iter().rev()) {
        let beta = rho * dot(y, &q);
        for (qi, si) in q.iter_mut().zip(s) {
            *qi += (alpha - beta) * si;
        }
    }
    for v in &mut q {
        *v = -*v;
    }
    q
}

/// The symbolic Cholesky analysis of a Newton Hessian's sparsity pattern (lower triangle,
/// compressed columns), kept for the next solve of the same pattern: a robust level solves its
/// pattern again after each reweighting, and a video or a batch stitches the same layout (the
/// same overlap and prior sample cells) image after image. The analysis is a function of the
/// pattern alone, so a kept one gives the bits a fresh one gives.
struct Analysis {
    pattern: SymbolicSparseColMat<usize>,
    factorization: Factorization,
    llt: SymbolicCholesky<usize>,
}

/// How an [`Analysis`] orders and factorises its pattern.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Factorization {
    /// Approximate minimum degree order; faer's choice of numeric Cholesky by the flop count
    /// per factor entry.
    Auto,
    /// A tangent's block on a prior-only level: a `cols` × `rows` grid of nodes, two unknowns
    /// each (node `row·cols + col`), coupled at most one node away. Ordered by nested
    /// dissection ([`grid_dissection`]) and factorised with dense supernodes always. Dense
    /// supernodes are 2.5× faster here than faer's own choice, the simplicial one (at 2K: 23
    /// against 59 ms for the twenty blocks). The dissection has 5 % more factor entries than
    /// minimum degree on a 43 × 40 grid, but they fall in larger dense supernodes: its numeric
    /// factorisation takes about a quarter less time (1.6 against 2.1 ms per block).
    Grid { cols: usize, rows: usize },
}

/// Regions of the grid with at most this many nodes are not cut further by
/// [`grid_dissection`].
const DISSECTION_LEAF: usize = 12;

/// A nested-dissection order of a `cols` × `rows` grid whose nodes couple at most one node
/// away (the 9-point stencil of bilinear cells): each region is cut by its middle column or
/// row, across its longer side; the two halves come first, then the cut. The halves share no
/// term, so their factors stay apart, and the cuts end up as the dense supernodes at the root.
/// Returns the nodes (`row·cols + col`) in their new order.
fn grid_dissection(cols: usize, rows: usize) -> Vec<usize> {
    fn order(cols: usize, c: Range<usize>, r: Range<usize>, out: &mut Vec<usize>) {
        let (width, height) = (c.len(), r.len());
        if width * height <= DISSECTION_LEAF {
            out.extend(r.flat_map(|row| c.clone().map(move |col| row * cols + col)));
        } else if width >= height {
            let cut = c.start + width / 2;
            order(cols, c.start..cut, r.clone(), out);
            order(cols, cut + 1..c.end, r.clone(), out);
            out.extend(r.map(|row| row * cols + cut));
        } else {
            let cut = r.start + height / 2;
            order(cols, c.clone(), r.start..cut, out);
            order(cols, c.clone(), cut + 1..r.end, out);
            out.extend(c.map(|col| cut * cols + col));
        }
    }
    let mut out = Vec::with_capacity(cols * rows);
    order(cols, 0..cols, 0..rows, &mut out);
    out
}

/// How many analyses are kept (most recently used; a stitch with a prior uses a few patterns,
/// and one per tangent on its prior-only level).
const ANALYSES_KEPT: usize = 64;
/// Patterns larger than this many entries are not kept (their analysis holds about as much).
const ANALYSIS_MAX_ENTRIES: usize = 1 << 23;

static ANALYSES: Mutex<Vec<Arc<Analysis>>> = Mutex::new(Vec::new());

impl Analysis {
    /// The analysis of `pattern` (square, lower triangle), kept or made.
    fn of(pattern: SymbolicSparseColMat<usize>, factorization: Factorization) -> Result<Arc<Self>> {
        let same = |a: &Self| a.matches(&pattern, factorization);
        {
            let mut kept = ANALYSES.lock().unwrap_or_else(PoisonError::into_inner);
            if let Some(at) = kept.iter().position(|a| same(a)) {
                let hit = kept.remove(at);
                kept.push(Arc::clone(&hit));
                return Ok(hit);
            }
        }
        // Made outside the lock: other threads' solves need not wait for this one.
        let made = Self::fresh(pattern, factorization)?;
        if made.pattern.row_idx().len() > ANALYSIS_MAX_ENTRIES {
            return Ok(Arc::new(made));
        }
        let mut kept = ANALYSES.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(other) = kept
            .iter()
            .find(|a| a.matches(&made.pattern, made.factorization))
        {
            return Ok(Arc::clone(other)); // made by another thread meanwhile
        }
        let made = Arc::new(made);
        kept.push(Arc::clone(&made));
        if kept.len() > ANALYSES_KEPT {
            kept.remove(0);
        }
        Ok(made)
    }

    fn matches(&self, pattern: &SymbolicSparseColMat<usize>, factorization: Factorization) -> bool {
        self.factorization == factorization
            && self.pattern.nrows() == pattern.nrows()
            && self.pattern.col_ptr() == pattern.col_ptr()
            && self.pattern.row_idx() == pattern.row_idx()
    }

    /// The analysis of `pattern`, made now.
    fn fresh(pattern: SymbolicSparseColMat<usize>, factorization: Factorization) -> Result<Self> {
        let (threshold, order) = match factorization {
            Factorization::Auto => (SupernodalThreshold::AUTO, None),
            Factorization::Grid { cols, rows } if pattern.nrows() == 2 * cols * rows => {
                // Each node's two unknowns stay side by side.
                let forward: Vec<usize> = grid_dissection(cols, rows)
                    .into_iter()
                    .flat_map(|node| [2 * node, 2 * node + 1])
                    .collect();
                let mut inverse = vec![0; forward.len()];
                for (new, &old) in forward.iter().enumerate() {
                    inverse[old] = new;
                }
                (
                    SupernodalThreshold::FORCE_SUPERNODAL,
                    Some((forward, inverse)),
                )
            }
            // Not a grid of that size (never, by construction): minimum degree is still exact.
            Factorization::Grid { .. } => {
                debug_assert!(false, "{factorization:?} for {} unknowns", pattern.nrows());
                (SupernodalThreshold::FORCE_SUPERNODAL, None)
            }
        };
        let params = CholeskySymbolicParams {
            supernodal_flop_ratio_threshold: threshold,
            ..Default::default()
        };
        let ordering = match &order {
            Some((forward, inverse)) => {
                SymmetricOrdering::Custom(PermRef::new_checked(forward, inverse, forward.len()))
            }
            None => SymmetricOrdering::Amd,
        };
        let llt = factorize_symbolic_cholesky(pattern.as_ref(), Side::Lower, ordering, params)
            .map_err(|e| CoreError::NotPositiveDefinite {
                what: "the alignment Hessian",
                detail: format!("Cholesky analysis failed: {e:?}"),
            })?;
        Ok(Self {
            pattern,
            factorization,
            llt,
        })
    }

    /// Solve H·X = `rhs` in place, H symmetric with this analysis' pattern and `values` (lower
    /// triangle). Sequential: the callers run it on every core already, or between parallel
    /// evaluations (docs/architecture.md, "Threading").
    fn solve_in_place(&self, values: &[f64], rhs: MatMut<'_, f64>) -> Result<()> {
        let par = Par::Seq;
        let failed = |detail: String| CoreError::NotPositiveDefinite {
            what: "the alignment Hessian",
            detail,
        };
        let matrix = SparseColMatRef::new(self.pattern.as_ref(), values);
        let mut factor = vec![0.0; self.llt.len_val()];
        let scratch = StackReq::any_of(&[
            self.llt
                .factorize_numeric_llt_scratch::<f64>(par, Spec::default()),
            self.llt.solve_in_place_scratch::<f64>(rhs.ncols(), par),
        ]);
        let mut buffer = MemBuffer::try_new(scratch).map_err(|e| failed(format!("{e:?}")))?;
        let stack = MemStack::new(&mut buffer);
        let llt = self
            .llt
            .factorize_numeric_llt(
                &mut factor,
                matrix,
                Side::Lower,
                LltRegularization::default(),
                par,
                stack,
                Spec::default(),
            )
            .map_err(|e| failed(format!("{e:?}")))?;
        llt.solve_in_place_with_conj(Conj::No, rhs, par, stack);
        Ok(())
    }
}

/// The Newton system of a problem: one sparse Cholesky over all unknowns, or, when the
/// tangents share no term but the prior's (α, β) (a prior-only level: no overlap samples), one per
/// tangent and the 2 × 2 Schur complement of (α, β).
enum Newton {
    Global(NewtonSystem),
    Tangents(TangentSystems),
}

impl Newton {
    fn new(problem: &Problem) -> Result<Self> {
        if problem.samples() == 0 && problem.prior.is_some() {
            if let Some(systems) = TangentSystems::new(problem)? {
                return Ok(Self::Tangents(systems));
            }
        }
        Ok(Self::Global(NewtonSystem::new(problem)?))
    }

    fn step(&mut self, problem: &Problem, x: &[f64], g: &[f64]) -> Result<Vec<f64>> {
        match self {
            Self::Global(system) => system.step(problem, x, g),
            Self::Tangents(systems) => systems.step(problem, x, g),
        }
    }
}

/// One tangent's part of a [`TangentSystems`]: its Hessian block H_t (lower triangle,
/// compressed columns, local unknowns) and its coupling B_t to (α, β).
struct TangentBlock {
    analysis: Arc<Analysis>,
    constant: Vec<f64>,
    /// Position in `constant` of each local scale node's (s, s) diagonal entry.
    scale_diagonal: Vec<usize>,
    /// Row i: ∂²E/∂x_i∂α and ∂²E/∂x_i∂β.
    coupling: Vec<[f64; 2]>,
}

/// The Newton system of a problem whose Hessian is block diagonal over the tangents but for the
/// prior's (α, β) node (an arrow): per tangent H_t [u_t V_t] = [−g_t B_t], in parallel, then
/// (C − Σ B_tᵀV_t) δ_αβ = −g_αβ − Σ B_tᵀu_t and δ_t = u_t − V_t δ_αβ. The exact Newton step of
/// [`NewtonSystem`], with one small factorisation per tangent instead of one large one (a
/// prior-only level at 3° has 68,800 unknowns; the sums over tangents run in tangent order).
struct TangentSystems {
    tangents: Vec<TangentBlock>,
    /// Unknowns per tangent.
    per: usize,
    /// (α, β)'s own 2 × 2 block, row-major.
    prior_block: [f64; 4],
}

impl TangentSystems {
    /// None when a term couples two tangents (the arrow structure does not hold).
    fn new(problem: &Problem) -> Result<Option<Self>> {
        let nodes = problem.params.cols * problem.params.rows;
        let prior_node = problem.scale_nodes();
        if problem.len() != 2 * (prior_node + 1) || problem.tangents == 0 {
            return Ok(None);
        }
        let per = 2 * nodes;
        let mut prior_block = [0.0; 4];
        let row = |p: usize| {
            let range = problem.pattern.start[p]..problem.pattern.start[p + 1];
            problem.pattern.col[range.clone()]
                .iter()
                .zip(&problem.blocks[range])
        };
        for (&q, b) in row(prior_node) {
            if q as usize == prior_node {
                prior_block = *b;
            }
        }
        // The blocks in parallel (their analyses are kept: a lookup after the first stitch).
        let tangents: Option<Vec<TangentBlock>> = (0..problem.tangents)
            .into_par_iter()
            .map(|t| {
                let first = t * nodes;
                let mut col_ptr = Vec::with_capacity(per + 1);
                let mut row_idx = Vec::new();
                let mut constant = Vec::new();
                let mut scale_diagonal = Vec::with_capacity(nodes);
                let mut coupling = vec![[0.0; 2]; per];
                col_ptr.push(0usize);
                for local in 0..nodes {
                    let p = first + local;
                    for d in 0..2 {
                        let j = 2 * local + d;
                        for (&q, b) in row(p) {
                            let q = q as usize;
                            if q == prior_node {
                                coupling[j] = [b[2 * d], b[2 * d + 1]];
                                continue;
                            }
                            if q < first || q >= first + nodes {
                                return Ok(None); // a term between two tangents
                            }
                            for e in 0..2 {
                                let i = 2 * (q - first) + e;
                                if i >= j {
                                    if i == j && d == 0 {
                                        scale_diagonal.push(row_idx.len());
                                    }
                                    row_idx.push(i);
                                    constant.push(b[2 * d + e]);
                                }
                            }
                        }
                        col_ptr.push(row_idx.len());
                    }
                }
                let pattern = SymbolicSparseColMat::new_checked(per, per, col_ptr, None, row_idx);
                Ok(Some(TangentBlock {
                    analysis: Analysis::of(
                        pattern,
                        Factorization::Grid {
                            cols: problem.params.cols,
                            rows: problem.params.rows,
                        },
                    )?,
                    constant,
                    scale_diagonal,
                    coupling,
                }))
            })
            .collect::<Result<Option<Vec<_>>>>()?;
        let Some(tangents) = tangents else {
            return Ok(None);
        };
        Ok(Some(Self {
            tangents,
            per,
            prior_block,
        }))
    }

    fn step(&mut self, problem: &Problem, x: &[f64], g: &[f64]) -> Result<Vec<f64>> {
        let per = self.per;
        let curvature = 2.0 * problem.scale_weight;
        // Per tangent: u = H⁻¹(−g_t), V = H⁻¹B_t, and their products with B_tᵀ.
        let parts: Vec<(Mat<f64>, [f64; 4], [f64; 2])> = self
            .tangents
            .par_iter()
            .enumerate()
            .map(|(t, block)| {
                let offset = t * per;
                let mut values = block.constant.clone();
                for (node, &at) in block.scale_diagonal.iter().enumerate() {
                    let s = x[offset + 2 * node];
                    values[at] += curvature / (s * s * s);
                }
                let mut rhs = Mat::<f64>::from_fn(per, 3, |i, c| match c {
                    0 => -g[offset + i],
                    _ => block.coupling[i][c - 1],
                });
                block.analysis.solve_in_place(&values, rhs.as_mut())?;
                let (mut btv, mut btu) = ([0.0; 4], [0.0; 2]);
                for (i, b) in block.coupling.iter().enumerate() {
                    for (r, &br) in b.iter().enumerate() {
                        btu[r] += br * rhs[(i, 0)];
                        btv[2 * r] += br * rhs[(i, 1)];
                        btv[2 * r + 1] += br * rhs[(i, 2)];
                    }
                }
                Ok((rhs, btv, btu))
            })
            .collect::<Result<_>>()?;
        let at = g.len() - 2;
        let mut schur = self.prior_block;
        let mut right = [-g[at], -g[at + 1]];
        for (_, btv, btu) in &parts {
            for k in 0..4 {
                schur[k] -= btv[k];
            }
            right[0] -= btu[0];
            right[1] -= btu[1];
        }
        let det = schur[0] * schur[3] - schur[1] * schur[2];
        if !(det.is_finite() && det.abs() > f64::MIN_POSITIVE) {
            return Err(CoreError::NotPositiveDefinite {
                what: "the alignment Hessian",
                detail: "the prior's (alpha, beta) block is singular".into(),
            });
        }
        let da = (schur[3] * right[0] - schur[1] * right[1]) / det;
        let db = (schur[0] * right[1] - schur[2] * right[0]) / det;
        let mut dir = vec![0.0; g.len()];
        for (t, (rhs, _, _)) in parts.iter().enumerate() {
            for i in 0..per {
                dir[t * per + i] = rhs[(i, 0)] - rhs[(i, 1)] * da - rhs[(i, 2)] * db;
            }
        }
        dir[at] = da;
        dir[at + 1] = db;
        if dir.iter().any(|v| !v.is_finite()) {
            return Err(CoreError::NonFinite {
                what: "Newton step",
            });
        }
        Ok(dir)
    }
}

/// The exact Hessian in compressed-column form (lower triangle), with the constant part
/// (data, smoothness, gauge) assembled once and only the 1/s curvature updated per step, and
/// the symbolic Cholesky analysis done once.
struct NewtonSystem {
    analysis: Arc<Analysis>,
    constant: Vec<f64>,
    /// Position in the value array of each diagonal entry (2·node, 2·node).
    scale_diagonal: Vec<usize>,
}

impl NewtonSystem {
    fn new(problem: &Problem) -> Result<Self> {
        let n = problem.len();
        // H is symmetric, so column j of its lower triangle is row j of H from the diagonal on:
        // unknown 2p + d takes the (d, e) entries of node p's blocks with column 2q + e ≥ 2p + d.
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(2 * problem.blocks.len());
        let mut constant = Vec::with_capacity(2 * problem.blocks.len());
        let mut scale_diagonal = Vec::with_capacity(n / 2);
        col_ptr.push(0usize);
        for p in 0..n / 2 {
            let range = problem.pattern.start[p]..problem.pattern.start[p + 1];
            let row = problem.pattern.col[range.clone()]
                .iter()
                .zip(&problem.blocks[range]);
            for d in 0..2 {
                let j = 2 * p + d;
                for (&q, b) in row.clone() {
                    for e in 0..2 {
                        let i = 2 * q as usize + e;
                        if i >= j {
                            if i == j && d == 0 && p < problem.scale_nodes() {
                                scale_diagonal.push(row_idx.len());
                            }
                            row_idx.push(i);
                            constant.push(b[2 * d + e]);
                        }
                    }
                }
                col_ptr.push(row_idx.len());
            }
        }
        Ok(Self {
            analysis: Analysis::of(
                SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx),
                Factorization::Auto,
            )?,
            constant,
            scale_diagonal,
        })
    }

    /// The Newton direction −H(x)⁻¹ g.
    fn step(&mut self, problem: &Problem, x: &[f64], g: &[f64]) -> Result<Vec<f64>> {
        let mut values = self.constant.clone();
        for (node, &at) in self.scale_diagonal.iter().enumerate() {
            let s = x[2 * node];
            values[at] += 2.0 * problem.scale_weight / (s * s * s);
        }
        let mut rhs = Mat::<f64>::from_fn(g.len(), 1, |i, _| -g[i]);
        self.analysis.solve_in_place(&values, rhs.as_mut())?;
        let dir: Vec<f64> = (0..g.len()).map(|i| rhs[(i, 0)]).collect();
        if dir.iter().any(|v| !v.is_finite()) {
            return Err(CoreError::NonFinite {
                what: "Newton step",
            });
        }
        Ok(dir)
    }
}

/// Apply solved fields to the maps in place: D ← s(x)·D + o(x)·f(x) with bilinear s, o per
/// pixel and f the offset factor of `params.offsets`.
///
/// Row by row: the fields are first interpolated between the row's two grid rows at the grid
/// columns, then linearly along the row from a per-column cell table.
pub fn apply_fields(layout: &Layout, maps: &mut [f32], x: &[f64], params: &LevelParams) {
    let mut transform = Transform::new(layout, params.offsets);
    transform.fields(params, x.to_vec());
    transform.apply(maps);
}

/// One solved level: its parameters, fields (x, node-interleaved s/o) and report.
#[derive(Debug, Clone)]
pub struct Level {
    /// Parameters of the level.
    pub params: LevelParams,
    /// Solved fields, `x[2·node] = s`, `x[2·node + 1] = o`.
    pub fields: Vec<f64>,
    /// How the solve ended.
    pub report: SolveReport,
    /// Seconds spent building the level's problem.
    pub build_seconds: f64,
    /// Seconds spent solving it.
    pub solve_seconds: f64,
    /// The data-term weight of each valid overlap sample after the last reweighting (all 1
    /// with [`Loss::Squared`]).
    pub sample_weights: Vec<f32>,
    /// Index in the [`Overlaps`] of each entry of `sample_weights`.
    pub sample_origins: Vec<u32>,
    /// The residual scale σ of the last reweighting (0 with [`Loss::Squared`]).
    pub robust_scale: f64,
    /// With a prior: the solved (α, β) (after the mean-scale normalisation), the prior samples'
    /// IRLS weights and their median |residual| at the end.
    pub prior: Option<LevelPrior>,
}

/// What a level solved for the prior term.
#[derive(Debug, Clone)]
pub struct LevelPrior {
    /// α, β: the maps after this level match α·P + β (P the standardised prior).
    pub affine: (f64, f64),
    /// IRLS weight of each prior sample after the last reweighting.
    pub weights: Vec<f64>,
    /// Confidence of each prior sample.
    pub confidence: Vec<f64>,
    /// Median |residual| at the end.
    pub residual: f64,
    /// The weights a prior-only level starting from this level's result gives the prior
    /// samples (its judgement, [`Problem::reweight_prior`]), found here where the
    /// samples' views by the other tangents are at hand; empty on a prior-only level.
    pub trust: Vec<f64>,
}

/// What an alignment could do with the overlap samples it had.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fallback {
    /// Every level of the schedule ran.
    None,
    /// Some levels had too few samples for their grid and were left out; the coarser ones ran.
    CoarserGrid,
    /// No level of the schedule had enough samples; one per-tangent affine level ran (a 2x2
    /// grid held flat by a strong smoothness).
    Affine,
    /// Too few samples even for a per-tangent affine map: the tangents are only standardised
    /// (each one's median and mean absolute deviation matched), not aligned.
    Unaligned,
}

impl Fallback {
    /// The name reports and sidecars use.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::CoarserGrid => "coarser_grid",
            Self::Affine => "affine",
            Self::Unaligned => "unaligned",
        }
    }
}

/// The result of [`align`]: the levels solved and the fallback taken.
#[derive(Debug, Clone)]
pub struct Alignment {
    /// The levels that ran, coarse to fine.
    pub levels: Vec<Level>,
    /// Whether the schedule had to be cut short for lack of overlap samples.
    pub fallback: Fallback,
    /// What was fitted to the prior (None without a prior or when no level ran).
    pub prior: Option<PriorFit>,
}

/// The share of each tangent's pixels the prior samples keep: as many as the overlap samples
/// keep on a 2K tangent (`sample_fraction` of [`SAMPLE_BUDGET_PIXELS`]; twice that gave the same
/// accuracy for 0.07 s more at 2K, docs/method.md "Global prior"), and on smaller tangents
/// twice the overlap samples' share, up to that count. Below 2K this is the rule the prior
/// samples had before: the prior-only level (one sample per [`NODES_PER_SAMPLE`] of its nodes
/// in every tangent) runs at 1K, where real photos need it, and is skipped on tangents of the
/// 512-px layout, where with a wrong prior it followed the wrong region (tests/test_prior.py).
fn prior_sample_fraction(layout: &Layout, sample_fraction: f64) -> f64 {
    let (h, w) = layout.tangent_shape();
    let pixels = (h * w).max(1) as f64;
    let budget = SAMPLE_BUDGET_PIXELS as f64;
    let count = sample_fraction * (2.0 * pixels).min(budget);
    (count / pixels.min(budget)).min(1.0)
}

/// A level's grid is solved only with at least one valid overlap sample per this many grid nodes
/// (all tangents together); below it the data cannot support the grid. (The smoothness term
/// carries sparse data between samples: the paper's 16x14 level at ERP width 512 has about one
/// sample per two nodes and still aligns.)
pub const NODES_PER_SAMPLE: usize = 4;

/// Smoothness of the per-tangent affine fallback level: with it the 2x2 grid stays flat (one
/// scale and offset per tangent) to well below the data's resolution.
const AFFINE_SMOOTHNESS: f64 = 1e4;

/// Options of a whole alignment, every default resolved.
#[derive(Debug, Clone, PartialEq)]
pub struct Options {
    /// (cols, rows) grid nodes per tangent of each level, coarse to fine.
    pub levels: Vec<(usize, usize)>,
    /// Which energy.
    pub energy: Energy,
    /// Which solver.
    pub solver: Solver,
    /// Iteration cap per level.
    pub iterations: usize,
    /// Converged when the gradient's max-norm ≤ tolerance · max(1, |E|).
    pub tolerance: f64,
    /// Fraction of overlap pixels the data term uses, chosen deterministically.
    pub sample_fraction: f64,
    /// Overlap samples within this many degrees of either pole are left out.
    pub pole_cap_deg: f64,
    /// Weight of the smoothness term.
    pub smoothness: f64,
    /// Weight of the 1/s term.
    pub scale_weight: f64,
    /// Where the offset acts.
    pub offsets: Offsets,
    /// The data term's loss.
    pub loss: Loss,
    /// Weight λ of the prior term (used only with a prior).
    pub prior_weight: f64,
    /// Frequency split of the prior term, in degrees: the finest scale the prior dictates.
    /// After the schedule a prior-only level with grid nodes this far apart runs (when finer
    /// than the schedule's last grid), and the tangents' values compared with the prior are
    /// averaged over half this radius, so finer detail stays the tangents' (used only with a
    /// prior; 0: no prior-only level, point values).
    pub prior_scale_deg: f64,
    /// Whether the prior is fused with the tangents' own low frequencies (used only with a
    /// prior).
    pub prior_fusion: PriorFusion,
}

impl Options {
    /// Default relative gradient tolerance.
    pub const DEFAULT_TOLERANCE: f64 = 1e-6;
    /// The paper's share of overlap pixels in the data term.
    pub const DEFAULT_SAMPLE_FRACTION: f64 = 0.01;
    /// Default weight of the prior term (benches/bench_prior.py; docs/method.md, "Global prior").
    pub const DEFAULT_PRIOR_WEIGHT: f64 = 1.0;
    /// Default frequency split of the prior term, degrees: 3° measured better than 4° on every
    /// case of benches/bench_prior.py at 2K and 4K, and 2.5° no better than 3°.
    pub const DEFAULT_PRIOR_SCALE_DEG: f64 = 3.0;
    /// Largest frequency split, degrees.
    pub const MAX_PRIOR_SCALE_DEG: f64 = 30.0;

    /// The defaults of `energy` with `solver`: its schedule, weights and offsets.
    #[must_use]
    pub fn new(energy: Energy, solver: Solver) -> Self {
        let (smoothness, scale_weight) = energy.default_weights();
        Self {
            levels: energy.default_schedule().to_vec(),
            energy,
            solver,
            iterations: solver.default_iterations(),
            tolerance: Self::DEFAULT_TOLERANCE,
            sample_fraction: Self::DEFAULT_SAMPLE_FRACTION,
            pole_cap_deg: 0.0,
            smoothness,
            scale_weight,
            offsets: energy.default_offsets(),
            loss: energy.default_loss(),
            prior_weight: Self::DEFAULT_PRIOR_WEIGHT,
            prior_scale_deg: Self::DEFAULT_PRIOR_SCALE_DEG,
            prior_fusion: PriorFusion::Auto,
        }
    }

    /// `self` if every value is usable (and every grid fits a tangent of `tangent_shape`
    /// = (h, w) when given), else the first problem, naming the option.
    ///
    /// # Errors
    /// [`CoreError::InvalidOption`] naming the option at fault.
    pub fn validate(self, tangent_shape: Option<(usize, usize)>) -> Result<Self> {
        if self.levels.is_empty() {
            return Err(CoreError::option(
                "align",
                "an alignment schedule needs at least one (cols, rows) grid",
            ));
        }
        for &(cols, rows) in &self.levels {
            if cols < 2 || rows < 2 {
                return Err(CoreError::option(
                    "align",
                    format!(
                        "alignment grid ({cols}, {rows}) needs at least 2 x 2 nodes (cols, rows)"
                    ),
                ));
            }
            if let Some((h, w)) = tangent_shape {
                if cols > w || rows > h {
                    return Err(CoreError::option(
                        "align",
                        format!(
                            "alignment grid ({cols}, {rows}) has more nodes than the tangent has \
                             pixels ({w}x{h})"
                        ),
                    ));
                }
            }
        }
        check_iterations("iterations", self.iterations, 0)?;
        check_range("tolerance", self.tolerance, 0.0, f64::MAX)?;
        check_range("sample_fraction", self.sample_fraction, 0.0, 1.0)?;
        check_range("pole_cap_deg", self.pole_cap_deg, 0.0, MAX_POLE_CAP_DEG)?;
        check_range("smoothness", self.smoothness, 0.0, f64::MAX)?;
        check_positive(
            "scale_weight",
            self.scale_weight,
            "it keeps the scales from 0",
        )?;
        check_range("prior_weight", self.prior_weight, 0.0, f64::MAX)?;
        check_range(
            "prior_scale_deg",
            self.prior_scale_deg,
            0.0,
            Self::MAX_PRIOR_SCALE_DEG,
        )?;
        Ok(self)
    }

    /// The parameters of each level.
    #[must_use]
    pub fn level_params(&self) -> Vec<LevelParams> {
        self.levels
            .iter()
            .map(|&(cols, rows)| LevelParams {
                cols,
                rows,
                energy: self.energy,
                smoothness: self.smoothness,
                scale_weight: self.scale_weight,
                offsets: self.offsets,
            })
            .collect()
    }
}

impl Default for Options {
    fn default() -> Self {
        Self::new(Energy::default(), Solver::default())
    }
}

/// Align spherical disparity maps (N·h·w, NaN = invalid) in place.
///
/// Each tangent is standardised, then every level is solved from identity fields on the maps
/// as the previous level left them, and its fields are applied before the next level (so no
/// deformation is ever applied twice: reference pitfall B3, docs/reference-pitfalls.md). With a
/// robust [`Loss`] each level is reweighted and solved again [`ROBUST_ROUNDS`] times.
/// Finally the common standardisation is undone with the mean median and spread of the inputs,
/// so the result is in the inputs' range.
///
/// The steps are composed, not applied one by one: a level reads the maps as the earlier steps
/// leave them at its overlap samples only, and the stack is written once at the end (the
/// `transform` module: the same numbers as applying each step in turn, in one pass).
///
/// Degrades instead of failing: a level with fewer than one valid overlap sample per
/// [`NODES_PER_SAMPLE`] grid nodes is left out; when no level is left, one per-tangent affine level runs
/// if the samples support it, else the tangents stay standardised only ([`Fallback`]).
///
/// # Errors
/// Those of [`standardize`] and [`solve`].
pub fn align(
    layout: &Layout,
    maps: &mut [f32],
    overlaps: &Overlaps,
    options: &Options,
) -> Result<Alignment> {
    align_with_prior(layout, maps, overlaps, options, None)
}

/// [`align`] with a global `prior` term when given (docs/method.md, "Global prior"): every
/// level also pulls each tangent's low-passed disparity at the prior samples towards α·P + β,
/// (α, β) solved jointly; with an absolute prior the result is in the prior's units.
///
/// # Errors
/// Those of [`align`], and those of [`PriorSamples::build`].
pub fn align_with_prior(
    layout: &Layout,
    maps: &mut [f32],
    overlaps: &Overlaps,
    options: &Options,
    prior: Option<&Prior>,
) -> Result<Alignment> {
    let (alignment, transform) = solve_levels(layout, maps, overlaps, options, prior)?;
    transform.apply(maps);
    Ok(alignment)
}

/// [`align`] from `maps` into `out` (the same size), leaving `maps` as they are.
///
/// # Errors
/// Those of [`align`].
///
/// # Panics
/// If `out` is not as long as `maps`.
pub fn align_into(
    layout: &Layout,
    maps: &[f32],
    out: &mut [f32],
    overlaps: &Overlaps,
    options: &Options,
) -> Result<Alignment> {
    align_into_with_prior(layout, maps, out, overlaps, options, None)
}

/// [`align_with_prior`] from `maps` into `out` (the same size), leaving `maps` as they are.
///
/// # Errors
/// Those of [`align_with_prior`].
///
/// # Panics
/// If `out` is not as long as `maps`.
pub fn align_into_with_prior(
    layout: &Layout,
    maps: &[f32],
    out: &mut [f32],
    overlaps: &Overlaps,
    options: &Options,
    prior: Option<&Prior>,
) -> Result<Alignment> {
    assert_eq!(maps.len(), out.len(), "output size");
    let (alignment, transform) = solve_levels(layout, maps, overlaps, options, prior)?;
    transform.apply_into(maps, out);
    Ok(alignment)
}

/// The levels of [`align`] and the transform that applies them (with the standardisation and
/// its undoing) to `maps`, which are only read.
fn solve_levels(
    layout: &Layout,
    maps: &[f32],
    overlaps: &Overlaps,
    options: &Options,
    prior: Option<&Prior>,
) -> Result<(Alignment, Transform)> {
    let mut transform = Transform::new(layout, options.offsets);
    let stats = standardize_stats(layout, maps, transform.factors())?;
    transform.standardize(stats.clone());
    let n = layout.cameras.len();
    let mut levels: Vec<Level> = Vec::with_capacity(options.levels.len());
    let mut skipped = false;
    let schedule = options.level_params();
    let (prior_samples, first) = prior_samples_beside_first_level(
        layout,
        maps,
        &mut transform,
        overlaps,
        &schedule,
        options,
        prior,
    )?;
    let solved_first = usize::from(!matches!(first, FirstLevel::Ahead));
    match first {
        FirstLevel::Solved(level) => levels.push(*level),
        FirstLevel::Skipped => skipped = true,
        FirstLevel::Ahead => {}
    }
    let prior_term = prior_samples.as_ref().map(|p| (p, options.prior_weight));
    // The units the alignment restores (the tangents' mean median and spread).
    let frame = common_frame(&stats);
    let mut fusion: Option<Fusion> = None;
    for (i, params) in schedule.iter().enumerate().skip(solved_first) {
        let t0 = std::time::Instant::now();
        let samples = fusion
            .as_ref()
            .and_then(|f| f.samples.as_ref())
            .or(prior_samples.as_ref());
        // The prior joins from the schedule's second solved level: the first one, solved
        // without it, is the tangents' own consensus, against which the prior is judged
        // before it can pull them (`prior_start`). A schedule of one level takes it there.
        let joins = !levels.is_empty() || i + 1 == schedule.len();
        let term = samples.map(|p| (p, options.prior_weight)).filter(|_| joins);
        let mut problem = level_problem(layout, maps, &transform, overlaps, *params, term, true);
        if fusion.is_none() && options.prior_fusion == PriorFusion::Auto {
            fusion = fuse_as_prior_joins(&mut problem, prior_samples.as_ref(), &levels, frame);
        }
        match solve_supported(
            layout,
            maps,
            &mut transform,
            overlaps,
            problem,
            &levels,
            options,
            t0,
        )? {
            Some(level) => levels.push(level),
            None => skipped = true,
        }
    }
    // The frequency split: a finer level on which only the prior (and the smoothness) acts, so
    // the prior dictates down to `prior_scale_deg` while the tangents keep the detail below.
    let fused = fusion.as_ref().and_then(|f| f.samples.as_ref());
    if let Some(samples) = fused.or(prior_samples.as_ref()) {
        if let Some(level) =
            prior_only_level(layout, maps, &mut transform, samples, &levels, options)?
        {
            levels.push(level);
        }
    }
    let mut fallback = if skipped {
        Fallback::CoarserGrid
    } else {
        Fallback::None
    };
    if levels.is_empty() {
        let t0 = std::time::Instant::now();
        let mut params = options.level_params()[0];
        params.cols = 2;
        params.rows = 2;
        params.smoothness = params.smoothness.max(AFFINE_SMOOTHNESS);
        let problem = level_problem(layout, maps, &transform, overlaps, params, prior_term, true);
        if (problem.samples() + problem.prior_samples()) * NODES_PER_SAMPLE >= n * 4 {
            let start = prior_start(
                layout, maps, &transform, overlaps, &problem, &levels, options,
            )?;
            let level = solve_level(&mut transform, problem, options, t0, start, None)?;
            levels.push(level);
            fallback = Fallback::Affine;
        } else {
            fallback = Fallback::Unaligned;
        }
    }
    let fit = prior_samples
        .as_ref()
        .zip(levels.last().and_then(|l| l.prior.as_ref()))
        .map(|(samples, level)| {
            prior_fit(samples, level, frame, options.prior_weight, fusion.as_ref())
        });
    let (spread, median) = fit.as_ref().map_or(frame, |f| f.0);
    transform.restore(spread, median);
    Ok((
        Alignment {
            levels,
            fallback,
            prior: fit.map(|f| f.1),
        },
        transform,
    ))
}

/// The schedule's first level, as [`prior_samples_beside_first_level`] leaves it.
enum FirstLevel {
    /// Not solved yet (no prior, or a schedule of one level, which the prior joins).
    Ahead,
    /// Solved without the prior.
    Solved(Box<Level>),
    /// Too few samples to support its grid.
    Skipped,
}

/// The prior's samples, and the schedule's first level when it is solved without the prior,
/// that is when another level follows (`solve_levels`). That solve and the samples' build are
/// independent, so they run side by side, the build on the cores the level's serial parts leave
/// idle (5–9 ms less per stitch at 2K, medians of 25 interleaved runs; the same bits).
fn prior_samples_beside_first_level(
    layout: &Layout,
    maps: &[f32],
    transform: &mut Transform,
    overlaps: &Overlaps,
    schedule: &[LevelParams],
    options: &Options,
    prior: Option<&Prior>,
) -> Result<(Option<PriorSamples>, FirstLevel)> {
    let build_samples = || {
        prior
            .map(|p| {
                PriorSamples::build(
                    layout,
                    maps,
                    p,
                    prior_sample_fraction(layout, options.sample_fraction),
                    0.5 * options.prior_scale_deg,
                )
            })
            .transpose()
    };
    match schedule.first() {
        Some(params) if prior.is_some() && schedule.len() > 1 => {
            let (samples, first) = rayon::join(build_samples, || {
                let t0 = std::time::Instant::now();
                let problem = level_problem(layout, maps, transform, overlaps, *params, None, true);
                solve_supported(layout, maps, transform, overlaps, problem, &[], options, t0)
            });
            let samples = samples?; // its error first, as when built before the level
            let first = first?.map_or(FirstLevel::Skipped, |l| FirstLevel::Solved(Box::new(l)));
            Ok((samples, first))
        }
        _ => Ok((build_samples()?, FirstLevel::Ahead)),
    }
}

/// Solve a level of the schedule whose `problem` was built from `t0` on after the solved
/// `levels` ([`solve_level`] from [`prior_start`]), or None when its samples are too few to
/// support its grid (the level is skipped). Prior samples support a grid as overlap samples do
/// (a partial panorama with little overlap can still be aligned to its prior).
#[expect(
    clippy::too_many_arguments,
    reason = "a level's inputs, passed through"
)]
fn solve_supported(
    layout: &Layout,
    maps: &[f32],
    transform: &mut Transform,
    overlaps: &Overlaps,
    problem: Problem,
    levels: &[Level],
    options: &Options,
    t0: std::time::Instant,
) -> Result<Option<Level>> {
    let params = problem.params;
    let support = problem.samples() + problem.prior_samples();
    if support * NODES_PER_SAMPLE < layout.cameras.len() * params.cols * params.rows {
        return Ok(None);
    }
    let start = prior_start(layout, maps, transform, overlaps, &problem, levels, options)?;
    solve_level(transform, problem, options, t0, start, None).map(Some)
}

/// The prior fused with the tangents' own low frequencies where they agree well enough
/// ([`PriorSamples::fused`]), when `problem` is the level the prior joins after the schedule's
/// first level, solved without it, left the tangents as their own consensus: read off the
/// problem's prior samples and their views (this level's transform, as a pass of its own would
/// read them), the fused values then replace the prior's in the problem. None otherwise.
fn fuse_as_prior_joins(
    problem: &mut Problem,
    samples: Option<&PriorSamples>,
    levels: &[Level],
    frame: (f64, f64),
) -> Option<Fusion> {
    let samples = samples.filter(|_| matches!(levels, [first] if first.prior.is_none()))?;
    let consensus = problem.prior_consensus(samples.len())?;
    let fusion = samples.fused(
        &consensus,
        || problem.consensus_variance(samples.len()),
        frame,
    )?;
    if let Some(fused) = &fusion.samples {
        problem.set_prior_values(&fused.value);
        problem.set_prior_confidence(&fused.confidence);
    }
    Some(fusion)
}

/// (spread, median) the alignment restores: the tangents' mean median and mean spread (constant
/// tangents, spread 0, say nothing about the scale).
fn common_frame(stats: &[(f64, f64)]) -> (f64, f64) {
    let median = stats.iter().map(|s| s.0).sum::<f64>() / stats.len() as f64;
    let varied = stats.iter().filter(|s| s.1 > 0.0).count();
    let spread = if varied == 0 {
        1.0
    } else {
        stats.iter().map(|s| s.1).sum::<f64>() / varied as f64
    };
    (spread, median)
}

/// The frequency split's prior-only level after the schedule's `levels`, when its grid is finer
/// than theirs and every tangent has a prior sample per 4 of its nodes.
fn prior_only_level(
    layout: &Layout,
    maps: &[f32],
    transform: &mut Transform,
    samples: &PriorSamples,
    levels: &[Level],
    options: &Options,
) -> Result<Option<Level>> {
    let Some(last) = levels.last() else {
        return Ok(None);
    };
    let Some(params) = prior_level_params(layout, options, &last.params) else {
        return Ok(None);
    };
    let per_tangent = params.cols * params.rows;
    let mut counts = vec![0usize; layout.cameras.len()];
    for &t in &samples.tangent {
        counts[t as usize] += 1;
    }
    if counts.iter().any(|&c| c * NODES_PER_SAMPLE < per_tangent) {
        return Ok(None);
    }
    let t0 = std::time::Instant::now();
    let empty = Overlaps::default();
    let term = Some((samples, options.prior_weight));
    // Judged by the last level (its `trust`): the samples' views are not needed. Its samples
    // are these (the same maps, the same filter); were they not, judge them here.
    let trust = last.prior.as_ref().map(|p| p.trust.clone());
    #[cfg(test)]
    let trust = trust.filter(|_| !JUDGE_AFRESH.with(std::cell::Cell::get));
    let build = |views| level_problem(layout, maps, transform, &empty, params, term, views);
    let mut problem = build(trust.is_none());
    let trust = match trust {
        Some(t) if t.len() == problem.prior_samples() => Some(t),
        Some(_) => {
            problem = build(true);
            None
        }
        None => None,
    };
    let start = prior_start(layout, maps, transform, &empty, &problem, levels, options)?;
    solve_level(transform, problem, options, t0, start, trust).map(Some)
}

#[cfg(test)]
thread_local! {
    /// Tests only: the prior-only level judges its samples itself instead of inheriting the
    /// last level's judgement (`prior::tests`, which checks that both agree).
    pub(crate) static JUDGE_AFRESH: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// The restore (spread, median) of an alignment with a prior and what was fitted: an absolute
/// prior's units replace the tangents' mean units (`frame`), and the fusion is reported.
fn prior_fit(
    samples: &PriorSamples,
    level: &LevelPrior,
    frame: (f64, f64),
    weight: f64,
    fusion: Option<&Fusion>,
) -> ((f64, f64), PriorFit) {
    let (alpha, beta) = level.affine;
    let (p_median, p_spread) = samples.stats;
    // The maps now match α·(P − m_P)/s_P + β; as the result, v·spread + median.
    let (mut spread, mut median) = frame;
    if samples.absolute && alpha.abs() > f64::MIN_POSITIVE {
        // Express the result in the prior's units: v ← ((v − β)/α)·s_P + m_P.
        spread = p_spread / alpha;
        median = p_median - beta * p_spread / alpha;
    }
    let a = alpha * spread / p_spread;
    let b = (beta - alpha * p_median / p_spread) * spread + median;
    let pull: f64 = level.confidence.iter().sum();
    let lost: f64 = level
        .confidence
        .iter()
        .zip(&level.weights)
        .filter(|(_, &w)| w < 0.5)
        .map(|(c, _)| c)
        .sum();
    (
        (spread, median),
        PriorFit {
            affine: (a, b),
            samples: level.weights.len(),
            outvoted: if pull > 0.0 { lost / pull } else { 0.0 },
            weight,
            residual: level.residual,
            tangent_spread: fusion.map(|f| f.spread),
            tangent_share: fusion.map_or(0.0, |f| f.share),
            consensus_outvoted: fusion.map_or(0.0, |f| f.outvoted),
            low_order_gap: fusion.map_or(0.0, |f| f.low_order_gap),
            low_order_share: fusion.map_or(0.0, |f| f.low_order_share),
        },
    )
}

/// The problem of a level on `maps` as `transform` leaves them (`views`: see
/// [`Problem::unassembled`]).
fn level_problem(
    layout: &Layout,
    maps: &[f32],
    transform: &Transform,
    overlaps: &Overlaps,
    params: LevelParams,
    prior: Option<(&PriorSamples, f64)>,
    views: bool,
) -> Problem {
    let view = Transformed { maps, transform };
    // With a prior, `solve_level` reweights it (and so assembles) before the first solve.
    let mut problem = Problem::unassembled(layout, &view, overlaps, params, prior, views);
    if prior.is_none() {
        problem.assemble();
    }
    problem
}

/// The prior-only level of the frequency split: grid nodes `prior_scale_deg` apart over a
/// tangent's field of view, when that is finer than the `last` level's grid.
fn prior_level_params(
    layout: &Layout,
    options: &Options,
    last: &LevelParams,
) -> Option<LevelParams> {
    if options.prior_scale_deg <= 0.0 || options.prior_weight <= 0.0 {
        return None;
    }
    let cam = layout.cameras.first()?;
    let fov = |pixels: usize, focal: f64| 2.0 * (pixels as f64 / (2.0 * focal)).atan().to_degrees();
    let nodes = |deg: f64| (deg / options.prior_scale_deg).ceil() as usize + 1;
    let (h, w) = layout.tangent_shape();
    let cols = nodes(fov(w, cam.fx)).min(w);
    let rows = nodes(fov(h, cam.fy)).min(h);
    (cols > last.cols && rows > last.rows).then_some(LevelParams {
        cols,
        rows,
        smoothness: last.smoothness * PRIOR_LEVEL_SMOOTHNESS,
        scale_weight: last.scale_weight * PRIOR_LEVEL_BARRIER,
        ..*last
    })
}

/// The prior-only level's smoothness, relative to the schedule's: a bump of the fields costs
/// the same Dirichlet energy whatever its size, so at the schedule's smoothness the prior could
/// not move a region of a tenth of a tangent; this lets it, down to the level's node spacing.
/// On 4 synthetic rooms (2K / 4K; content errors, affine errors, the wrong prior), slope held:
/// 1/100 gave 0.0128 / 0.0133, 0.0100 / 0.0091, 0.0260 / 0.0249 (slack 0.3); 3/1000 gives
/// 0.0124 / 0.0124, 0.0097 / 0.0090, 0.0274 / 0.0258 (slack 0.2), and on the real photos the
/// same or larger gains (docs/method.md, "On real networks").
const PRIOR_LEVEL_SMOOTHNESS: f64 = 0.003;

/// The prior-only level's 1/s weight, relative to the schedule's. With its slope held
/// ([`Problem::hold_prior_slope`]) the prior fixes the fields' scale there, and a full barrier
/// would fight it (pushing every s up against the prior's pull: 0.0129 → 0.0144 under content
/// errors at 2K); a hundredth keeps the Hessian positive definite where a tangent lost its
/// samples.
const PRIOR_LEVEL_BARRIER: f64 = 0.01;

/// The prior-only level's pull towards identity fields (the maps as the schedule aligned them),
/// relative to the prior term ([`Problem::damp_fields`]). Without it nothing but the weak
/// smoothness resisted the prior there: the fields followed the prior's own smooth error, and
/// where a wrong region's samples had lost their pull they were interpolated from its edges,
/// so the level carried the wrong region in (a prior 30 % wrong on a fifth of the sphere, one
/// room at 2K: 0.027 at 3°, 0.11 at 10°; damped 0.020 at 3°). On 4
/// synthetic rooms at 2K (content errors, affine errors, the wrong prior; none: 0.0124, 0.0097,
/// 0.0280): 0.03 gave 0.0120, 0.0096, 0.0227; 0.05 0.0120, 0.0096, 0.0221; 0.1 0.0121, 0.0096,
/// 0.0216; 0.3 0.0124, 0.0098, 0.0213; 1 0.0132, 0.0099, 0.0212 (docs/method.md, "Global
/// prior").
const PRIOR_LEVEL_DAMPING: f64 = 0.05;

/// Where a level with a prior starts: identity fields, with (α, β) from the previous level if
/// it had the prior; else (α, β) fitted robustly to the tangents' own consensus, so the prior's
/// first weights judge it against the tangents before it could pull them: the maps as the
/// previous levels left them, or, on the first level, this level solved without the prior.
/// None without a prior.
fn prior_start(
    layout: &Layout,
    maps: &[f32],
    transform: &Transform,
    overlaps: &Overlaps,
    problem: &Problem,
    levels: &[Level],
    options: &Options,
) -> Result<Option<Vec<f64>>> {
    if problem.prior.is_none() {
        return Ok(None);
    }
    let mut x = problem.identity();
    let at = x.len() - 2;
    if let Some(prev) = levels.last().and_then(|l| l.prior.as_ref()) {
        x[at] = prev.affine.0;
        x[at + 1] = prev.affine.1;
        return Ok(Some(x));
    }
    if levels.is_empty() {
        let alone = level_problem(
            layout,
            maps,
            transform,
            overlaps,
            problem.params,
            None,
            true,
        );
        if alone.samples() * NODES_PER_SAMPLE >= alone.scale_nodes() {
            let (fields, _) = solve(
                &alone,
                &alone.identity(),
                options.solver,
                options.iterations,
                options.tolerance,
            )?;
            x[..at].copy_from_slice(&fields);
        }
    }
    if let Some((alpha, beta)) = problem.fit_prior_affine(&x) {
        x[at] = alpha;
        x[at + 1] = beta;
    }
    Ok(Some(x))
}

/// Solve one level's `problem` (built from `t0` on) from `start` (identity fields when None),
/// reweighting it for a robust loss, and add its fields to `transform`. A prior-only level
/// takes its prior samples' weights from `trust` when given (the level before judged them).
fn solve_level(
    transform: &mut Transform,
    mut problem: Problem,
    options: &Options,
    t0: std::time::Instant,
    start: Option<Vec<f64>>,
    trust: Option<Vec<f64>>,
) -> Result<Level> {
    let params = problem.params;
    let t1 = std::time::Instant::now();
    let start = start.unwrap_or_else(|| problem.identity());
    // A prior-only level (the frequency split's, no overlap samples) judges the prior once, at
    // its start (the tangents as the schedule aligned them): reweighted from its own solution
    // it would trust whatever it had just followed.
    let prior_only = problem.prior.is_some() && problem.samples() == 0;
    if let Some(node) = problem.prior.as_ref().map(|p| 2 * p.node as usize) {
        if prior_only {
            problem.hold_prior_slope(start[node]);
            problem.damp_fields(PRIOR_LEVEL_DAMPING);
        }
        match (trust, problem.prior.as_mut()) {
            (Some(weights), Some(prior)) if prior_only => {
                prior.weights = weights;
                problem.assemble();
            }
            _ => {
                problem.reweight_prior(&start);
            }
        }
    }
    let (mut fields, mut report) = solve(
        &problem,
        &start,
        options.solver,
        options.iterations,
        options.tolerance,
    )?;
    let mut robust_scale = 0.0;
    // The prior's samples are always judged again (`Problem::reweight_prior`): a prior is
    // wrong on whole regions (windows, mirrors, sky), whatever the data term's loss.
    let has_prior = problem.prior.is_some();
    if (options.loss != Loss::Squared || has_prior) && !prior_only {
        let rounds = problem.robust_rounds();
        for _ in 0..rounds {
            // Both weights depend on `fields` only: the Hessian is assembled once for both.
            if options.loss == Loss::Squared {
                problem.reweight_prior(&fields);
            } else {
                if has_prior {
                    problem.set_prior_weights(&fields);
                }
                robust_scale = problem.reweight(&fields, options.loss);
            }
            let (next, next_report) = solve(
                &problem,
                &fields,
                options.solver,
                options.iterations,
                options.tolerance,
            )?;
            fields = next;
            report = SolveReport {
                iterations: report.iterations + next_report.iterations,
                initial_energy: report.initial_energy,
                ..next_report
            };
        }
    }
    // Only the 1/s term fixes the global scale, weakly: dividing by the mean scale keeps
    // the maps in standardised units from level to level (a global factor aligns nothing).
    // The paper applies its fields as they are.
    // With a prior the (α, β) node scales with the fields (its residuals are homogeneous in
    // all unknowns), so the same division keeps the fit; the prior's own gauge is applied at the
    // end (`solve_levels`), not here.
    let scale_len = 2 * problem.scale_nodes();
    if params.energy == Energy::Normalized {
        let mean_scale =
            fields[..scale_len].iter().step_by(2).sum::<f64>() / (scale_len / 2) as f64;
        for v in &mut fields {
            *v /= mean_scale;
        }
    }
    let prior = problem.prior.as_ref().map(|term| {
        let at = 2 * term.node as usize;
        LevelPrior {
            affine: (fields[at], fields[at + 1]),
            weights: term.weights.clone(),
            confidence: term.confidence.clone(),
            residual: median_abs(&problem.prior_residuals(&fields)),
            trust: if prior_only {
                Vec::new()
            } else {
                problem.prior_trust(&fields).0
            },
        }
    });
    fields.truncate(scale_len);
    transform.fields(&params, fields.clone());
    Ok(Level {
        prior,
        params,
        fields,
        report,
        build_seconds: (t1 - t0).as_secs_f64(),
        solve_seconds: t1.elapsed().as_secs_f64(),
        sample_weights: problem.weights().iter().map(|&w| w as f32).collect(),
        sample_origins: problem.origins().to_vec(),
        robust_scale,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random(seed: u64, i: usize) -> f64 {
        (splitmix64(seed ^ (i as u64).wrapping_mul(0x9E37)) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Smooth maps of `layout` with per-tangent affine distortion, plus `noise` (uniform, that
    /// amplitude) and a NaN at every `hole`-th pixel if given.
    fn distorted_maps(layout: &Layout, noise: f64, hole: Option<usize>) -> Vec<f32> {
        let (h, w) = layout.tangent_shape();
        let mut maps = Vec::with_capacity(layout.cameras.len() * h * w);
        for (t, cam) in layout.cameras.iter().enumerate() {
            let (sc, sh) = (0.5 + random(1, t), random(2, t) - 0.5);
            for r in 0..h {
                for c in 0..w {
                    let d = cam.pixel_direction(c as f64, r as f64);
                    let v = sc * (1.0 + 0.3 * d.x + 0.2 * d.y * d.z) + sh;
                    let v = v + noise * random(3, r * w + c);
                    let holed = hole.is_some_and(|k| (t * h * w + r * w + c).is_multiple_of(k));
                    maps.push(if holed { f32::NAN } else { v as f32 });
                }
            }
        }
        maps
    }

    /// A small layout and smooth maps with per-tangent affine distortion.
    fn setup(energy: Energy, cols: usize, rows: usize) -> (Layout, Vec<f32>, Problem) {
        let layout = Layout::icosahedron(128, 0.3, None).expect("layout");
        let mut maps = distorted_maps(&layout, 0.0, None);
        standardize(&layout, &mut maps, Offsets::Perspective).expect("standardize");
        let overlaps = Overlaps::build(&layout, 0.2, 0.0);
        let params = LevelParams {
            cols,
            rows,
            energy,
            smoothness: 40.0,
            scale_weight: 0.007,
            offsets: Offsets::Perspective,
        };
        let problem = Problem::new(&layout, &maps, &overlaps, params);
        (layout, maps, problem)
    }

    /// A point away from the identity: scales in [0.7, 1.3], offsets in [-0.5, 0.5].
    fn trial_point(len: usize) -> Vec<f64> {
        (0..len)
            .map(|i| {
                if i % 2 == 0 {
                    0.7 + 0.6 * random(3, i)
                } else {
                    random(4, i) - 0.5
                }
            })
            .collect()
    }

    #[test]
    fn gradient_matches_finite_differences() {
        for energy in [Energy::Paper, Energy::Normalized] {
            let (_, _, problem) = setup(energy, 4, 3);
            let x = trial_point(problem.len());
            assert_gradient_matches(&problem, &x, (0..x.len()).step_by(7), 1e-6);
        }
    }

    /// The energy's gradient at `x` against central differences (step 1e-6) on the unknowns
    /// `at`, to `tolerance` relative (absolute below a gradient of 1e-3).
    pub(super) fn assert_gradient_matches(
        problem: &Problem,
        x: &[f64],
        at: impl Iterator<Item = usize>,
        tolerance: f64,
    ) {
        let mut g = vec![0.0; x.len()];
        let _ = problem.energy(x, Some(&mut g));
        for i in at {
            let h = 1e-6;
            let (mut xp, mut xm) = (x.to_vec(), x.to_vec());
            xp[i] += h;
            xm[i] -= h;
            let fd = (problem.energy(&xp, None) - problem.energy(&xm, None)) / (2.0 * h);
            let rel = (fd - g[i]).abs() / g[i].abs().max(1e-3);
            assert!(rel < tolerance, "unknown {i}: analytic {} vs fd {fd}", g[i]);
        }
    }

    #[test]
    fn weighted_gradient_matches_finite_differences() {
        for energy in [Energy::Paper, Energy::Normalized] {
            let (_, _, mut problem) = setup(energy, 4, 3);
            let weights = (0..problem.samples()).map(|k| random(7, k)).collect();
            problem.set_weights(weights);
            let x = trial_point(problem.len());
            let mut g = vec![0.0; x.len()];
            let e = problem.energy(&x, Some(&mut g));
            // The data term is the weighted mean of r², independently of the assembled Hessian.
            let r = problem.residuals(&x);
            let w = problem.weights();
            let data = r.iter().zip(w).map(|(r, w)| w * r * r).sum::<f64>() / w.iter().sum::<f64>();
            let unweighted = {
                let mut p = problem.clone();
                p.set_weights(vec![0.0; p.samples()]);
                p.energy(&x, None)
            };
            assert!(
                (e - (unweighted + data)).abs() <= 1e-9 * e.abs(),
                "{e} vs {data}"
            );
            assert_gradient_matches(&problem, &x, (0..x.len()).step_by(7), 1e-6);
        }
    }

    fn cam_shape(cam: &crate::TangentCamera) -> (usize, usize) {
        (cam.height, cam.width)
    }

    #[test]
    fn reweighting_gives_planted_outliers_small_weights() {
        for loss in [Loss::Cauchy, Loss::Huber] {
            // Tangents that agree up to a per-tangent affine map in spherical disparity.
            let layout = Layout::icosahedron(512, 0.3, None).expect("layout");
            let mut maps: Vec<f32> = layout
                .cameras
                .iter()
                .enumerate()
                .flat_map(|(t, cam)| {
                    let (h, w) = cam_shape(cam);
                    let (sc, sh) = (0.5 + random(1, t), random(2, t) - 0.5);
                    (0..h * w).map(move |p| {
                        let d = cam.pixel_direction((p % w) as f64, (p / w) as f64);
                        (sc * (1.0 + 0.3 * d.x + 0.2 * d.y * d.z) + sh) as f32
                    })
                })
                .collect();
            standardize(&layout, &mut maps, Offsets::Spherical).expect("standardize");
            let (h, w) = layout.tangent_shape();
            // A disc in tangent 5, in its overlap with its left neighbour, off by 2 standardised
            // units (a content error).
            let inside = |p: usize| {
                let (x, y) = (
                    (p % w) as f64 - w as f64 / 10.0,
                    (p / w) as f64 - h as f64 / 2.0,
                );
                x * x + y * y < (w as f64 / 6.0).powi(2)
            };
            for p in (0..h * w).filter(|&p| inside(p)) {
                maps[5 * h * w + p] += 2.0;
            }
            let overlaps = Overlaps::build(&layout, 0.1, 0.0);
            // A 2x2 grid cannot bend around the disc, so the disc stays in the residuals.
            let params = LevelParams {
                cols: 2,
                rows: 2,
                energy: Energy::Normalized,
                smoothness: 1.0,
                scale_weight: 0.01,
                offsets: Offsets::Spherical,
            };
            let mut problem = Problem::new(&layout, &maps, &overlaps, params);
            let mut x = problem.identity();
            for _ in 0..3 {
                x = solve(&problem, &x, Solver::Newton, 100, 1e-9)
                    .expect("solve")
                    .0;
                let sigma = problem.reweight(&x, loss);
                assert!(sigma > 0.0);
            }
            let (mut planted, mut clean) = (Vec::new(), Vec::new());
            for (&k, &wgt) in problem.origins().iter().zip(problem.weights()) {
                let (a, pa, b) = overlaps.sample(k as usize);
                if a == 5 && inside(pa) {
                    planted.push(wgt);
                } else if a != 5 && b != 5 {
                    clean.push(wgt);
                }
            }
            let median = |v: &mut Vec<f64>| {
                v.sort_by(f64::total_cmp);
                v[v.len() / 2]
            };
            assert!(planted.len() >= 10, "{}", planted.len());
            let (mp, mc) = (median(&mut planted), median(&mut clean));
            assert!(mp < 0.2 && mc > 0.8, "{loss:?}: planted {mp}, clean {mc}");
        }
    }

    #[test]
    fn the_ray_rescale_lands_on_the_energy_minimum_along_the_ray() {
        for energy in [Energy::Paper, Energy::Normalized] {
            let (_, _, problem) = setup(energy, 4, 3);
            let x = trial_point(problem.len());
            // Along the ray E(t·x) = t²·Q + B/t: Q and B from two energies, the minimum at
            // t* = (B/2Q)^⅓. Start 1.5× below it (a start 3× off is left alone).
            let scaled = |x: &[f64], f: f64| x.iter().map(|v| v * f).collect::<Vec<f64>>();
            let (e1, e2) = (
                problem.energy(&x, None),
                problem.energy(&scaled(&x, 2.0), None),
            );
            let q = (e2 - 0.5 * e1) / 3.5;
            let best = ((e1 - q) / (2.0 * q)).cbrt();
            let far = scaled(&x, best / 3.0);
            let mut moved = far.clone();
            let change = problem.rescale_to_ray_minimum(&mut moved);
            assert!(
                change.abs() < 1e-300,
                "{energy:?}: a start 3x off changed {change}"
            );
            assert_eq!(moved, far, "{energy:?}: a start 3x off moved");
            let start = scaled(&x, best / 1.5);
            let mut moved = start.clone();
            let change = problem.rescale_to_ray_minimum(&mut moved);
            let t = moved[0] / start[0];
            assert!((t - 1.5).abs() < 1e-6, "{energy:?}: t = {t}");
            // The change it reports is the energy's, evaluated sample by sample.
            let (before, after) = (problem.energy(&start, None), problem.energy(&moved, None));
            assert!(
                (after - before - change).abs() <= 1e-9 * before.abs(),
                "{energy:?}: {change} vs {}",
                after - before
            );
            // Least along the ray: both neighbours on it cost more.
            for f in [0.999, 1.001] {
                assert!(
                    problem.energy(&scaled(&moved, f), None) > after,
                    "{energy:?}: factor {f}"
                );
            }
        }
    }

    #[test]
    fn newton_and_lbfgs_reach_the_same_minimum() {
        let (_, _, problem) = setup(Energy::Normalized, 4, 3);
        let x0 = problem.identity();
        let (xn, rn) = solve(&problem, &x0, Solver::Newton, 100, 1e-10).expect("newton");
        let (_, rl) = solve(&problem, &x0, Solver::Lbfgs, 20_000, 1e-8).expect("lbfgs");
        assert!(rn.converged && rn.iterations < 30, "{rn:?}");
        assert!(rl.converged, "{rl:?}");
        assert!(
            (rn.energy - rl.energy).abs() <= 1e-7 * rn.energy.abs().max(1.0),
            "{rn:?} {rl:?}"
        );
        assert!(xn.iter().step_by(2).all(|&s| s > 0.0));
    }

    #[test]
    fn newton_step_matches_a_dense_solve() {
        let (_, _, problem) = setup(Energy::Paper, 3, 2);
        let n = problem.len();
        let x: Vec<f64> = (0..n)
            .map(|i| {
                if i % 2 == 0 {
                    1.0 + 0.1 * random(5, i)
                } else {
                    0.1 * random(6, i)
                }
            })
            .collect();
        let mut g = vec![0.0; n];
        let _ = problem.energy(&x, Some(&mut g));
        let mut system = NewtonSystem::new(&problem).expect("system");
        let dir = system.step(&problem, &x, &g).expect("step");
        // Dense Hessian by finite differences of the analytic gradient: H·dir must equal −g.
        let h = 1e-6;
        let mut hd = vec![0.0; n];
        for j in 0..n {
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[j] += h;
            xm[j] -= h;
            let (mut gp, mut gm) = (vec![0.0; n], vec![0.0; n]);
            let _ = problem.energy(&xp, Some(&mut gp));
            let _ = problem.energy(&xm, Some(&mut gm));
            for i in 0..n {
                hd[i] += (gp[i] - gm[i]) / (2.0 * h) * dir[j];
            }
        }
        let err = hd
            .iter()
            .zip(&g)
            .map(|(a, b)| (a + b).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-5 * max_abs(&g).max(1e-6), "residual {err}");
    }

    #[test]
    fn groups_and_pattern_match_one_sort_of_all_pairs() {
        let groups = Groups::by_key(vec![(5, 0), (2, 1), (5, 2), (9, 3), (2, 4)]);
        assert_eq!(groups.slices(), vec![&[1u32, 4][..], &[0, 2], &[3]]);
        assert!(Groups::by_key(Vec::new()).is_empty());
        // The bucketed pattern against the plain construction: every pair sorted, deduplicated.
        let (_, _, problem) = setup(Energy::Normalized, 8, 7);
        let blocks = problem.data_blocks();
        let (start, col) = (&problem.pattern.start, &problem.pattern.col);
        let mut pairs: Vec<(u32, u32)> = Vec::new();
        for (nd, _) in &blocks {
            for &p in nd {
                pairs.extend(nd.iter().map(|&q| (p, q)));
            }
        }
        for &(p, q, _) in &problem.edges {
            pairs.extend([(p, q), (q, p)]);
        }
        pairs.extend((0..(problem.len() / 2) as u32).map(|i| (i, i)));
        pairs.sort_unstable();
        pairs.dedup();
        let rebuilt: Vec<(u32, u32)> = (0..start.len() - 1)
            .flat_map(|p| {
                col[start[p]..start[p + 1]]
                    .iter()
                    .map(move |&q| (p as u32, q))
            })
            .collect();
        assert_eq!(rebuilt, pairs);
    }

    /// The prior's slope at the join is the geometric-mean line's: exact on a line, about
    /// reciprocal when the roles swap (least squares: the correlation² instead), robust to
    /// outliers.
    #[test]
    fn the_prior_fit_is_symmetric_and_robust() {
        let n = 2000;
        let p: Vec<f64> = (0..n).map(|i| random(1, i) * 2.0 - 1.0).collect();
        let noise: Vec<f64> = (0..n).map(|i| random(2, i) * 2.0 - 1.0).collect();
        let ones = vec![1.0; n];
        let line: Vec<f64> = p.iter().map(|x| 1.5 - 0.5 * x).collect();
        let (a, b) = symmetric_line(&p, &line, &ones).expect("fit");
        assert!((a + 0.5).abs() < 1e-9 && (b - 1.5).abs() < 1e-9, "{a} {b}");
        // v = p + noise of p's spread: correlation 1/√2, least squares slope ≈ 1.
        let v: Vec<f64> = p.iter().zip(&noise).map(|(x, e)| x + e).collect();
        let (forward, _) = symmetric_line(&p, &v, &ones).expect("fit");
        let (backward, _) = symmetric_line(&v, &p, &ones).expect("fit");
        // (The robust weights differ with the roles, so not exactly 1; least squares: ≈ ½.)
        assert!(
            (forward * backward - 1.0).abs() < 0.1,
            "{forward} · {backward}"
        );
        assert!(
            forward > 1.2,
            "slope {forward} shrunk towards least squares"
        );
        // A fifth of the points far off the line: the slope and intercept hold.
        let spoiled: Vec<f64> = line
            .iter()
            .enumerate()
            .map(|(i, &y)| if i % 5 == 0 { y + 8.0 } else { y })
            .collect();
        let (a, b) = symmetric_line(&p, &spoiled, &ones).expect("fit");
        assert!((a + 0.5).abs() < 0.02 && (b - 1.5).abs() < 0.02, "{a} {b}");
        // Confidence 0 is no point; a constant p has no slope.
        let half: Vec<f64> = (0..n).map(|i| f64::from(u8::from(i % 2 == 0))).collect();
        let odd_spoiled: Vec<f64> = line
            .iter()
            .enumerate()
            .map(|(i, &y)| if i % 2 == 1 { -y } else { y })
            .collect();
        let (a, _) = symmetric_line(&p, &odd_spoiled, &half).expect("fit");
        assert!((a + 0.5).abs() < 1e-9, "{a}");
        assert!(symmetric_line(&ones, &line, &ones).is_none());
        assert!(symmetric_line(&p, &line, &vec![0.0; n]).is_none());
    }

    /// The prior samples keep the overlap samples' count on tangents of 2K and above, twice
    /// their share below (up to that count): enough for the prior-only level's 43 x 40 grid at
    /// 1K (one sample per 4 nodes), not at 512 px.
    #[test]
    fn prior_samples_keep_the_2k_count_and_twice_the_share_below() {
        let nodes = 43.0 * 40.0;
        for (width, runs) in [(512, false), (1024, true), (2048, true), (4096, true)] {
            let layout = Layout::icosahedron(width, 0.3, None).expect("layout");
            let (h, w) = layout.tangent_shape();
            let pixels = (h * w).min(SAMPLE_BUDGET_PIXELS) as f64;
            let kept = prior_sample_fraction(&layout, 0.01) * pixels;
            let expected = (0.02 * (h * w) as f64).min(0.01 * SAMPLE_BUDGET_PIXELS as f64);
            assert!(
                (kept - expected).abs() < 1e-6,
                "{width}: {kept} against {expected}"
            );
            assert_eq!(
                kept * NODES_PER_SAMPLE as f64 >= nodes,
                runs,
                "{width}: {kept}"
            );
        }
        let tiny = Layout::icosahedron(64, 0.3, None).expect("layout");
        assert!(prior_sample_fraction(&tiny, 0.6) <= 1.0);
    }

    #[test]
    fn a_kept_analysis_steps_as_a_fresh_one() {
        let (_, _, problem) = setup(Energy::Normalized, 4, 3);
        let (_, _, other) = setup(Energy::Normalized, 3, 2); // another pattern between
        let n = problem.len();
        let x: Vec<f64> = (0..n)
            .map(|i| {
                if i % 2 == 0 {
                    1.0 + 0.1 * random(7, i)
                } else {
                    0.0
                }
            })
            .collect();
        let mut g = vec![0.0; n];
        let _ = problem.energy(&x, Some(&mut g));
        let first = NewtonSystem::new(&problem).expect("system");
        let _ = NewtonSystem::new(&other).expect("other system");
        let mut kept = NewtonSystem::new(&problem).expect("system again");
        assert!(first
            .analysis
            .matches(&kept.analysis.pattern, kept.analysis.factorization));
        let mut fresh = NewtonSystem::new(&problem).expect("system");
        let pattern = fresh.analysis.pattern.clone();
        fresh.analysis = Arc::new(Analysis::fresh(pattern, Factorization::Auto).expect("analysis"));
        let a = kept.step(&problem, &x, &g).expect("step");
        let b = fresh.step(&problem, &x, &g).expect("step");
        assert!(a.iter().zip(&b).all(|(u, v)| u.to_bits() == v.to_bits()));
    }

    /// The lower triangle of an SPD matrix on a `cols` × `rows` grid of 2-unknown nodes
    /// coupled to their 8 neighbours (a prior-only level's tangent block), as a pattern, its
    /// values and the dense matrix.
    fn grid_block(cols: usize, rows: usize) -> (SymbolicSparseColMat<usize>, Vec<f64>, Mat<f64>) {
        let n = 2 * cols * rows;
        let mut dense = Mat::<f64>::zeros(n, n);
        for r in 0..rows {
            for c in 0..cols {
                let p = r * cols + c;
                for (rr, cc) in [
                    (r, c + 1),
                    (r + 1, c.wrapping_sub(1)),
                    (r + 1, c),
                    (r + 1, c + 1),
                ] {
                    if rr >= rows || cc >= cols {
                        continue;
                    }
                    let q = rr * cols + cc;
                    for (d, e) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                        let v = 0.5 * random(p as u64, 4 * q + 2 * d + e) - 0.25;
                        dense[(2 * q + e, 2 * p + d)] = v;
                        dense[(2 * p + d, 2 * q + e)] = v;
                    }
                }
            }
        }
        for i in 0..n {
            dense[(i, i)] = 5.0 + random(11, i);
        }
        let (mut col_ptr, mut row_idx, mut values) = (vec![0], Vec::new(), Vec::new());
        for j in 0..n {
            for i in j..n {
                if dense[(i, j)] != 0.0 {
                    row_idx.push(i);
                    values.push(dense[(i, j)]);
                }
            }
            col_ptr.push(row_idx.len());
        }
        let pattern = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
        (pattern, values, dense)
    }

    #[test]
    fn grid_dissection_orders_each_node_once_and_fills_about_as_minimum_degree() {
        for (cols, rows) in [(1, 1), (2, 7), (5, 4), (16, 14), (43, 40)] {
            let order = grid_dissection(cols, rows);
            let mut seen = vec![false; cols * rows];
            for &node in &order {
                assert!(!seen[node], "{cols}×{rows}: node {node} twice");
                seen[node] = true;
            }
            assert!(seen.iter().all(|&s| s), "{cols}×{rows}: a node missing");
        }
        // Nested dissection keeps the fill near minimum degree's with the same dense
        // supernodes; an order that does not part the grid (row by row: a band) fills far more.
        let (cols, rows) = (43, 40);
        let (pattern, _, _) = grid_block(cols, rows);
        let dissected = Analysis::fresh(pattern.clone(), Factorization::Grid { cols, rows })
            .expect("analysis")
            .llt
            .len_val();
        let supernodal = |ordering| {
            let params = CholeskySymbolicParams {
                supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SUPERNODAL,
                ..Default::default()
            };
            factorize_symbolic_cholesky(pattern.as_ref(), Side::Lower, ordering, params)
                .expect("analysis")
                .len_val()
        };
        let minimum_degree = supernodal(SymmetricOrdering::Amd);
        let rows_order: Vec<usize> = (0..pattern.nrows()).collect();
        let banded = supernodal(SymmetricOrdering::Custom(PermRef::new_checked(
            &rows_order,
            &rows_order,
            rows_order.len(),
        )));
        assert!(
            (dissected as f64) < 1.1 * minimum_degree as f64 && 3 * dissected < 2 * banded,
            "{dissected} factor entries against {minimum_degree} (minimum degree), {banded} (rows)"
        );
    }

    #[test]
    fn a_grid_block_solves_as_the_dense_system() {
        for (cols, rows) in [(5, 4), (9, 8), (16, 14)] {
            let (pattern, values, dense) = grid_block(cols, rows);
            let n = pattern.nrows();
            let rhs = Mat::<f64>::from_fn(n, 2, |i, k| random(3 + k as u64, i) - 0.5);
            for factorization in [Factorization::Grid { cols, rows }, Factorization::Auto] {
                let analysis = Analysis::fresh(pattern.clone(), factorization).expect("analysis");
                let mut x = rhs.clone();
                analysis.solve_in_place(&values, x.as_mut()).expect("solve");
                let residual = &dense * &x - &rhs;
                let worst = (0..n)
                    .flat_map(|i| (0..2).map(move |k| (i, k)))
                    .fold(0.0f64, |m, (i, k)| m.max(residual[(i, k)].abs()));
                assert!(
                    worst < 1e-12,
                    "{cols}×{rows} {factorization:?}: residual {worst}"
                );
            }
        }
    }

    #[test]
    fn one_and_two_threads_agree_bit_for_bit() {
        let (_, _, problem) = setup(Energy::Normalized, 4, 3);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool");
            pool.install(|| {
                solve(&problem, &problem.identity(), Solver::Lbfgs, 30, 0.0).expect("solve")
            })
        };
        let (x1, r1) = run(1);
        let (x2, r2) = run(2);
        assert_eq!(r1, r2);
        assert!(x1.iter().zip(&x2).all(|(a, b)| a.to_bits() == b.to_bits()));
    }

    /// Standardise with `stats` the old way: one full pass (the oracle of the composed steps).
    fn standardize_pass(layout: &Layout, maps: &mut [f32], stats: &[(f64, f64)], offsets: Offsets) {
        let (h, w) = layout.tangent_shape();
        for (face_row, row) in maps.chunks_mut(w).enumerate() {
            let (t, y) = (face_row / h, face_row % h);
            let cam = &layout.cameras[t];
            let (m, spread) = stats[t];
            let inv = if spread > 0.0 { 1.0 / spread } else { 1.0 };
            for (x, v) in row.iter_mut().enumerate() {
                let f = offset_factor(offsets, cam, x as f64, y as f64);
                *v = ((f64::from(*v) - m * f) * inv) as f32;
            }
        }
    }

    /// Apply a level's fields the old way: one full pass, per pixel from the grid directly.
    fn apply_fields_pass(layout: &Layout, maps: &mut [f32], x: &[f64], params: &LevelParams) {
        let (h, w) = layout.tangent_shape();
        let (cols, rows) = (params.cols, params.rows);
        for (face_row, row) in maps.chunks_mut(w).enumerate() {
            let (t, y) = (face_row / h, face_row % h);
            let cam = &layout.cameras[t];
            let (_, r0, _, fy) = grid_cell(0.0, y as f64, w, h, cols, rows);
            let node = |r: usize, c: usize, k: usize| x[2 * (t * cols * rows + r * cols + c) + k];
            for (xp, v) in row.iter_mut().enumerate() {
                let (c0, _, fx, _) = grid_cell(xp as f64, 0.0, w, h, cols, rows);
                let at = |c: usize, k: usize| (1.0 - fy) * node(r0, c, k) + fy * node(r0 + 1, c, k);
                let s = (1.0 - fx) * at(c0, 0) + fx * at(c0 + 1, 0);
                let o = (1.0 - fx) * at(c0, 1) + fx * at(c0 + 1, 1);
                let f = offset_factor(params.offsets, cam, xp as f64, y as f64);
                *v = (s * f64::from(*v) + o * f) as f32;
            }
        }
    }

    /// The composed alignment (`align`, `align_into`) against standardising, applying each
    /// level's fields and restoring the range one full pass at a time, as the steps were
    /// applied before: each level's problem is the same as one built from the maps as the
    /// passes leave them, and the result is the same bit for bit. With NaN holes, perspective
    /// and spherical offsets.
    #[test]
    fn composed_steps_equal_one_pass_per_step_bit_for_bit() {
        let layout = Layout::icosahedron(512, 0.3, None).expect("layout");
        let maps = distorted_maps(&layout, 0.002, Some(53));
        let overlaps = Overlaps::build(&layout, 0.2, 0.0);
        let same = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits());
        for offsets in [Offsets::Perspective, Offsets::Spherical] {
            let options = Options {
                offsets,
                ..Options::default()
            };
            let mut composed = maps.clone();
            let alignment = align(&layout, &mut composed, &overlaps, &options).expect("align");
            assert_eq!(alignment.fallback, Fallback::None);
            let mut into = vec![0.0; maps.len()];
            let again = align_into(&layout, &maps, &mut into, &overlaps, &options).expect("into");
            assert!(same(&composed, &into), "align and align_into differ");
            let last = alignment.levels.len() - 1;
            assert_eq!(alignment.levels[last].fields, again.levels[last].fields);

            let stats = standardize_stats(&layout, &maps, &FactorTable::new(&layout, offsets))
                .expect("stats");
            let mut passes = maps.clone();
            standardize_pass(&layout, &mut passes, &stats, offsets);
            let mut transform = Transform::new(&layout, offsets);
            transform.standardize(stats.clone());
            for level in &alignment.levels {
                let direct = Problem::new(&layout, &passes, &overlaps, level.params);
                let lazy = level_problem(
                    &layout,
                    &maps,
                    &transform,
                    &overlaps,
                    level.params,
                    None,
                    true,
                );
                assert_eq!(direct.origin, lazy.origin);
                assert!(
                    direct.samples.len() > 500,
                    "{} samples",
                    direct.samples.len()
                );
                for (p, q) in direct.samples.iter().zip(&lazy.samples) {
                    assert_eq!(
                        (p.da.to_bits(), p.db.to_bits()),
                        (q.da.to_bits(), q.db.to_bits())
                    );
                }
                apply_fields_pass(&layout, &mut passes, &level.fields, &level.params);
                transform.fields(&level.params, level.fields.clone());
            }
            let median = stats.iter().map(|s| s.0).sum::<f64>() / stats.len() as f64;
            let spread = stats.iter().map(|s| s.1).sum::<f64>() / stats.len() as f64;
            for v in &mut passes {
                *v = (f64::from(*v) * spread + median) as f32;
            }
            assert!(
                same(&composed, &passes),
                "composed and pass-by-pass maps differ"
            );
            // Not trivially: the alignment moved the maps.
            let moved = composed
                .iter()
                .zip(&maps)
                .filter(|(a, b)| a.to_bits() != b.to_bits())
                .count();
            assert!(moved > composed.len() / 2);
        }
    }

    #[test]
    #[expect(clippy::float_cmp, reason = "a constant's median and shift are exact")]
    fn standardize_rejects_empty_tangents_and_shifts_constant_ones() {
        let layout = Layout::icosahedron(128, 0.3, None).expect("layout");
        let (h, w) = layout.tangent_shape();
        let mut maps: Vec<f32> = (0..20 * h * w).map(|i| (i % 97) as f32).collect();
        maps[3 * h * w..4 * h * w].fill(f32::NAN);
        let err = standardize(&layout, &mut maps, Offsets::Spherical).expect_err("tangent 3");
        assert!(matches!(err, CoreError::Degenerate(m) if m.contains("tangent 3")));
        let mut flat = vec![2.0f32; 20 * h * w];
        let stats = standardize(&layout, &mut flat, Offsets::Spherical).expect("constant");
        assert!(
            stats.iter().all(|&(m, s)| m == 2.0 && s == 0.0),
            "{stats:?}"
        );
        assert!(flat.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn perspective_standardisation_removes_a_perspective_affine_map() {
        // Perspective disparity p, then spherical = p·f: after standardising in perspective
        // space, two different affine maps of p give the same result.
        let layout = Layout::icosahedron(128, 0.3, None).expect("layout");
        let (h, w) = layout.tangent_shape();
        let sph = |scale: f64, shift: f64| -> Vec<f32> {
            let mut v = Vec::with_capacity(20 * h * w);
            for cam in &layout.cameras {
                for p in 0..h * w {
                    let (x, y) = ((p % w) as f64, (p / w) as f64);
                    let persp = 1.0 + 0.5 * ((x * 0.05).sin() + (y * 0.03).cos());
                    v.push(((scale * persp + shift) * cam.spherical_factor(x, y)) as f32);
                }
            }
            v
        };
        let (mut a, mut b) = (sph(1.0, 0.0), sph(3.0, 2.0));
        standardize(&layout, &mut a, Offsets::Perspective).expect("a");
        standardize(&layout, &mut b, Offsets::Perspective).expect("b");
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "{worst}");
    }
}
