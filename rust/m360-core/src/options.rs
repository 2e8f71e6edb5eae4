//! Option names, defaults and limits: written once here, exported by the bindings, read by Python.
//!
//! Every choice-valued option is an enum implementing [`Choice`]: its names (the default first)
//! and its parsing live with the type, so no other layer spells them. The numeric limits below
//! are the bounds the option checks (`align::Options::validate`, `PoissonParams::validate`) use.

use crate::error::{CoreError, Result};

/// Largest iteration cap of any solver: a cap above this is a typo, not a budget.
pub const MAX_ITERATIONS: usize = 100_000;
/// Smallest Poisson tolerance: a float64 conjugate gradient stalls near 1e-14 relative residual,
/// so a tighter request could only spin until its iteration cap and fail.
pub const MIN_POISSON_TOLERANCE: f64 = 1e-13;
/// Largest pole cap (degrees) of the alignment's overlap samples: beyond it nothing is left.
pub const MAX_POLE_CAP_DEG: f64 = 89.0;
/// Most worker threads m360 starts: a larger count is a typo, and spawning it would take seconds
/// to minutes before failing or working no faster.
pub const MAX_THREADS: usize = 1024;

/// An option whose value is one of a few named choices.
pub trait Choice: Sized + Copy + PartialEq + 'static {
    /// The option's name as the user spells it (`"energy"`).
    const OPTION: &'static str;
    /// Every value with its name, the default first.
    const ALL: &'static [(Self, &'static str)];
    /// The names alone, in the order of [`Choice::ALL`].
    const NAMES: &'static [&'static str];

    /// The name of this value.
    fn name(self) -> &'static str {
        Self::ALL
            .iter()
            .find(|(v, _)| *v == self)
            .map_or("?", |(_, n)| n)
    }

    /// The value called `name`, or [`CoreError::UnknownChoice`] listing the names.
    ///
    /// # Errors
    /// When no value has that name.
    fn parse(name: &str) -> Result<Self> {
        Self::ALL
            .iter()
            .find(|(_, n)| *n == name)
            .map(|(v, _)| *v)
            .ok_or_else(|| CoreError::UnknownChoice {
                option: Self::OPTION,
                given: name.to_owned(),
                choices: Self::NAMES,
            })
    }

    /// The default value (the first of [`Choice::ALL`]).
    fn default_choice() -> Self {
        Self::ALL[0].0
    }
}

/// Implement [`Choice`], `FromStr`, `Display` and `Default` for a unit enum from its names.
macro_rules! choice {
    ($ty:ty, $option:literal, [$(($value:expr, $name:literal)),+ $(,)?]) => {
        impl $crate::options::Choice for $ty {
            const OPTION: &'static str = $option;
            const ALL: &'static [(Self, &'static str)] = &[$(($value, $name)),+];
            const NAMES: &'static [&'static str] = &[$($name),+];
        }

        impl std::str::FromStr for $ty {
            type Err = $crate::error::CoreError;
            fn from_str(name: &str) -> $crate::error::Result<Self> {
                <Self as $crate::options::Choice>::parse(name)
            }
        }

        impl std::fmt::Display for $ty {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str($crate::options::Choice::name(*self))
            }
        }

        impl Default for $ty {
            fn default() -> Self {
                <Self as $crate::options::Choice>::default_choice()
            }
        }
    };
}
pub(crate) use choice;

/// `value` if it is finite and in `[low, high]`, else [`CoreError::InvalidOption`].
///
/// # Errors
/// When `value` is not finite or out of range.
pub(crate) fn check_range(option: &'static str, value: f64, low: f64, high: f64) -> Result<f64> {
    if value.is_finite() && (low..=high).contains(&value) {
        Ok(value)
    } else {
        Err(CoreError::option(
            option,
            format!(
                "{option}={value} must be a finite number in [{}, {}]",
                shown(low),
                shown(high)
            ),
        ))
    }
}

/// A bound as a person writes it: 1e-13 rather than 0.0000000000001, "inf" for no bound.
fn shown(bound: f64) -> String {
    if bound == f64::MAX {
        "inf".into()
    } else if bound != 0.0 && bound.abs() < 1e-3 {
        format!("{bound:e}")
    } else {
        format!("{bound}")
    }
}

/// `value` if it is finite and > 0, else [`CoreError::InvalidOption`] saying `why`.
///
/// # Errors
/// When `value` is not finite or not positive.
pub(crate) fn check_positive(option: &'static str, value: f64, why: &str) -> Result<f64> {
    if value.is_finite() && value > 0.0 {
        Ok(value)
    } else {
        Err(CoreError::option(
            option,
            format!("{option}={value} must be finite and > 0 ({why})"),
        ))
    }
}

/// `value` if it is in `[low, MAX_ITERATIONS]`, else [`CoreError::InvalidOption`].
///
/// # Errors
/// When `value` is out of range.
pub(crate) fn check_iterations(option: &'static str, value: usize, low: usize) -> Result<usize> {
    if (low..=MAX_ITERATIONS).contains(&value) {
        Ok(value)
    } else {
        Err(CoreError::option(
            option,
            format!("{option}={value} must be an integer in [{low}, {MAX_ITERATIONS}]"),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::align::{Energy, Offsets, Solver};
    use crate::blend::{Fidelity, PoissonSolver, Weighting};

    fn round_trips<T: Choice + std::str::FromStr + std::fmt::Debug>() {
        assert_eq!(T::NAMES.len(), T::ALL.len());
        for (value, name) in T::ALL {
            assert_eq!(T::parse(name).ok(), Some(*value));
            assert_eq!(value.name(), *name);
        }
        let err = T::parse("no such thing").expect_err("unknown name");
        assert!(err.to_string().contains(T::NAMES[0]), "{err}");
        assert!(err.is_input_error());
    }

    #[test]
    fn every_choice_parses_its_own_names_and_lists_them_when_unknown() {
        round_trips::<Energy>();
        round_trips::<Offsets>();
        round_trips::<Solver>();
        round_trips::<Fidelity>();
        round_trips::<PoissonSolver>();
        round_trips::<Weighting>();
    }

    #[test]
    fn ranges_refuse_nan_and_the_outside() {
        assert!(check_range("x", f64::NAN, 0.0, 1.0).is_err());
        assert!(check_range("x", 1.5, 0.0, 1.0).is_err());
        assert_eq!(check_range("x", 1.0, 0.0, 1.0).ok(), Some(1.0));
        assert!(check_positive("lam", 0.0, "it anchors").is_err());
        assert!(check_iterations("iterations", MAX_ITERATIONS + 1, 0).is_err());
        let msg = check_positive("lam", -1.0, "why")
            .expect_err("negative")
            .to_string();
        assert!(msg.starts_with("lam"), "{msg}");
    }
}
