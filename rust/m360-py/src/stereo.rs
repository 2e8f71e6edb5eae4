//! `m360.stereo`: the omnidirectional stereo (ODS) warp of the core, both eyes in one call.

use crate::arrays::{check_shape, contiguous, output_array, writable};
use crate::errors::{core, input_error};
use crate::threads::on_pool;
use m360_core::stereo::{
    ods_eye, Eye, OdsOptions, DEFAULT_MAX_DEPTH_RATIO, DEFAULT_POLE_FADE_DEG, MAX_IPD,
};
use numpy::{
    PyArrayDyn, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;

type Eyes<'py> = (
    Bound<'py, PyArrayDyn<u8>>,
    Bound<'py, PyArrayDyn<u8>>,
    Bound<'py, PyArrayDyn<bool>>,
    Bound<'py, PyArrayDyn<bool>>,
    usize,
    usize,
);

/// Panorama `rgb` (H, W, C) uint8 and its radial `depth` (H, W) float32 (NaN or ≤ 0: at
/// infinity) → (left, right (H, W, C) uint8, left_holes, right_holes (H, W) bool, filled left,
/// filled right): the ODS eyes of `m360_core::stereo::ods_eye`.
#[pyfunction]
pub(crate) fn ods_stereo<'py>(
    py: Python<'py>,
    rgb: PyReadonlyArray3<'py, u8>,
    depth: PyReadonlyArray2<'py, f32>,
    ipd: f64,
    pole_fade: f64,
    max_depth_ratio: f64,
) -> PyResult<Eyes<'py>> {
    let shape = rgb.shape().to_vec();
    let (h, w, c) = (shape[0], shape[1], shape[2]);
    if h == 0 || w == 0 || !(1..=4).contains(&c) {
        return Err(input_error(format!(
            "rgb must be a non-empty (H, W, C) image with 1 to 4 channels, got {shape:?}"
        )));
    }
    check_shape("depth", depth.shape(), &[h, w])?;
    let opts = OdsOptions {
        ipd,
        pole_fade_deg: pole_fade,
        max_depth_ratio,
    };
    core(opts.validate())?;
    let src = contiguous(&rgb, "rgb")?;
    let dist = contiguous(&depth, "depth")?;
    let left = output_array::<u8>(py, &[h, w, c])?;
    let right = output_array::<u8>(py, &[h, w, c])?;
    let left_holes = output_array::<bool>(py, &[h, w])?;
    let right_holes = output_array::<bool>(py, &[h, w])?;
    let mut filled = [0_usize; 2];
    for (k, (eye, out, holes)) in [
        (Eye::Left, &left, &left_holes),
        (Eye::Right, &right, &right_holes),
    ]
    .into_iter()
    .enumerate()
    {
        let mut out_rw = out.readwrite();
        let mut holes_rw = holes.readwrite();
        let dst = writable(&mut out_rw)?;
        let mask = writable(&mut holes_rw)?;
        filled[k] = core(on_pool(py, None, || {
            ods_eye(src, c, dist, h, w, &opts, eye, dst, mask)
        })?)?;
    }
    Ok((left, right, left_holes, right_holes, filled[0], filled[1]))
}

/// The ODS warp's defaults and limits: `pole_fade` (degrees), `max_depth_ratio`, `max_ipd`.
#[pyfunction]
pub(crate) fn ods_defaults(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let out = PyDict::new(py);
    out.set_item("pole_fade", DEFAULT_POLE_FADE_DEG)?;
    out.set_item("max_depth_ratio", DEFAULT_MAX_DEPTH_RATIO)?;
    out.set_item("max_ipd", MAX_IPD)?;
    Ok(out)
}
