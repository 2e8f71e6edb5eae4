//! Poisson gradient-domain blend.

use crate::blend::WeightMaps;
use crate::error::{CoreError, Result};
use crate::layout::Layout;
use crate::options::{
    check_iterations, check_positive, check_range, choice, MIN_POISSON_TOLERANCE,
};
use crate::resample::ErpTaps;
use rayon::prelude::*;
use std::time::Instant;

pub(crate) mod cg;
pub(crate) mod system;

use cg::solve;
use system::{assemble, LayerSource, System, TapSource, Target};

/// The image the Poisson solution is held close to (the λ term).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fidelity {
    /// The frustum-weighted blend (the same weights as the gradient term): measured best on
    /// AbsRel and seams together, the default.
    Frustum,
    /// The nearest-face stitch D_NN (the paper's choice).
    Nearest,
    /// The unweighted mean of the valid samples.
    Mean,
    /// The disagreement-aware blend ([`crate::blend::consensus_blend`]): a face that disagrees
    /// with the others is voted down in the target too.
    Consensus,
}

choice!(
    Fidelity,
    "fidelity",
    [
        (Fidelity::Frustum, "frustum"),
        (Fidelity::Nearest, "nn"),
        (Fidelity::Mean, "mean"),
        (Fidelity::Consensus, "consensus"),
    ]
);

/// Which conjugate-gradient implementation solves the Poisson system (all matrix-free, f64,
/// deterministic for any thread count).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoissonSolver {
    /// CG preconditioned by a geometric multigrid V-cycle on the ERP grid (f32, red-black
    /// Gauss–Seidel, 2×2 aggregation): about ten iterations at any size instead of about 80.
    /// The default. Grids of odd width fall back to [`PoissonSolver::Fused`].
    Multigrid,
    /// Jacobi-preconditioned CG with fused, parallel passes over the grid (three memory sweeps
    /// per iteration and fixed-order reductions).
    Fused,
    /// faer's `conjugate_gradient` with the same operator and the multigrid V-cycle as its
    /// preconditioner (Jacobi on grids of odd width); faer's own vector operations run
    /// sequentially to stay deterministic.
    Faer,
}

choice!(
    PoissonSolver,
    "poisson solver",
    [
        (PoissonSolver::Multigrid, "multigrid"),
        (PoissonSolver::Fused, "fused"),
        (PoissonSolver::Faer, "faer"),
    ]
);

/// Options of the Poisson blend.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoissonParams {
    /// Fidelity weight λ (> 0 keeps the system positive definite).
    pub lam: f64,
    /// Fidelity target.
    pub fidelity: Fidelity,
    /// Stop when the true relative residual ‖Ax − b‖/‖b‖ is at most this.
    pub tolerance: f64,
    /// Most conjugate-gradient iterations in total.
    pub iterations: usize,
    /// The CG implementation.
    pub solver: PoissonSolver,
}

impl PoissonParams {
    /// The paper's fidelity weight λ.
    pub const DEFAULT_LAM: f64 = 0.1;
    /// Default relative residual ‖Ax − b‖/‖b‖ at which the solve stops.
    pub const DEFAULT_TOLERANCE: f64 = 1e-6;
    /// Default iteration cap (multigrid CG needs about ten, Jacobi CG about 80).
    pub const DEFAULT_ITERATIONS: usize = 2000;

    /// `self` if every value is usable, else the first problem, naming the option.
    ///
    /// # Errors
    /// [`CoreError::InvalidOption`] for λ ≤ 0, a tolerance outside
    /// [[`MIN_POISSON_TOLERANCE`], 1) or an iteration cap outside [1, `MAX_ITERATIONS`].
    pub fn validate(self) -> Result<Self> {
        check_positive("lam", self.lam, "it anchors the Poisson solution")?;
        check_range("tolerance", self.tolerance, MIN_POISSON_TOLERANCE, 1.0)?;
        if self.tolerance >= 1.0 {
            return Err(CoreError::option("tolerance", "tolerance=1 must be < 1"));
        }
        check_iterations("iterations", self.iterations, 1)?;
        Ok(self)
    }
}

