//! Stitching options between Python dicts and the core's option types; the names, defaults
//! and limits Python reads (`CHOICES`, `LIMITS`, `DEFAULTS`) come from the core's types.

use crate::errors::{core, input_error};
use m360_core::align::{self, Energy, Loss, Offsets, PriorFusion, Solver};
use m360_core::blend::{Fidelity, Method, PoissonParams, PoissonSolver, Weighting};
use m360_core::layout;
use m360_core::options::{
    Choice, MAX_ITERATIONS, MAX_POLE_CAP_DEG, MAX_THREADS, MIN_POISSON_TOLERANCE,
};
use m360_core::resample::Sampling;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};

const ALIGN_KEYS: &[&str] = &[
    "levels",
    "energy",
    "solver",
    "iterations",
    "tolerance",
    "sample_fraction",
    "pole_cap_deg",
    "smoothness",
    "scale_weight",
    "offsets",
    "loss",
    "prior_weight",
    "prior_scale_deg",
    "prior_fusion",
];
const POISSON_KEYS: &[&str] = &["fidelity", "lam", "tolerance", "iterations", "solver"];

/// The value of `key` in `dict` as `T`, None when missing or None.
fn get<'py, T: pyo3::conversion::FromPyObjectOwned<'py>>(
    dict: &Bound<'py, PyDict>,
    key: &str,
    what: &str,
) -> PyResult<Option<T>> {
    match dict.get_item(key)? {
        Some(v) if !v.is_none() => v.extract::<T>().map(Some).map_err(|_| {
            let shown = v.repr().map_or_else(|_| "?".into(), |r| r.to_string());
            input_error(format!("{key}={shown} must be {what}"))
        }),
        _ => Ok(None),
    }
}

fn get_choice<T: Choice>(dict: &Bound<'_, PyDict>, key: &str) -> PyResult<Option<T>> {
    get::<String>(dict, key, "a string")?
        .map(|name| core(T::parse(&name)))
        .transpose()
}

fn refuse_unknown(dict: &Bound<'_, PyDict>, known: &[&str], what: &str) -> PyResult<()> {
    for key in dict.keys() {
        let name: String = key.str()?.extract()?;
        if !known.contains(&name.as_str()) {
            return Err(input_error(format!(
                "unknown {what} option {name:?}; known: {}",
                known.join(", ")
            )));
        }
    }
    Ok(())
}

/// Alignment options from a dict (every key optional; None = the core's default), resolved
/// and checked (grids against `tangent_shape` = (h, w) when given).
pub(crate) fn align_options(
    dict: &Bound<'_, PyDict>,
    tangent_shape: Option<(usize, usize)>,
) -> PyResult<align::Options> {
    refuse_unknown(dict, ALIGN_KEYS, "alignment")?;
    let energy = get_choice::<Energy>(dict, "energy")?.unwrap_or_default();
    let solver = get_choice::<Solver>(dict, "solver")?.unwrap_or_default();
    let mut options = align::Options::new(energy, solver);
    let grids = "a list of (cols, rows) grids of integers, each at least 2 x 2";
    if let Some(levels) = get::<Vec<(usize, usize)>>(dict, "levels", grids)? {
        options.levels = levels;
    }
    let count = "an integer in [0, LIMITS['max_iterations']]";
    if let Some(v) = get::<usize>(dict, "iterations", count)? {
        options.iterations = v;
    }
    let number = "a number";
    if let Some(v) = get::<f64>(dict, "tolerance", number)? {
        options.tolerance = v;
    }
    if let Some(v) = get::<f64>(dict, "sample_fraction", number)? {
        options.sample_fraction = v;
    }
    if let Some(v) = get::<f64>(dict, "pole_cap_deg", number)? {
        options.pole_cap_deg = v;
    }
    if let Some(v) = get::<f64>(dict, "smoothness", number)? {
        options.smoothness = v;
    }
    if let Some(v) = get::<f64>(dict, "scale_weight", number)? {
        options.scale_weight = v;
    }
    if let Some(v) = get_choice::<Offsets>(dict, "offsets")? {
        options.offsets = v;
    }
    if let Some(v) = get_choice::<Loss>(dict, "loss")? {
        options.loss = v;
    }
    if let Some(v) = get::<f64>(dict, "prior_weight", number)? {
        options.prior_weight = v;
    }
    if let Some(v) = get::<f64>(dict, "prior_scale_deg", number)? {
        options.prior_scale_deg = v;
    }
    if let Some(v) = get_choice::<PriorFusion>(dict, "prior_fusion")? {
        options.prior_fusion = v;
    }
    core(options.validate(tangent_shape))
}

