//! The full-resolution pass of `m360.upsample.guided_upsample`.

use crate::arrays::{check_shape, contiguous, output_array, writable};
use crate::errors::input_error;
use crate::threads::on_pool;
use m360_core::upsample::{upsample, BILINEAR_PLANES, GUIDED_PLANES};
use numpy::{
    PyArrayDyn, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::prelude::*;

/// Planes (h, w, C) float32 at the working resolution → (out_h, out_w) float32: C = 2 is
/// (p0, m), bilinear p0/m; C = 7 is (p0, m, e, a, b, lo, hi) with `grey` (out_h, out_w) uint8,
/// p0/m moved towards clamp(a·grey/255 + b, lo, hi) by e. NaN where the validity m < ½.
#[pyfunction]
#[pyo3(signature = (planes, out_shape, grey=None))]
pub(crate) fn upsample_planes<'py>(
    py: Python<'py>,
    planes: PyReadonlyArray3<'py, f32>,
    out_shape: (usize, usize),
    grey: Option<PyReadonlyArray2<'py, u8>>,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let shape = planes.shape().to_vec();
    let (h, w, c) = (shape[0], shape[1], shape[2]);
    let (out_h, out_w) = out_shape;
    if h == 0 || w == 0 || out_h == 0 || out_w == 0 {
        return Err(input_error("upsample_planes: empty input or output"));
    }
    let needed = match (c, &grey) {
        (BILINEAR_PLANES, None) | (GUIDED_PLANES, Some(_)) => c,
        _ => {
            return Err(input_error(format!(
                "planes must have {BILINEAR_PLANES} channels without grey or \
                 {GUIDED_PLANES} with it, got {c}"
            )))
        }
    };
    let src = contiguous(&planes, "planes")?;
    let guide = match &grey {
        Some(g) => {
            check_shape("grey", g.shape(), &[out_h, out_w])?;
            Some(contiguous(g, "grey")?)
        }
        None => None,
    };
    let out = output_array(py, &[out_h, out_w])?;
    {
        let mut rw = out.readwrite();
        let dst = writable(&mut rw)?;
        on_pool(py, None, || {
            upsample(src, needed, h, w, guide, dst, out_h, out_w);
        })?;
    }
    Ok(out)
}
