//! Failure kinds of the core, one variant per kind (in the style of faer's typed errors).

use std::fmt;

/// An error of the core. The bindings map each kind to a specific Python exception: the first
/// five are problems with the input (`InputError`), the rest failures of a numerical solve
/// (`SolverError`).
#[derive(Debug, Clone, PartialEq)]
pub enum CoreError {
    /// A layout is unusable (checked here because layouts can be user-built).
    InvalidLayout(String),
    /// An option has a value outside its range.
    InvalidOption {
        /// The option's name as the user spells it (`"lam"`, `"sample_fraction"`).
        option: &'static str,
        /// What is wrong, naming the value.
        reason: String,
    },
    /// An option names a choice that does not exist.
    UnknownChoice {
        /// The option's name.
        option: &'static str,
        /// What was given.
        given: String,
        /// The names that exist, the default first.
        choices: &'static [&'static str],
    },
    /// Array dimensions do not match the plan they are used with.
    ShapeMismatch {
        /// What was being checked.
        what: &'static str,
        /// The shape the plan expects.
        expected: Vec<usize>,
        /// The shape that was given.
        actual: Vec<usize>,
    },
    /// The input cannot be processed as asked (a tangent without valid pixels, a constant map).
    Degenerate(String),
    /// A solver met a non-finite value (energy, step or residual).
    NonFinite {
        /// Which quantity.
        what: &'static str,
    },
    /// A system that must be symmetric positive definite was found not to be (a Cholesky
    /// factorisation failed, or conjugate gradients met pᵀAp ≤ 0).
    NotPositiveDefinite {
        /// Which system.
        what: &'static str,
        /// What was observed.
        detail: String,
    },
    /// An iterative solve stopped at its iteration cap above its tolerance.
    NotConverged {
        /// Which solve.
        what: &'static str,
        /// Iterations run.
        iterations: usize,
        /// Relative residual reached.
        residual: f64,
        /// Relative residual asked for.
        tolerance: f64,
    },
}

impl CoreError {
    /// An [`CoreError::InvalidOption`] for `option`.
    pub fn option(option: &'static str, reason: impl Into<String>) -> Self {
        Self::InvalidOption {
            option,
            reason: reason.into(),
        }
    }

    /// Whether the error is about the input (as opposed to a failed solve).
    pub fn is_input_error(&self) -> bool {
        matches!(
            self,
            Self::InvalidLayout(_)
                | Self::InvalidOption { .. }
                | Self::UnknownChoice { .. }
                | Self::ShapeMismatch { .. }
                | Self::Degenerate(_)
        )
    }
}

impl fmt::Display for CoreError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::InvalidLayout(msg) => write!(f, "invalid layout: {msg}"),
            Self::InvalidOption { option, reason } => write!(f, "{option}: {reason}"),
            Self::UnknownChoice {
                option,
                given,
                choices,
            } => {
                let names: Vec<String> = choices.iter().map(|c| format!("{c:?}")).collect();
                write!(
                    f,
                    "unknown {option} {given:?}: choose one of {}",
                    names.join(", ")
                )
            }
            Self::ShapeMismatch {
                what,
                expected,
                actual,
            } => write!(f, "{what} has shape {actual:?}, expected {expected:?}"),
            Self::Degenerate(msg) => write!(f, "{msg}"),
            Self::NonFinite { what } => write!(f, "numerical failure: non-finite {what}"),
            Self::NotPositiveDefinite { what, detail } => {
                write!(f, "{what} is not positive definite: {detail}")
            }
            Self::NotConverged {
                what,
                iterations,
                residual,
                tolerance,
            } => write!(
                f,
                "{what} did not converge: relative residual {residual:.3e} after {iterations} \
                 iterations (tolerance {tolerance:.1e}); raise the iteration cap or the tolerance"
            ),
        }
    }
}

impl std::error::Error for CoreError {}

/// Result alias of the core.
pub type Result<T> = std::result::Result<T, CoreError>;