/// Poisson parameters from the Poisson keys of a dict (None = default), checked.
fn poisson_params(dict: &Bound<'_, PyDict>) -> PyResult<PoissonParams> {
    let mut params = PoissonParams::default();
    if let Some(v) = get_choice::<Fidelity>(dict, "fidelity")? {
        params.fidelity = v;
    }
    if let Some(v) = get::<f64>(dict, "lam", "a number")? {
        params.lam = v;
    }
    if let Some(v) = get::<f64>(dict, "tolerance", "a number")? {
        params.tolerance = v;
    }
    let count = "an integer in [1, LIMITS['max_iterations']]";
    if let Some(v) = get::<usize>(dict, "iterations", count)? {
        params.iterations = v;
    }
    if let Some(v) = get_choice::<PoissonSolver>(dict, "solver")? {
        params.solver = v;
    }
    core(params.validate())
}

/// A blend method from a dict `{"method": name, <Poisson keys>}`, checked.
pub(crate) fn blend_method(dict: &Bound<'_, PyDict>) -> PyResult<Method> {
    let mut known = vec!["method"];
    known.extend_from_slice(POISSON_KEYS);
    refuse_unknown(dict, &known, "blend")?;
    let name = get::<String>(dict, "method", "a string")?;
    let method: Method = match name {
        Some(name) => core(name.parse())?,
        None => Method::default(),
    };
    if let Method::Poisson(_) = method {
        return Ok(Method::Poisson(poisson_params(dict)?));
    }
    for key in POISSON_KEYS {
        if dict.get_item(key)?.is_some_and(|v| !v.is_none()) {
            return Err(input_error(format!(
                "blend option {key:?} applies to blend='poisson' only, got blend={:?}",
                method.name()
            )));
        }
    }
    Ok(method)
}

/// Poisson parameters from an optional dict whose method, if given, must be "poisson".
pub(crate) fn poisson_only(dict: Option<&Bound<'_, PyDict>>) -> PyResult<PoissonParams> {
    let Some(dict) = dict else {
        return Ok(PoissonParams::default());
    };
    if dict.get_item("method")?.is_none_or(|m| m.is_none()) {
        // No method named: these are Poisson options (the default blend is another method).
        refuse_unknown(dict, POISSON_KEYS, "Poisson")?;
        return poisson_params(dict);
    }
    match blend_method(dict)? {
        Method::Poisson(params) => Ok(params),
        other => Err(input_error(format!(
            "this function blends with 'poisson', got method={:?}",
            other.name()
        ))),
    }
}

/// The canonical dict of alignment options.
pub(crate) fn align_dict<'py>(py: Python<'py>, o: &align::Options) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    let levels: Vec<(usize, usize)> = o.levels.clone();
    d.set_item("levels", PyList::new(py, levels)?)?;
    d.set_item("energy", o.energy.name())?;
    d.set_item("solver", o.solver.name())?;
    d.set_item("iterations", o.iterations)?;
    d.set_item("tolerance", o.tolerance)?;
    d.set_item("sample_fraction", o.sample_fraction)?;
    d.set_item("pole_cap_deg", o.pole_cap_deg)?;
    d.set_item("smoothness", o.smoothness)?;
    d.set_item("scale_weight", o.scale_weight)?;
    d.set_item("offsets", o.offsets.name())?;
    d.set_item("loss", o.loss.name())?;
    d.set_item("prior_weight", o.prior_weight)?;
    d.set_item("prior_scale_deg", o.prior_scale_deg)?;
    d.set_item("prior_fusion", o.prior_fusion.name())?;
    Ok(d)
}

/// The canonical dict of a blend method.
pub(crate) fn blend_dict<'py>(py: Python<'py>, method: &Method) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("method", method.name())?;
    if let Method::Poisson(p) = method {
        poisson_items(&d, p)?;
    }
    Ok(d)
}

/// The Poisson parameters' entries of a dict.
pub(crate) fn poisson_items(d: &Bound<'_, PyDict>, p: &PoissonParams) -> PyResult<()> {
    d.set_item("fidelity", p.fidelity.name())?;
    d.set_item("lam", p.lam)?;
    d.set_item("tolerance", p.tolerance)?;
    d.set_item("iterations", p.iterations)?;
    d.set_item("solver", p.solver.name())?;
    Ok(())
}

