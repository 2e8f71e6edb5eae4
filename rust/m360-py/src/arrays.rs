//! Array conversion between numpy and the core's slices.

use crate::errors::{input_error, internal_error};
use numpy::ndarray::{Array, IxDyn};
use numpy::{IntoPyArray, PyArrayDyn, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::prelude::*;

/// An owned buffer as a new numpy array of `shape`.
pub(crate) fn to_numpy<'py, T: numpy::Element>(
    py: Python<'py>,
    data: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    Array::from_shape_vec(IxDyn(shape), data)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| internal_error(format!("internal shape error: {e}")))
}

/// A new zero-filled C-contiguous array for the core to write into: numpy's allocator (which
/// asks for huge pages on large arrays) instead of a Rust `Vec` handed over afterwards. Unlike
/// `PyArray::zeros` (which panics on a null pointer) a failed allocation is an `InputError`.
pub(crate) fn output_array<'py, T: numpy::Element>(
    py: Python<'py>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    use numpy::npyffi::{npy_intp, PY_ARRAY_API};
    use numpy::PyArrayDescrMethods;
    let too_big = || input_error(format!("an output array of shape {shape:?} is too large"));
    let mut dims = shape
        .iter()
        .map(|&d| npy_intp::try_from(d).map_err(|_| too_big()))
        .collect::<PyResult<Vec<npy_intp>>>()?;
    let ndim = std::ffi::c_int::try_from(dims.len()).map_err(|_| too_big())?;
    // SAFETY: dims outlives the call; PyArray_Zeros steals the dtype reference it is given and
    // returns a new reference or null with a Python exception set.
    let array = unsafe {
        let ptr = PY_ARRAY_API.PyArray_Zeros(
            py,
            ndim,
            dims.as_mut_ptr(),
            T::get_dtype(py).into_dtype_ptr(),
            0,
        );
        Bound::from_owned_ptr_or_err(py, ptr)
    }
    .map_err(|err| {
        input_error(format!(
            "cannot allocate an output array of shape {shape:?}: {err}"
        ))
    })?;
    // SAFETY: PyArray_Zeros made an ndarray of T's dtype with shape.len() dimensions.
    Ok(unsafe { array.cast_into_unchecked() })
}

/// The data of an array made by [`output_array`].
pub(crate) fn writable<'a, T: numpy::Element>(
    array: &'a mut numpy::PyReadwriteArrayDyn<'_, T>,
) -> PyResult<&'a mut [T]> {
    array
        .as_slice_mut()
        .map_err(|e| internal_error(format!("internal error: output not contiguous: {e}")))
}

/// The data of an input array, which must be C-contiguous (`as_slice` alone also takes a
/// Fortran-ordered array, whose data would be read in the wrong order).
pub(crate) fn contiguous<'a, T: numpy::Element, D: numpy::ndarray::Dimension>(
    array: &'a numpy::PyReadonlyArray<'_, T, D>,
    name: &str,
) -> PyResult<&'a [T]> {
    let not_c = || input_error(format!("{name} must be a C-contiguous array"));
    if !array.is_c_contiguous() {
        return Err(not_c());
    }
    array.as_slice().map_err(|_| not_c())
}

/// The data of an array the core writes in place, which must be C-contiguous.
pub(crate) fn contiguous_mut<'a, T: numpy::Element, D: numpy::ndarray::Dimension>(
    array: &'a mut numpy::PyReadwriteArray<'_, T, D>,
    name: &str,
) -> PyResult<&'a mut [T]> {
    let not_c = || input_error(format!("{name} must be a C-contiguous array"));
    if !array.is_c_contiguous() {
        return Err(not_c());
    }
    array.as_slice_mut().map_err(|_| not_c())
}

pub(crate) fn check_shape(name: &str, actual: &[usize], expected: &[usize]) -> PyResult<()> {
    if actual == expected {
        Ok(())
    } else {
        Err(input_error(format!(
            "{name} has shape {actual:?}, expected {expected:?}"
        )))
    }
}

/// An ERP image of either supported pixel type.
#[derive(FromPyObject)]
pub(crate) enum ErpImage<'py> {
    U8(PyReadonlyArray3<'py, u8>),
    F32(PyReadonlyArray3<'py, f32>),
}
