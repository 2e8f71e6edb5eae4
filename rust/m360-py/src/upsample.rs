//! `m360.upsample.guided_upsample`: the working-resolution fit and the full-resolution pass;
//! `m360.stitching.refine_edges`: the photo-guided edge refinement.

use crate::arrays::{check_shape, contiguous, output_array, writable};
use crate::errors::{core, input_error};
use crate::threads::on_pool;
use m360_core::edges::{refine_edges as edges, EdgeRefine};
use m360_core::upsample::{
    bilinear_upsample as bilinear, fit_planes, guided_upsample as guided, upsample, GuidedFit,
    WorkingMaps, BILINEAR_PLANES, GUIDED_PLANES,
};
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

/// The working maps of a fit: disparity and grey of the same (h, w), neither empty.
fn working_maps<'a>(
    disparity: &'a PyReadonlyArray2<'_, f32>,
    grey: &'a PyReadonlyArray2<'_, u8>,
) -> PyResult<WorkingMaps<'a>> {
    let shape = disparity.shape();
    let (h, w) = (shape[0], shape[1]);
    if h == 0 || w == 0 {
        return Err(input_error("disparity is empty"));
    }
    check_shape("grey", grey.shape(), &[h, w])?;
    Ok(WorkingMaps {
        disparity: contiguous(disparity, "disparity")?,
        grey: contiguous(grey, "grey")?,
        h,
        w,
    })
}

/// Disparity (h, w) float32 and the photo's grey levels shrunk to (h, w) uint8 → the planes
/// (h, w, 7) float32 (p0, m, e, a, b, lo, hi) of the guided fit, as `upsample_planes` reads them.
#[pyfunction]
pub(crate) fn guided_fit<'py>(
    py: Python<'py>,
    disparity: PyReadonlyArray2<'py, f32>,
    grey: PyReadonlyArray2<'py, u8>,
    radius: usize,
    eps: f64,
    edge_low: f64,
    edge_high: f64,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let maps = working_maps(&disparity, &grey)?;
    let fit = core(GuidedFit::new(radius, eps, edge_low, edge_high, maps.h))?;
    let out = output_array(py, &[maps.h, maps.w, GUIDED_PLANES])?;
    {
        let mut rw = out.readwrite();
        let dst = writable(&mut rw)?;
        on_pool(py, None, || fit_planes(maps, &fit, dst))?;
    }
    Ok(out)
}

/// Guided upsampling in one pass: disparity (h, w) float32, grey (h, w) uint8 and the
/// full-resolution grey `grey_full` (H, W) uint8 → (H, W) float32; the planes of `guided_fit`
/// evaluated as `upsample_planes` does, without storing them.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
pub(crate) fn guided_upsample<'py>(
    py: Python<'py>,
    disparity: PyReadonlyArray2<'py, f32>,
    grey: PyReadonlyArray2<'py, u8>,
    grey_full: PyReadonlyArray2<'py, u8>,
    radius: usize,
    eps: f64,
    edge_low: f64,
    edge_high: f64,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let maps = working_maps(&disparity, &grey)?;
    let fit = core(GuidedFit::new(radius, eps, edge_low, edge_high, maps.h))?;
    let full_shape = grey_full.shape();
    let (out_h, out_w) = (full_shape[0], full_shape[1]);
    if out_h == 0 || out_w == 0 {
        return Err(input_error("grey_full is empty"));
    }
    let full = contiguous(&grey_full, "grey_full")?;
    let out = output_array(py, &[out_h, out_w])?;
    {
        let mut rw = out.readwrite();
        let dst = writable(&mut rw)?;
        on_pool(py, None, || guided(maps, &fit, full, dst, (out_h, out_w)))?;
    }
    Ok(out)
}

/// NaN-aware bilinear upsampling, wrapping in longitude: disparity (h, w) float32 →
/// `out_shape` float32; what `upsample_planes` makes of the planes (p0, m).
#[pyfunction]
pub(crate) fn bilinear_upsample<'py>(
    py: Python<'py>,
    disparity: PyReadonlyArray2<'py, f32>,
    out_shape: (usize, usize),
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let shape = disparity.shape();
    let (h, w) = (shape[0], shape[1]);
    let (out_h, out_w) = out_shape;
    if h == 0 || w == 0 || out_h == 0 || out_w == 0 {
        return Err(input_error("bilinear_upsample: empty input or output"));
    }
    let src = contiguous(&disparity, "disparity")?;
    let out = output_array(py, &[out_h, out_w])?;
    {
        let mut rw = out.readwrite();
        let dst = writable(&mut rw)?;
        on_pool(py, None, || bilinear(src, (h, w), dst, out_shape))?;
    }
    Ok(out)
}

/// Photo-guided refinement of blurred depth edges: disparity (h, w) float32 and photo
/// (h, w, 3) uint8 → (h, w) float32 (`m360_core::edges`).
#[pyfunction]
pub(crate) fn refine_edges<'py>(
    py: Python<'py>,
    disparity: PyReadonlyArray2<'py, f32>,
    rgb: PyReadonlyArray3<'py, u8>,
    radius: usize,
    colour_sigma: f64,
    transition: f64,
    jump: f64,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let shape = disparity.shape();
    let (h, w) = (shape[0], shape[1]);
    if h == 0 || w == 0 {
        return Err(input_error("refine_edges: the disparity is empty"));
    }
    check_shape("photo", rgb.shape(), &[h, w, 3])?;
    let opts = core(EdgeRefine::new(radius, colour_sigma, transition, jump))?;
    let src = contiguous(&disparity, "disparity")?;
    let photo = contiguous(&rgb, "photo")?;
    let out = output_array(py, &[h, w])?;
    {
        let mut rw = out.readwrite();
        let dst = writable(&mut rw)?;
        on_pool(py, None, || edges(src, photo, (h, w), &opts, dst))?;
    }
    Ok(out)
}
