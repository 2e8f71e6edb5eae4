//! Blending (paper §3.4; docs/method.md, "Blending"): how the tangents that see an ERP pixel are
//! combined into one value.
//!
//! - [`weights`]: per-face weight maps on each tangent's own pixel grid, from that face's own
//!   intrinsics (reference pitfall B9, docs/reference-pitfalls.md).
//! - [`rows`]: the mean, nearest-face and weighted blends, one ERP row at a time.
//! - [`poisson`]: the gradient-domain blend, assembled from the taps and solved by conjugate
//!   gradients preconditioned with the `multigrid` V-cycle.
//!
//! [`Method`] names them all; [`crate::Plan::blend`] dispatches on it.

pub(crate) mod multigrid;
pub mod poisson;
pub mod rows;
pub mod weights;

#[cfg(test)]
mod tests;

pub use poisson::{
    poisson_blend, poisson_blend_layers, poisson_blend_with_prior, Fidelity, PoissonParams,
    PoissonReport, PoissonSolver,
};
pub use rows::{
    combine_confidence_with_prior, consensus_blend, consensus_blend_with_prior, mean_blend,
    median_blend, nearest_blend, weighted_blend, PriorVote,
};
pub use weights::{weight_maps, WeightMaps, Weighting};

use crate::error::{CoreError, Result};
use std::str::FromStr;

/// How the tangents that see an ERP pixel are combined.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Method {
    /// Gradient-domain blend (the paper's): frustum-weighted gradients of the tangents, held to a
    /// fidelity target with weight λ.
    Poisson(PoissonParams),
    /// Frustum-weighted mean: the fast seam-free choice.
    Frustum,
    /// Disagreement-aware frustum blend ([`rows::consensus_blend`], the default): where three or
    /// more faces see a pixel, one that disagrees with the others' consensus is voted down.
    /// Measured on synthetic rooms with content errors (benches/bench_blend.py) it beats the
    /// Poisson blend's AbsRel at about half its time, which on them differed from the frustum
    /// blend by a median relative 1e-5.
    #[default]
    Consensus,
    /// Frustum-weighted median where three or more faces see a pixel, the frustum blend
    /// elsewhere ([`rows::median_blend`]).
    Median,
    /// Radially weighted mean.
    Radial,
    /// Unweighted mean of every valid sample.
    Mean,
    /// The face whose axis is nearest the pixel (falling back to the next nearest where that
    /// face has no valid value).
    Nearest,
}

impl Method {
    /// The names of the methods, the default first.
    pub const NAMES: &'static [&'static str] = &[
        "consensus",
        "poisson",
        "frustum",
        "median",
        "radial",
        "mean",
        "nn",
    ];

    /// The method's name.
    #[must_use]
    pub fn name(&self) -> &'static str {
        match self {
            Self::Poisson(_) => "poisson",
            Self::Frustum => "frustum",
            Self::Consensus => "consensus",
            Self::Median => "median",
            Self::Radial => "radial",
            Self::Mean => "mean",
            Self::Nearest => "nn",
        }
    }

    /// The per-face weights the method reads at the taps, if any (Poisson weighs its gradients
    /// with the frustum weights).
    #[must_use]
    pub fn weighting(&self) -> Option<Weighting> {
        match self {
            Self::Poisson(_) | Self::Frustum | Self::Consensus | Self::Median => {
                Some(Weighting::Frustum)
            }
            Self::Radial => Some(Weighting::Radial),
            Self::Mean | Self::Nearest => None,
        }
    }

    /// `self` if its parameters are usable.
    ///
    /// # Errors
    /// [`CoreError::InvalidOption`] naming the Poisson option at fault.
    pub fn validate(self) -> Result<Self> {
        if let Self::Poisson(params) = self {
            params.validate()?;
        }
        Ok(self)
    }
}

impl FromStr for Method {
    type Err = CoreError;

    /// The method called `name`, Poisson with its default parameters.
    fn from_str(name: &str) -> Result<Self> {
        Ok(match name {
            "poisson" => Self::Poisson(PoissonParams::default()),
            "frustum" => Self::Frustum,
            "consensus" => Self::Consensus,
            "median" => Self::Median,
            "radial" => Self::Radial,
            "mean" => Self::Mean,
            "nn" => Self::Nearest,
            _ => {
                return Err(CoreError::UnknownChoice {
                    option: "blend",
                    given: name.to_owned(),
                    choices: Self::NAMES,
                })
            }
        })
    }
}

/// What a blend reports: the Poisson solve's figures, if it was one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlendReport {
    /// The method that ran.
    pub method: Method,
    /// The Poisson solve's report.
    pub poisson: Option<PoissonReport>,
}