impl Default for PoissonParams {
    fn default() -> Self {
        Self {
            lam: Self::DEFAULT_LAM,
            fidelity: Fidelity::default(),
            tolerance: Self::DEFAULT_TOLERANCE,
            iterations: Self::DEFAULT_ITERATIONS,
            solver: PoissonSolver::default(),
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

fn solve_assembled(
    system: &System,
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
    let (iterations, relative_residual, initial_residual) = solve(system, &mut x, params)?;
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

/// Poisson blend of per-tangent maps (N·h·w, NaN = invalid) through the plan's taps, with
/// per-face gradient weights `weights` (the frustum maps): minimises
/// Σ_a Σ_x ω_a(x)‖∇B(x) − ∇D_a(x)‖² + λ Σ_x (B(x) − T(x))² with T the fidelity target.
/// `disparity` (H·W) gets B (NaN where no face is valid), `spread` (if given) the overlap
/// disagreement.
///
/// ∇ is the forward difference on the ERP grid; for the edge x → x' the face term is
/// ω̄_a·((B(x') − B(x)) − (D_a(x') − D_a(x)))² with ω̄_a = (ω_a(x) + ω_a(x'))/2, counted for the
/// faces valid at both ends.
///
/// # Errors
/// [`CoreError::InvalidOption`] for unusable `params`; [`CoreError::NotConverged`],
/// [`CoreError::NotPositiveDefinite`] or [`CoreError::NonFinite`] when the solve fails.
pub fn poisson_blend(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    weights: &WeightMaps,
    params: &PoissonParams,
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) -> Result<PoissonReport> {
    poisson_blend_with_prior(
        taps, layout, tangents, weights, params, None, disparity, spread,
    )
}

/// [`poisson_blend`] whose consensus target (with [`Fidelity::Consensus`]) takes the global
/// prior's vote ([`crate::blend::consensus_blend_with_prior`]); other targets ignore it.
///
/// # Errors
/// Those of [`poisson_blend`].
#[allow(clippy::too_many_arguments)]
pub fn poisson_blend_with_prior(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    weights: &WeightMaps,
    params: &PoissonParams,
    prior: Option<&crate::blend::PriorVote<'_>>,
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) -> Result<PoissonReport> {
    params.validate()?;
    let t0 = Instant::now();
    let source = TapSource {
        taps,
        tangents,
        weights,
        ranks: params.fidelity == Fidelity::Nearest,
    };
    let (h, w) = (layout.erp_height, layout.erp_width);
    let system = if params.fidelity == Fidelity::Consensus {
        let mut consensus = vec![0.0f32; h * w];
        crate::blend::consensus_blend_with_prior(
            taps,
            layout,
            tangents,
            weights,
            prior,
            &mut consensus,
            spread,
        );
        assemble(&source, h, w, params.lam, Target::Given(&consensus), None)
    } else {
        assemble(
            &source,
            h,
            w,
            params.lam,
            Target::FromSamples(params.fidelity),
            spread,
        )
    };
    let assemble_seconds = t0.elapsed().as_secs_f64();
    solve_assembled(&system, params, assemble_seconds, disparity, None)
}

/// The same Poisson blend for K maps already on an H×W ERP grid: `values` and `weights` are
/// K·H·W (NaN value = invalid), `target` H·W is the fidelity image (NaN = no fidelity and no
/// unknown there, allowed only where no layer is valid; `params.fidelity` is ignored).
/// Returns B in f64 (NaN where `target` is NaN).
///
/// # Errors
/// As [`poisson_blend`], and [`CoreError::ShapeMismatch`] or [`CoreError::InvalidOption`]
/// (naming the pixel) for inconsistent layers and target.
pub fn poisson_blend_layers(
    values: &[f32],
    weights: &[f32],
    target: &[f32],
    height: usize,
    width: usize,
    params: &PoissonParams,
    out: &mut [f64],
) -> Result<PoissonReport> {
    params.validate()?;
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
        return Err(CoreError::option(
            "target",
            format!(
                "the Poisson target is NaN at pixel (row {}, column {}) where a layer is valid",
                p / width,
                p % width
            ),
        ));
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
        params.lam,
        Target::Given(target),
        None,
    );
    let assemble_seconds = t0.elapsed().as_secs_f64();
    let mut scratch = vec![0.0f32; n];
    solve_assembled(&system, params, assemble_seconds, &mut scratch, Some(out))
}
