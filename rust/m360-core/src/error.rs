//! Failure kinds of the core that can happen on validated input.

use std::fmt;

/// An error of the core. The bindings map each kind to a specific Python exception.
#[derive(Debug, Clone, PartialEq)]
pub enum CoreError {
    /// A layout or option is unusable (checked again here because layouts can be user-built).
    InvalidLayout(String),
    /// The input cannot be processed as asked (a tangent without valid pixels, a constant map).
    Degenerate(String),
    /// A solver met a non-finite value or an indefinite system.
    NonFinite(String),
    /// Array dimensions do not match the plan they are used with.
    ShapeMismatch {
        /// What was being checked.
        what: &'static str,
        /// The shape the plan expects.
        expected: Vec<usize>,
        /// The shape that was given.
        actual: Vec<usize>,
    },
    /// An option value is unusable.
    InvalidOption(String),
    /// A numerical solve failed (did not converge, or the system was not positive definite).
    Solver(String),
}

impl fmt::Display for CoreError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CoreError::InvalidLayout(msg) => write!(f, "invalid layout: {msg}"),
            CoreError::Degenerate(msg) => write!(f, "{msg}"),
            CoreError::NonFinite(msg) => write!(f, "numerical failure: {msg}"),
            CoreError::ShapeMismatch {
                what,
                expected,
                actual,
            } => write!(f, "{what} has shape {actual:?}, expected {expected:?}"),
            CoreError::InvalidOption(msg) => write!(f, "invalid option: {msg}"),
            CoreError::Solver(msg) => write!(f, "solver failed: {msg}"),
        }
    }
}

impl std::error::Error for CoreError {}

/// Result alias of the core.
pub type Result<T> = std::result::Result<T, CoreError>;
