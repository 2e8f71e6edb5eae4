//! Alignment through a plan: options from a dict in, aligned maps and reports out.

use crate::arrays::{contiguous, contiguous_mut, output_array, to_numpy, writable};
use crate::errors::{core, input_error};
use crate::options::align_options;
use crate::threads::on_pool;
use m360_core::align::{self, Alignment, LevelParams, Overlaps, Prior, PriorFit, Problem};
use m360_core::options::Choice;
use m360_core::plan::{Need, Plan};
use numpy::{
    PyArray3, PyArrayDyn, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;

#[allow(clippy::type_complexity)]
pub(crate) fn align<'py>(
    py: Python<'py>,
    plan: &Plan,
    maps: &Bound<'py, PyArray3<f32>>,
    options: &Bound<'py, PyDict>,
    in_place: bool,
) -> PyResult<(
    Bound<'py, PyArrayDyn<f32>>,
    Vec<Bound<'py, PyDict>>,
    Vec<Bound<'py, PyArrayDyn<f64>>>,
    &'static str,
)> {
    let (out, reports, grids, fallback, _) =
        align_with_prior(py, plan, maps, options, in_place, None)?;
    Ok((out, reports, grids, fallback))
}

/// A prior from its ERP values (Hp, Wp), optional confidence and whether it is absolute.
pub(crate) fn prior_from(
    values: &PyReadonlyArray2<'_, f32>,
    confidence: Option<&PyReadonlyArray2<'_, f32>>,
    absolute: bool,
) -> PyResult<Prior> {
    let shape = values.shape();
    let (height, width) = (shape[0], shape[1]);
    let values = contiguous2(values, "prior")?.to_vec();
    let confidence = match confidence {
        Some(c) => {
            if c.shape() != shape {
                return Err(input_error(format!(
                    "prior_confidence has shape {:?}, the prior {:?}",
                    c.shape(),
                    shape
                )));
            }
            Some(contiguous2(c, "prior_confidence")?.to_vec())
        }
        None => None,
    };
    let prior = Prior {
        values,
        confidence,
        height,
        width,
        absolute,
    };
    core(prior.validate())?;
    Ok(prior)
}

fn contiguous2<'a>(array: &'a PyReadonlyArray2<'_, f32>, what: &str) -> PyResult<&'a [f32]> {
    array
        .as_slice()
        .map_err(|_| input_error(format!("{what} must be C-contiguous")))
}

/// The prior's fit as a dict.
fn prior_dict<'py>(py: Python<'py>, fit: &PriorFit) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("affine", fit.affine)?;
    d.set_item("samples", fit.samples)?;
    d.set_item("outvoted", fit.outvoted)?;
    d.set_item("weight", fit.weight)?;
    d.set_item("residual", fit.residual)?;
    d.set_item("tangent_spread", fit.tangent_spread)?;
    d.set_item("tangent_share", fit.tangent_share)?;
    d.set_item("consensus_outvoted", fit.consensus_outvoted)?;
    d.set_item("low_order_gap", fit.low_order_gap)?;
    d.set_item("low_order_share", fit.low_order_share)?;
    Ok(d)
}

