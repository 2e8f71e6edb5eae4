//! Errors on their way to Python: core errors map to the `m360.errors` hierarchy.

use m360_core::CoreError;
use pyo3::prelude::*;

pyo3::import_exception!(m360.errors, M360Error);
pyo3::import_exception!(m360.errors, InputError);
pyo3::import_exception!(m360.errors, SolverError);

/// A core error on its way to Python (the orphan rule forbids `From<CoreError> for PyErr`).
pub(crate) struct PyCoreError(pub CoreError);

impl From<CoreError> for PyCoreError {
    fn from(err: CoreError) -> Self {
        Self(err)
    }
}

impl From<PyCoreError> for PyErr {
    fn from(err: PyCoreError) -> PyErr {
        if err.0.is_input_error() {
            InputError::new_err(err.0.to_string())
        } else {
            SolverError::new_err(err.0.to_string())
        }
    }
}

/// `Result<T, CoreError>` → `PyResult<T>`.
pub(crate) fn core<T>(result: m360_core::error::Result<T>) -> PyResult<T> {
    result.map_err(|e| PyCoreError(e).into())
}

pub(crate) fn input_error(msg: impl Into<String>) -> PyErr {
    InputError::new_err(msg.into())
}

pub(crate) fn internal_error(msg: impl Into<String>) -> PyErr {
    M360Error::new_err(msg.into())
}
