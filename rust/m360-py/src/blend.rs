//! Blending through a plan (the core's `Plan::blend` dispatches on the method), and the
//! Poisson blend of layers already on the ERP grid.

use crate::arrays::{check_shape, contiguous, output_array, to_numpy, writable};
use crate::errors::core;
use crate::options::{blend_method, poisson_items, poisson_only};
use crate::threads::on_pool;
use m360_core::blend::{self as core_blend, Method, PoissonParams, PoissonReport, Weighting};
use m360_core::options::Choice;
use m360_core::plan::Plan;
use numpy::{
    PyArrayDyn, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;

#[allow(clippy::type_complexity)]
pub(crate) fn blend<'py>(
    py: Python<'py>,
    plan: &Plan,
    tangents: &PyReadonlyArray3<'py, f32>,
    options: &Bound<'py, PyDict>,
    confidence: bool,
    prior: Option<&core_blend::PriorVote<'_>>,
) -> PyResult<(
    Bound<'py, PyArrayDyn<f32>>,
    Option<Bound<'py, PyArrayDyn<f32>>>,
    Bound<'py, PyDict>,
)> {
    let method = blend_method(options)?;
    let layout = plan.layout();
    let data = contiguous(tangents, "tangents")?;
    let shape = [layout.erp_height, layout.erp_width];
    let disparity = output_array(py, &shape)?;
    let spread = confidence.then(|| output_array(py, &shape)).transpose()?;
    let report = {
        let mut rw_d = disparity.readwrite();
        let mut rw_s = spread.as_ref().map(numpy::PyArrayMethods::readwrite);
        let dst_d = writable(&mut rw_d)?;
        let dst_s = rw_s.as_mut().map(writable).transpose()?;
        let needs = Plan::blend_needs(&method);
        core(on_pool(py, Some((plan, &needs)), || {
            plan.blend_with_prior(data, &method, prior, dst_d, dst_s)
        })?)?
    };
    let dict = PyDict::new(py);
    dict.set_item("method", method.name())?;
    if let (Some(r), Method::Poisson(params)) = (report.poisson, &method) {
        fill_report(&dict, &r, params, params.fidelity.name())?;
    }
    Ok((disparity, spread, dict))
}

pub(crate) fn weights<'py>(
    py: Python<'py>,
    plan: &Plan,
    kind: &str,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let kind = core(Weighting::parse(kind))?;
    let layout = plan.layout();
    let (h, w) = layout.tangent_shape();
    let data = on_pool(py, None, || core_blend::weight_maps(layout, kind))?;
    to_numpy(py, data, &[layout.cameras.len(), h, w])
}

fn fill_report(
    report: &Bound<'_, PyDict>,
    r: &PoissonReport,
    params: &PoissonParams,
    fidelity: &str,
) -> PyResult<()> {
    poisson_items(report, params)?;
    report.set_item("fidelity", fidelity)?;
    report.set_item("iterations", r.iterations)?;
    report.set_item("relative_residual", r.relative_residual)?;
    report.set_item("initial_residual", r.initial_residual)?;
    report.set_item("converged", r.relative_residual <= params.tolerance)?;
    report.set_item("unknowns", r.unknowns)?;
    report.set_item("assemble_seconds", r.assemble_seconds)?;
    report.set_item("solve_seconds", r.solve_seconds)?;
    Ok(())
}

/// The Poisson blend of K maps already on an ERP grid: `values` and `weights` (K,H,W) float32
/// (NaN value = invalid), fidelity `target` (H,W) float32 (NaN only where no layer is valid),
/// Poisson options in the dict `blend` (None = defaults; its fidelity is ignored):
/// (B (H,W) float64, report dict).
#[pyfunction]
#[pyo3(signature = (values, weights, target, blend=None))]
pub(crate) fn poisson_blend<'py>(
    py: Python<'py>,
    values: PyReadonlyArray3<'py, f32>,
    weights: PyReadonlyArray3<'py, f32>,
    target: PyReadonlyArray2<'py, f32>,
    blend: Option<&Bound<'py, PyDict>>,
) -> PyResult<(Bound<'py, PyArrayDyn<f64>>, Bound<'py, PyDict>)> {
    let params = poisson_only(blend)?;
    let shape = values.shape().to_vec();
    check_shape("weights", weights.shape(), &shape)?;
    check_shape("target", target.shape(), &shape[1..])?;
    let (h, w) = (shape[1], shape[2]);
    let (v, wt, t) = (
        contiguous(&values, "values")?,
        contiguous(&weights, "weights")?,
        contiguous(&target, "target")?,
    );
    let out = output_array(py, &[h, w])?;
    let report = {
        let mut rw = out.readwrite();
        let dst = writable(&mut rw)?;
        core(on_pool(py, None, || {
            core_blend::poisson_blend_layers(v, wt, t, h, w, &params, dst)
        })?)?
    };
    let dict = PyDict::new(py);
    dict.set_item("method", "poisson")?;
    fill_report(&dict, &report, &params, "given")?;
    Ok((out, dict))
}