/// Resolve and check stitching options: `align` (None = no alignment) and `blend` dicts in,
/// the same dicts with every default filled in out; `tangent_shape` = (h, w) also checks that
/// every alignment grid fits a tangent.
#[pyfunction]
#[pyo3(signature = (align, blend, tangent_shape=None))]
#[allow(clippy::type_complexity)]
pub(crate) fn stitch_options<'py>(
    py: Python<'py>,
    align: Option<&Bound<'py, PyDict>>,
    blend: &Bound<'py, PyDict>,
    tangent_shape: Option<(usize, usize)>,
) -> PyResult<(Option<Bound<'py, PyDict>>, Bound<'py, PyDict>)> {
    let align = align
        .map(|d| align_options(d, tangent_shape).and_then(|o| align_dict(py, &o)))
        .transpose()?;
    let blend = blend_dict(py, &blend_method(blend)?)?;
    Ok((align, blend))
}

fn names<T: Choice>(py: Python<'_>) -> PyResult<Bound<'_, PyTuple>> {
    PyTuple::new(py, T::NAMES)
}

/// `CHOICES`: every choice-valued option's names, the default first.
pub(crate) fn choices(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("blend", PyTuple::new(py, Method::NAMES)?)?;
    d.set_item("fidelity", names::<Fidelity>(py)?)?;
    d.set_item("poisson_solver", names::<PoissonSolver>(py)?)?;
    d.set_item("energy", names::<Energy>(py)?)?;
    d.set_item("solver", names::<Solver>(py)?)?;
    d.set_item("offsets", names::<Offsets>(py)?)?;
    d.set_item("loss", names::<Loss>(py)?)?;
    d.set_item("prior_fusion", names::<PriorFusion>(py)?)?;
    d.set_item("weights", names::<Weighting>(py)?)?;
    d.set_item("sampling", names::<Sampling>(py)?)?;
    Ok(d)
}

/// `LIMITS`: the bounds the option checks use.
pub(crate) fn limits(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("max_threads", MAX_THREADS)?;
    d.set_item("max_iterations", MAX_ITERATIONS)?;
    d.set_item("min_poisson_tolerance", MIN_POISSON_TOLERANCE)?;
    d.set_item("max_pole_cap_deg", MAX_POLE_CAP_DEG)?;
    d.set_item("max_prior_scale_deg", align::Options::MAX_PRIOR_SCALE_DEG)?;
    d.set_item("min_erp_width", layout::MIN_ERP_WIDTH)?;
    d.set_item("max_erp_width", layout::MAX_ERP_WIDTH)?;
    d.set_item("max_padding", layout::MAX_PADDING)?;
    d.set_item("min_tangent_width", layout::MIN_TANGENT_WIDTH)?;
    d.set_item("max_subdivisions", layout::MAX_SUBDIVISIONS)?;
    Ok(d)
}

/// `DEFAULTS`: the resolved default options (`align`, `blend`), and the defaults that depend on
/// another option: `schedules` per energy, `iterations` per alignment solver, `weights`
/// (smoothness, scale_weight), `offsets` and `loss` per energy; `poisson`, the Poisson blend's
/// options.
pub(crate) fn defaults(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("align", align_dict(py, &align::Options::default())?)?;
    d.set_item("blend", blend_dict(py, &Method::default())?)?;
    d.set_item(
        "poisson",
        blend_dict(py, &Method::Poisson(PoissonParams::default()))?,
    )?;
    let (schedules, weights, offsets) = (PyDict::new(py), PyDict::new(py), PyDict::new(py));
    let losses = PyDict::new(py);
    for &(energy, name) in Energy::ALL {
        schedules.set_item(name, PyList::new(py, energy.default_schedule())?)?;
        weights.set_item(name, energy.default_weights())?;
        offsets.set_item(name, energy.default_offsets().name())?;
        losses.set_item(name, energy.default_loss().name())?;
    }
    let iterations = PyDict::new(py);
    for &(solver, name) in Solver::ALL {
        iterations.set_item(name, solver.default_iterations())?;
    }
    d.set_item("schedules", schedules)?;
    d.set_item("iterations", iterations)?;
    d.set_item("weights", weights)?;
    d.set_item("offsets", offsets)?;
    d.set_item("losses", losses)?;
    Ok(d)
}