/// [`align`] with an optional prior; also returns the prior's fit (None without a prior or
/// when no level ran).
#[allow(clippy::type_complexity)]
pub(crate) fn align_with_prior<'py>(
    py: Python<'py>,
    plan: &Plan,
    maps: &Bound<'py, PyArray3<f32>>,
    options: &Bound<'py, PyDict>,
    in_place: bool,
    prior: Option<&Prior>,
) -> PyResult<(
    Bound<'py, PyArrayDyn<f32>>,
    Vec<Bound<'py, PyDict>>,
    Vec<Bound<'py, PyArrayDyn<f64>>>,
    &'static str,
    Option<Bound<'py, PyDict>>,
)> {
    let layout = plan.layout();
    let options = align_options(options, Some(layout.tangent_shape()))?;
    let needs = [Need::Overlaps(
        options.sample_fraction,
        options.pole_cap_deg,
    )];
    // The alignment on the pool, from the overlaps to each level's sample origins as
    // (tangent a, pixel index in a, tangent b).
    let run = |solve: &mut (dyn FnMut(&Overlaps) -> Result<Alignment, m360_core::CoreError>
                         + Send)| {
        core(on_pool(py, Some((plan, &needs)), || {
            let overlaps = plan.overlaps(options.sample_fraction, options.pole_cap_deg);
            let solved = solve(&overlaps)?;
            let origins: Vec<Vec<i64>> = solved
                .levels
                .iter()
                .map(|level| {
                    level
                        .sample_origins
                        .iter()
                        .flat_map(|&k| {
                            let (a, pa, b) = overlaps.sample(k as usize);
                            [a as i64, pa as i64, b as i64]
                        })
                        .collect()
                })
                .collect();
            Ok::<_, m360_core::CoreError>((solved, origins))
        })?)
    };
    let (out, (solved, origins)) = if in_place {
        let mut rw = maps
            .try_readwrite()
            .map_err(|e| input_error(format!("maps cannot be aligned in place: {e}")))?;
        let data = contiguous_mut(&mut rw, "maps")?;
        let solved =
            run(&mut |overlaps| align::align_with_prior(layout, data, overlaps, &options, prior))?;
        (maps.to_dyn().clone(), solved)
    } else {
        let readonly = maps
            .try_readonly()
            .map_err(|e| input_error(format!("maps cannot be read: {e}")))?;
        let data = contiguous(&readonly, "maps")?;
        let out = output_array::<f32>(py, maps.shape())?;
        let mut rw = out.readwrite();
        let dst = writable(&mut rw)?;
        let solved = run(&mut |overlaps| {
            align::align_into_with_prior(layout, data, dst, overlaps, &options, prior)
        })?;
        drop(rw);
        (out, solved)
    };
    let fallback = solved.fallback.name();
    let fit = solved
        .prior
        .as_ref()
        .map(|f| prior_dict(py, f))
        .transpose()?;
    let n = layout.cameras.len();
    let mut reports = Vec::with_capacity(solved.levels.len());
    let mut grids = Vec::with_capacity(solved.levels.len());
    for (level, origin) in solved.levels.into_iter().zip(origins) {
        let r = &level.report;
        let d = PyDict::new(py);
        d.set_item("grid", (level.params.cols, level.params.rows))?;
        d.set_item("iterations", r.iterations)?;
        d.set_item("initial_energy", r.initial_energy)?;
        d.set_item("energy", r.energy)?;
        d.set_item("gradient_norm", r.gradient_norm)?;
        d.set_item("converged", r.converged)?;
        d.set_item("samples", r.samples)?;
        d.set_item("build_seconds", level.build_seconds)?;
        d.set_item("solve_seconds", level.solve_seconds)?;
        d.set_item("loss", options.loss.name())?;
        d.set_item("robust_scale", level.robust_scale)?;
        let k = level.sample_weights.len();
        d.set_item("sample_weights", to_numpy(py, level.sample_weights, &[k])?)?;
        d.set_item("sample_pixels", to_numpy(py, origin, &[k, 3])?)?;
        reports.push(d);
        let shape = [n, level.params.rows, level.params.cols, 2];
        grids.push(to_numpy(py, level.fields, &shape)?);
    }
    Ok((out, reports, grids, fallback, fit))
}

/// The options of one level on `grid` (the rest from `options`), its parameters and a copy of
/// `maps` to standardise: what the inspection functions below share.
fn single_level(
    plan: &Plan,
    maps: &PyReadonlyArray3<'_, f32>,
    grid: (usize, usize),
    options: &Bound<'_, PyDict>,
) -> PyResult<(align::Options, LevelParams, Vec<f32>)> {
    let shape = plan.layout().tangent_shape();
    let mut options = align_options(options, Some(shape))?;
    options.levels = vec![grid];
    let options = core(options.validate(Some(shape)))?;
    let params = options.level_params()[0];
    Ok((options, params, contiguous(maps, "maps")?.to_vec()))
}

pub(crate) fn alignment_problem<'py>(
    py: Python<'py>,
    plan: &Plan,
    maps: &PyReadonlyArray3<'py, f32>,
    grid: (usize, usize),
    options: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyDict>> {
    let layout = plan.layout();
    let (options, params, mut data) = single_level(plan, maps, grid, options)?;
    let needs = [Need::Overlaps(
        options.sample_fraction,
        options.pole_cap_deg,
    )];
    let problem = core(on_pool(py, Some((plan, &needs)), || {
        align::standardize(layout, &mut data, options.offsets)?;
        let overlaps = plan.overlaps(options.sample_fraction, options.pole_cap_deg);
        Ok::<_, m360_core::CoreError>(Problem::new(layout, &data, &overlaps, params))
    })?)?;
    let (nodes, coef_s, coef_o, edges, scale_weight, gauge_weight) = problem.terms();
    let k = nodes.len();
    let d = PyDict::new(py);
    let flat = |rows: Vec<[f64; 8]>| rows.into_iter().flatten().collect::<Vec<f64>>();
    d.set_item(
        "nodes",
        to_numpy(py, nodes.into_iter().flatten().collect(), &[k, 8])?,
    )?;
    d.set_item("coef_s", to_numpy(py, flat(coef_s), &[k, 8])?)?;
    d.set_item("coef_o", to_numpy(py, flat(coef_o), &[k, 8])?)?;
    let flat_edges = edges
        .iter()
        .flat_map(|&(p, q, w)| [f64::from(p), f64::from(q), w])
        .collect();
    d.set_item("edges", to_numpy(py, flat_edges, &[edges.len(), 3])?)?;
    d.set_item("scale_weight", scale_weight)?;
    d.set_item("gauge_weight", gauge_weight)?;
    d.set_item("unknowns", problem.len())?;
    Ok(d)
}

/// Energy and gradient at `x` (None: identity fields) of the first-level problem on `grid`,
/// with the prior term when given, its samples reweighted (consensus IRLS) at `reweight_at`
/// (default `x`): for checks of the gradient against finite differences.
#[allow(clippy::type_complexity, clippy::too_many_arguments)]
pub(crate) fn alignment_energy<'py>(
    py: Python<'py>,
    plan: &Plan,
    maps: &PyReadonlyArray3<'py, f32>,
    grid: (usize, usize),
    options: &Bound<'py, PyDict>,
    x: Option<Vec<f64>>,
    prior: Option<&Prior>,
    reweight_at: Option<Vec<f64>>,
) -> PyResult<(
    f64,
    Bound<'py, PyArrayDyn<f64>>,
    Bound<'py, PyArrayDyn<f64>>,
)> {
    let layout = plan.layout();
    let (options, params, mut data) = single_level(plan, maps, grid, options)?;
    let needs = [Need::Overlaps(
        options.sample_fraction,
        options.pole_cap_deg,
    )];
    let (energy, grad, x) = core(on_pool(py, Some((plan, &needs)), || {
        align::standardize(layout, &mut data, options.offsets)?;
        let overlaps = plan.overlaps(options.sample_fraction, options.pole_cap_deg);
        let samples = prior
            .map(|p| {
                align::PriorSamples::build(
                    layout,
                    &data,
                    p,
                    options.sample_fraction,
                    0.5 * options.prior_scale_deg,
                )
            })
            .transpose()?;
        let mut problem = Problem::with_prior(
            layout,
            data.as_slice(),
            &overlaps,
            params,
            samples.as_ref().map(|s| (s, options.prior_weight)),
        );
        let x = x.unwrap_or_else(|| problem.identity());
        let at = reweight_at.unwrap_or_else(|| x.clone());
        for v in [&x, &at] {
            if v.len() != problem.len() {
                return Err(m360_core::CoreError::ShapeMismatch {
                    what: "x (the problem's unknowns)",
                    expected: vec![problem.len()],
                    actual: vec![v.len()],
                });
            }
        }
        problem.reweight_prior(&at);
        let mut grad = vec![0.0; x.len()];
        let energy = problem.energy(&x, Some(&mut grad));
        Ok::<_, m360_core::CoreError>((energy, grad, x))
    })?)?;
    let n = grad.len();
    Ok((energy, to_numpy(py, grad, &[n])?, to_numpy(py, x, &[n])?))
}
