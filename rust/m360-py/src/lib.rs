//! `m360._core`: the compiled module. Converts arrays, releases the GIL, maps errors; no algorithm.
//!
//! The Python package validates every user argument before calling in here; the checks below
//! are a second line so that a mistake in that validation still gives a Python exception
//! (`m360.errors.InputError`), never a panic.

use m360_core::blend::{
    self as core_blend, Fidelity, PoissonParams, PoissonReport, Solver, Weighting,
};
use m360_core::layout::Layout;
use m360_core::resample;
use m360_core::stitch::{self, Blend};
use m360_core::{CoreError, TangentCamera};
use numpy::ndarray::{Array, IxDyn};
use numpy::{
    IntoPyArray, PyArrayDyn, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3,
    PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, RwLock};

pyo3::import_exception!(m360.errors, M360Error);
pyo3::import_exception!(m360.errors, InputError);
pyo3::import_exception!(m360.errors, SolverError);

/// A core error on its way to Python (the orphan rule forbids `From<CoreError> for PyErr`).
struct PyCoreError(CoreError);

impl From<PyCoreError> for PyErr {
    fn from(err: PyCoreError) -> PyErr {
        match err.0 {
            e @ (CoreError::InvalidLayout(_)
            | CoreError::ShapeMismatch { .. }
            | CoreError::Degenerate(_)
            | CoreError::InvalidOption(_)) => InputError::new_err(e.to_string()),
            e @ (CoreError::NonFinite(_) | CoreError::Solver(_)) => {
                SolverError::new_err(e.to_string())
            }
        }
    }
}

fn input_error(msg: impl Into<String>) -> PyErr {
    InputError::new_err(msg.into())
}

// ---------------------------------------------------------------------------------------------
// Threads: one explicitly sized rayon pool for every heavy call.

static POOL: RwLock<Option<Arc<rayon::ThreadPool>>> = RwLock::new(None);

fn default_threads() -> usize {
    std::env::var("M360_NUM_THREADS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&n| n > 0)
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

fn build_pool(threads: usize) -> PyResult<Arc<rayon::ThreadPool>> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("m360-{i}"))
        .build()
        .map(Arc::new)
        .map_err(|e| M360Error::new_err(format!("cannot start {threads} threads: {e}")))
}

fn pool() -> PyResult<Arc<rayon::ThreadPool>> {
    if let Some(pool) = POOL.read().ok().and_then(|g| g.clone()) {
        return Ok(pool);
    }
    let mut guard = POOL
        .write()
        .map_err(|_| M360Error::new_err("thread pool lock poisoned"))?;
    match guard.as_ref() {
        Some(pool) => Ok(pool.clone()),
        None => {
            let pool = build_pool(default_threads())?;
            *guard = Some(pool.clone());
            Ok(pool)
        }
    }
}

/// Run heavy work without the GIL on m360's pool; a panic becomes `M360Error`, never a crash.
fn detached<T: Send>(py: Python<'_>, work: impl FnOnce() -> T + Send) -> PyResult<T> {
    let pool = pool()?;
    py.detach(|| catch_unwind(AssertUnwindSafe(|| pool.install(work))))
        .map_err(|panic| {
            let msg = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            M360Error::new_err(format!(
                "internal error in m360's core (please report): {msg}"
            ))
        })
}

/// Most worker threads `set_num_threads` starts: a larger count is a typo, and spawning it
/// would take seconds to minutes before failing or working no faster.
const MAX_THREADS: usize = 1024;

/// Set the number of worker threads of m360's compiled core (None: `M360_NUM_THREADS` or all
/// cores), at most 1024. Results do not depend on it.
#[pyfunction]
#[pyo3(signature = (threads=None))]
fn set_num_threads(threads: Option<&Bound<'_, PyAny>>) -> PyResult<()> {
    let threads = match threads {
        None => default_threads(),
        Some(value) => {
            let bad = || {
                let shown = value.repr().map_or_else(|_| "?".into(), |r| r.to_string());
                input_error(format!(
                    "threads must be an integer in [1, {MAX_THREADS}] or None, got {shown}"
                ))
            };
            if value.is_instance_of::<pyo3::types::PyBool>() {
                return Err(bad());
            }
            match value.extract::<i64>() {
                Ok(n) if (1..=MAX_THREADS as i64).contains(&n) => n as usize,
                _ => return Err(bad()),
            }
        }
    };
    let pool = build_pool(threads)?;
    *POOL
        .write()
        .map_err(|_| M360Error::new_err("thread pool lock poisoned"))? = Some(pool);
    Ok(())
}

/// Number of worker threads of m360's compiled core.
#[pyfunction]
fn get_num_threads() -> PyResult<usize> {
    Ok(pool()?.current_num_threads())
}

// ---------------------------------------------------------------------------------------------
// Arrays.

fn to_numpy<'py, T: numpy::Element>(
    py: Python<'py>,
    data: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    Array::from_shape_vec(IxDyn(shape), data)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| M360Error::new_err(format!("internal shape error: {e}")))
}

/// A new zero-filled C-contiguous array for the core to write into: numpy's allocator (which
/// asks for huge pages on large arrays) instead of a Rust `Vec` handed over afterwards. Unlike
/// `PyArray::zeros` (which panics on a null pointer) a failed allocation is an `InputError`.
fn output_array<'py, T: numpy::Element>(
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

fn writable<'a, T: numpy::Element>(
    array: &'a mut numpy::PyReadwriteArrayDyn<'_, T>,
) -> PyResult<&'a mut [T]> {
    array
        .as_slice_mut()
        .map_err(|e| M360Error::new_err(format!("internal error: output not contiguous: {e}")))
}

fn contiguous<'a, T: numpy::Element, D: numpy::ndarray::Dimension>(
    array: &'a numpy::PyReadonlyArray<'_, T, D>,
    name: &str,
) -> PyResult<&'a [T]> {
    array
        .as_slice()
        .map_err(|_| input_error(format!("{name} must be a C-contiguous array")))
}

fn check_shape(name: &str, actual: &[usize], expected: &[usize]) -> PyResult<()> {
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
enum ErpImage<'py> {
    U8(PyReadonlyArray3<'py, u8>),
    F32(PyReadonlyArray3<'py, f32>),
}

fn parse_energy(name: &str) -> PyResult<m360_core::align::Energy> {
    use m360_core::align::Energy;
    match name {
        "paper" => Ok(Energy::Paper),
        "normalized" => Ok(Energy::Normalized),
        _ => Err(input_error(format!(
            "unknown energy {name:?}: 'normalized' or 'paper'"
        ))),
    }
}

fn parse_offsets(name: &str) -> PyResult<m360_core::align::Offsets> {
    use m360_core::align::Offsets;
    match name {
        "perspective" => Ok(Offsets::Perspective),
        "spherical" => Ok(Offsets::Spherical),
        _ => Err(input_error(format!(
            "unknown offsets {name:?}: 'perspective' or 'spherical'"
        ))),
    }
}

// ---------------------------------------------------------------------------------------------
// Layouts and plans.

/// The icosahedron layout's cameras: (rotations (N,3,3), intrinsics (N,4) as fx, fy, cx, cy,
/// (height, width), face triangles (N,3,2) in gnomonic coordinates).
#[pyfunction]
#[pyo3(signature = (erp_width, padding=0.3, tangent_width=None))]
#[allow(clippy::type_complexity)]
fn icosahedron_cameras(
    py: Python<'_>,
    erp_width: usize,
    padding: f64,
    tangent_width: Option<usize>,
) -> PyResult<(
    Bound<'_, PyArrayDyn<f64>>,
    Bound<'_, PyArrayDyn<f64>>,
    (usize, usize),
    Bound<'_, PyArrayDyn<f64>>,
)> {
    let layout = Layout::icosahedron(erp_width, padding, tangent_width).map_err(PyCoreError)?;
    let n = layout.cameras.len();
    let rotations = layout
        .cameras
        .iter()
        .flat_map(|c| (0..9).map(move |k| c.rotation[(k / 3, k % 3)]))
        .collect();
    let intrinsics = layout
        .cameras
        .iter()
        .flat_map(|c| [c.fx, c.fy, c.cx, c.cy])
        .collect();
    let polygons = layout
        .face_polygons
        .iter()
        .flatten()
        .flatten()
        .copied()
        .collect();
    Ok((
        to_numpy(py, rotations, &[n, 3, 3])?,
        to_numpy(py, intrinsics, &[n, 4])?,
        layout.tangent_shape(),
        to_numpy(py, polygons, &[n, 3, 2])?,
    ))
}

/// Sampling maps of one layout at one ERP size, built on first use and reused.
#[pyclass(frozen, module = "m360._core")]
struct Plan {
    inner: m360_core::Plan,
}

#[pymethods]
impl Plan {
    /// A plan for cameras given as rotations (N,3,3) world→camera and intrinsics (N,4)
    /// (fx, fy, cx, cy), all of size `tangent_shape` = (h, w), for an ERP of `erp_shape` = (H, W).
    #[new]
    fn new(
        erp_shape: (usize, usize),
        rotations: PyReadonlyArray3<'_, f64>,
        intrinsics: PyReadonlyArray2<'_, f64>,
        tangent_shape: (usize, usize),
    ) -> PyResult<Self> {
        let n = rotations.shape()[0];
        check_shape("rotations", rotations.shape(), &[n, 3, 3])?;
        check_shape("intrinsics", intrinsics.shape(), &[n, 4])?;
        let rot = rotations.as_array();
        let intr = intrinsics.as_array();
        let cameras = (0..n)
            .map(|k| TangentCamera {
                rotation: nalgebra::Matrix3::from_fn(|r, c| rot[[k, r, c]]),
                fx: intr[[k, 0]],
                fy: intr[[k, 1]],
                cx: intr[[k, 2]],
                cy: intr[[k, 3]],
                width: tangent_shape.1,
                height: tangent_shape.0,
            })
            .collect();
        let layout = Layout::new(erp_shape.0, erp_shape.1, cameras, vec![]).map_err(PyCoreError)?;
        Ok(Self {
            inner: m360_core::Plan::new(layout),
        })
    }

    /// Build the sampling maps now instead of on first use ("tangents", "erp" or "all").
    #[pyo3(signature = (which="all"))]
    fn prepare(&self, py: Python<'_>, which: &str) -> PyResult<()> {
        let (tangents, erp) = match which {
            "tangents" => (true, false),
            "erp" => (false, true),
            "all" => (true, true),
            _ => {
                return Err(input_error(format!(
                    "unknown map {which:?}: 'tangents', 'erp' or 'all'"
                )))
            }
        };
        detached(py, || {
            if tangents {
                self.inner.tangent_taps();
            }
            if erp {
                self.inner.erp_taps();
            }
        })
    }

    /// Bytes held by the maps built so far.
    fn memory_bytes(&self) -> usize {
        self.inner.memory_bytes()
    }

    /// (H, W) number of tangents that see each ERP pixel.
    fn coverage<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<u8>>> {
        let counts = detached(py, || self.inner.erp_taps().counts().to_vec())?;
        let layout = self.inner.layout();
        to_numpy(py, counts, &[layout.erp_height, layout.erp_width])
    }

    /// Bilinear ERP (H,W,C) uint8 or float32 → tangents (N,h,w,C) of the same dtype.
    fn erp_to_tangents<'py>(
        &self,
        py: Python<'py>,
        erp: ErpImage<'py>,
    ) -> PyResult<Bound<'py, PyAny>> {
        match erp {
            ErpImage::U8(a) => Ok(self.sample_tangents(py, &a)?.into_any()),
            ErpImage::F32(a) => Ok(self.sample_tangents(py, &a)?.into_any()),
        }
    }

    /// Tangents (N,h,w) float32 → per-face ERP maps (N,H,W) float32, NaN where a face is blind.
    fn tangents_to_erp<'py>(
        &self,
        py: Python<'py>,
        tangents: PyReadonlyArray3<'py, f32>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let layout = self.inner.layout();
        self.check_tangents("tangents", tangents.shape())?;
        let data = contiguous(&tangents, "tangents")?;
        let out = output_array(
            py,
            &[layout.cameras.len(), layout.erp_height, layout.erp_width],
        )?;
        {
            let mut rw = out.readwrite();
            let dst = writable(&mut rw)?;
            detached(py, || {
                resample::tangents_to_erp(self.inner.erp_taps(), layout, data, dst)
            })?;
        }
        Ok(out)
    }

    /// Perspective disparity (N,h,w) float32 (NaN or mask False = no estimate) → spherical
    /// disparity per tangent (N,h,w) float32, NaN where invalid.
    #[pyo3(signature = (perspective, mask=None))]
    fn spherical_disparity<'py>(
        &self,
        py: Python<'py>,
        perspective: PyReadonlyArray3<'py, f32>,
        mask: Option<PyReadonlyArray3<'py, bool>>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let layout = self.inner.layout();
        self.check_tangents("tangent_disparity", perspective.shape())?;
        let data = contiguous(&perspective, "tangent_disparity")?;
        let mask = match &mask {
            Some(m) => {
                self.check_tangents("mask", m.shape())?;
                Some(contiguous(m, "mask")?)
            }
            None => None,
        };
        let out = output_array(py, perspective.shape())?;
        {
            let mut rw = out.readwrite();
            let dst = writable(&mut rw)?;
            detached(py, || stitch::spherical_disparity(layout, data, mask, dst))?;
        }
        Ok(out)
    }

    /// Align spherical disparity maps (N,h,w) float32 (NaN = invalid): returns the aligned
    /// maps, and per level a report dict and the fields (N, rows, cols, 2) as (s, o).
    #[pyo3(signature = (maps, levels, energy, smoothness, scale, solver, max_iterations, tolerance, sample_fraction, pole_cap_deg, offsets))]
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    fn align<'py>(
        &self,
        py: Python<'py>,
        maps: PyReadonlyArray3<'py, f32>,
        levels: Vec<(usize, usize)>,
        energy: &str,
        smoothness: f64,
        scale: f64,
        solver: &str,
        max_iterations: usize,
        tolerance: f64,
        sample_fraction: f64,
        pole_cap_deg: f64,
        offsets: &str,
    ) -> PyResult<(
        Bound<'py, PyArrayDyn<f32>>,
        Vec<Bound<'py, pyo3::types::PyDict>>,
        Vec<Bound<'py, PyArrayDyn<f64>>>,
    )> {
        use m360_core::align::{self, AlignOptions, LevelParams, Solver};
        let layout = self.inner.layout();
        let (h, w) = layout.tangent_shape();
        self.check_tangents("maps", maps.shape())?;
        let energy = parse_energy(energy)?;
        let offsets = parse_offsets(offsets)?;
        let solver = match solver {
            "lbfgs" => Solver::Lbfgs,
            "newton" => Solver::Newton,
            _ => return Err(input_error(format!("unknown solver {solver:?}"))),
        };
        for &(cols, rows) in &levels {
            if cols < 2 || rows < 2 || cols > w || rows > h {
                return Err(input_error(format!(
                    "grid {cols}x{rows} must be at least 2x2 and at most the tangent size {w}x{h}"
                )));
            }
        }
        let options = AlignOptions {
            levels: levels
                .iter()
                .map(|&(cols, rows)| LevelParams {
                    cols,
                    rows,
                    energy,
                    smoothness,
                    scale,
                    offsets,
                })
                .collect(),
            solver,
            max_iterations,
            tolerance,
        };
        let data = contiguous(&maps, "maps")?;
        let out = output_array::<f32>(py, maps.shape())?;
        let solved = {
            let mut rw = out.readwrite();
            let dst = writable(&mut rw)?;
            dst.copy_from_slice(data);
            detached(py, || {
                let overlaps = self.inner.overlaps(sample_fraction, pole_cap_deg);
                align::align(layout, dst, &overlaps, &options)
            })?
            .map_err(PyCoreError)?
        };
        let n = layout.cameras.len();
        let mut reports = Vec::with_capacity(solved.len());
        let mut grids = Vec::with_capacity(solved.len());
        for level in solved {
            let r = &level.report;
            let d = pyo3::types::PyDict::new(py);
            d.set_item("grid", (level.params.cols, level.params.rows))?;
            d.set_item("iterations", r.iterations)?;
            d.set_item("initial_energy", r.initial_energy)?;
            d.set_item("energy", r.energy)?;
            d.set_item("gradient_norm", r.gradient_norm)?;
            d.set_item("converged", r.converged)?;
            d.set_item("samples", r.samples)?;
            d.set_item("build_seconds", level.build_seconds)?;
            d.set_item("solve_seconds", level.solve_seconds)?;
            reports.push(d);
            let shape = [n, level.params.rows, level.params.cols, 2];
            grids.push(to_numpy(py, level.fields, &shape)?);
        }
        Ok((out, reports, grids))
    }

    /// The first-level alignment problem of `maps` (standardised as `align` does): a dict with
    /// `nodes` (K,8) uint32, `coef_s`, `coef_o` (K,8) float64, `edges` (E,3) float64 as
    /// (p, q, weight), `scale_weight`, `gauge_weight`; unknowns are node-interleaved (s, o).
    /// For benchmarks and independent checks of the energy.
    #[pyo3(signature = (maps, grid, energy, smoothness, scale, sample_fraction, pole_cap_deg, offsets))]
    #[allow(clippy::too_many_arguments)]
    fn alignment_problem<'py>(
        &self,
        py: Python<'py>,
        maps: PyReadonlyArray3<'py, f32>,
        grid: (usize, usize),
        energy: &str,
        smoothness: f64,
        scale: f64,
        sample_fraction: f64,
        pole_cap_deg: f64,
        offsets: &str,
    ) -> PyResult<Bound<'py, pyo3::types::PyDict>> {
        use m360_core::align::{self, LevelParams, Problem};
        let layout = self.inner.layout();
        self.check_tangents("maps", maps.shape())?;
        let energy = parse_energy(energy)?;
        let offsets = parse_offsets(offsets)?;
        let params = LevelParams {
            cols: grid.0,
            rows: grid.1,
            energy,
            smoothness,
            scale,
            offsets,
        };
        let mut data = contiguous(&maps, "maps")?.to_vec();
        let problem = detached(py, || -> m360_core::error::Result<Problem> {
            align::standardize(layout, &mut data, offsets)?;
            let overlaps = self.inner.overlaps(sample_fraction, pole_cap_deg);
            Ok(Problem::new(layout, &data, &overlaps, params))
        })?
        .map_err(PyCoreError)?;
        let (nodes, coef_s, coef_o, edges, scale_weight, gauge_weight) = problem.terms();
        let k = nodes.len();
        let d = pyo3::types::PyDict::new(py);
        d.set_item(
            "nodes",
            to_numpy(py, nodes.iter().flatten().copied().collect(), &[k, 8])?,
        )?;
        d.set_item(
            "coef_s",
            to_numpy(py, coef_s.iter().flatten().copied().collect(), &[k, 8])?,
        )?;
        d.set_item(
            "coef_o",
            to_numpy(py, coef_o.iter().flatten().copied().collect(), &[k, 8])?,
        )?;
        let flat_edges = edges
            .iter()
            .flat_map(|&(p, q, w)| [p as f64, q as f64, w])
            .collect();
        d.set_item("edges", to_numpy(py, flat_edges, &[edges.len(), 3])?)?;
        d.set_item("scale_weight", scale_weight)?;
        d.set_item("gauge_weight", gauge_weight)?;
        d.set_item("unknowns", problem.len())?;
        Ok(d)
    }

    /// Blend per-tangent maps (N,h,w) float32 (NaN = invalid) onto the ERP grid with `blend` in
    /// {"mean", "nn", "radial", "frustum", "poisson"}: (disparity (H,W) float32, spread (H,W)
    /// float32 or None without `spread`, report dict). `fidelity` ("nn", "frustum", "mean"),
    /// `lam`, `tol` and `max_iterations` apply to "poisson" only.
    #[pyo3(signature = (tangents, blend, fidelity="frustum", lam=0.1,
                        tol=1e-6, max_iterations=2000, solver="multigrid", spread=true))]
    #[allow(clippy::type_complexity, clippy::too_many_arguments)]
    fn blend<'py>(
        &self,
        py: Python<'py>,
        tangents: PyReadonlyArray3<'py, f32>,
        blend: &str,
        fidelity: &str,
        lam: f64,
        tol: f64,
        max_iterations: usize,
        solver: &str,
        spread: bool,
    ) -> PyResult<(
        Bound<'py, PyArrayDyn<f32>>,
        Option<Bound<'py, PyArrayDyn<f32>>>,
        Bound<'py, PyDict>,
    )> {
        enum Mode {
            Simple(Blend),
            Weighted(Weighting),
            Poisson(PoissonParams),
        }
        let mode = match blend {
            "mean" => Mode::Simple(Blend::Mean),
            "nn" => Mode::Simple(Blend::Nearest),
            "radial" => Mode::Weighted(Weighting::Radial),
            "frustum" => Mode::Weighted(Weighting::Frustum),
            "poisson" => Mode::Poisson(PoissonParams {
                lambda: lam,
                fidelity: parse_fidelity(fidelity)?,
                tolerance: tol,
                max_iterations,
                solver: parse_solver(solver)?,
            }),
            _ => {
                return Err(input_error(format!(
                    "unknown blend {blend:?}: 'mean', 'nn', 'radial', 'frustum' or 'poisson'"
                )))
            }
        };
        let layout = self.inner.layout();
        self.check_tangents("tangents", tangents.shape())?;
        let data = contiguous(&tangents, "tangents")?;
        let shape = [layout.erp_height, layout.erp_width];
        let disparity = output_array(py, &shape)?;
        let spread = spread.then(|| output_array(py, &shape)).transpose()?;
        let report = PyDict::new(py);
        report.set_item("mode", blend)?;
        let poisson = {
            let mut rw_d = disparity.readwrite();
            let mut rw_s = spread.as_ref().map(|s| s.readwrite());
            let dst_d = writable(&mut rw_d)?;
            let dst_s = rw_s.as_mut().map(writable).transpose()?;
            let plan = &self.inner;
            detached(py, || match &mode {
                Mode::Simple(m) => {
                    stitch::blend(plan.erp_taps(), layout, data, *m, dst_d, dst_s);
                    Ok(None)
                }
                Mode::Weighted(kind) => {
                    core_blend::weighted_blend(
                        plan.erp_taps(),
                        layout,
                        data,
                        plan.tap_weights(*kind),
                        dst_d,
                        dst_s,
                    );
                    Ok(None)
                }
                Mode::Poisson(params) => core_blend::poisson_blend(
                    plan.erp_taps(),
                    layout,
                    data,
                    plan.tap_weights(Weighting::Frustum),
                    params,
                    dst_d,
                    dst_s,
                )
                .map(Some),
            })?
            .map_err(PyCoreError)?
        };
        if let (Some(r), Mode::Poisson(params)) = (poisson, &mode) {
            fill_report(&report, &r, params, fidelity)?;
        }
        Ok((disparity, spread, report))
    }

    /// Per-face blending weights (N,h,w) float32 of `kind` in {"nn", "mean", "radial",
    /// "frustum"}, on each tangent's pixel grid.
    fn blend_weights<'py>(
        &self,
        py: Python<'py>,
        kind: &str,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let kind = parse_weighting(kind)?;
        let layout = self.inner.layout();
        let (h, w) = layout.tangent_shape();
        let data = detached(py, || core_blend::weight_maps(layout, kind))?;
        to_numpy(py, data, &[layout.cameras.len(), h, w])
    }
}

fn parse_fidelity(name: &str) -> PyResult<Fidelity> {
    match name {
        "nn" => Ok(Fidelity::Nearest),
        "frustum" => Ok(Fidelity::Frustum),
        "mean" => Ok(Fidelity::Mean),
        _ => Err(input_error(format!(
            "unknown Poisson fidelity {name:?}: 'frustum', 'nn' or 'mean'"
        ))),
    }
}

fn parse_solver(name: &str) -> PyResult<Solver> {
    match name {
        "multigrid" => Ok(Solver::Multigrid),
        "fused" => Ok(Solver::Fused),
        "faer" => Ok(Solver::Faer),
        _ => Err(input_error(format!(
            "unknown Poisson solver {name:?}: 'multigrid', 'fused' or 'faer'"
        ))),
    }
}

fn parse_weighting(name: &str) -> PyResult<Weighting> {
    match name {
        "nn" => Ok(Weighting::Nearest),
        "mean" => Ok(Weighting::Mean),
        "radial" => Ok(Weighting::Radial),
        "frustum" => Ok(Weighting::Frustum),
        _ => Err(input_error(format!(
            "unknown weights {name:?}: 'nn', 'mean', 'radial' or 'frustum'"
        ))),
    }
}

fn fill_report(
    report: &Bound<'_, PyDict>,
    r: &PoissonReport,
    params: &PoissonParams,
    fidelity: &str,
) -> PyResult<()> {
    let solver = match params.solver {
        Solver::Multigrid => "multigrid",
        Solver::Fused => "fused",
        Solver::Faer => "faer",
    };
    report.set_item("solver", solver)?;
    report.set_item("iterations", r.iterations)?;
    report.set_item("relative_residual", r.relative_residual)?;
    report.set_item("initial_residual", r.initial_residual)?;
    report.set_item("tolerance", params.tolerance)?;
    report.set_item("converged", r.relative_residual <= params.tolerance)?;
    report.set_item("lambda", params.lambda)?;
    report.set_item("fidelity", fidelity)?;
    report.set_item("unknowns", r.unknowns)?;
    report.set_item("assemble_seconds", r.assemble_seconds)?;
    report.set_item("solve_seconds", r.solve_seconds)?;
    Ok(())
}

/// The Poisson blend of K maps already on an ERP grid: `values` and `weights` (K,H,W) float32
/// (NaN value = invalid), fidelity `target` (H,W) float32 (NaN only where no layer is valid):
/// (B (H,W) float64, report dict).
#[pyfunction]
#[pyo3(signature = (values, weights, target, lam=0.1,
                    tol=1e-6, max_iterations=2000, solver="multigrid"))]
#[allow(clippy::too_many_arguments)]
fn poisson_blend<'py>(
    py: Python<'py>,
    values: PyReadonlyArray3<'py, f32>,
    weights: PyReadonlyArray3<'py, f32>,
    target: PyReadonlyArray2<'py, f32>,
    lam: f64,
    tol: f64,
    max_iterations: usize,
    solver: &str,
) -> PyResult<(Bound<'py, PyArrayDyn<f64>>, Bound<'py, PyDict>)> {
    let shape = values.shape().to_vec();
    check_shape("weights", weights.shape(), &shape)?;
    check_shape("target", target.shape(), &shape[1..])?;
    let (h, w) = (shape[1], shape[2]);
    let (v, wt, t) = (
        contiguous(&values, "values")?,
        contiguous(&weights, "weights")?,
        contiguous(&target, "target")?,
    );
    let params = PoissonParams {
        lambda: lam,
        fidelity: Fidelity::Nearest,
        tolerance: tol,
        max_iterations,
        solver: parse_solver(solver)?,
    };
    let out = output_array(py, &[h, w])?;
    let report = {
        let mut rw = out.readwrite();
        let dst = writable(&mut rw)?;
        detached(py, || {
            core_blend::poisson_blend_layers(v, wt, t, h, w, &params, dst)
        })?
        .map_err(PyCoreError)?
    };
    let dict = PyDict::new(py);
    dict.set_item("mode", "poisson")?;
    fill_report(&dict, &report, &params, "given")?;
    Ok((out, dict))
}

impl Plan {
    fn sample_tangents<'py, T: resample::Texel + numpy::Element>(
        &self,
        py: Python<'py>,
        erp: &PyReadonlyArray3<'py, T>,
    ) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
        let layout = self.inner.layout();
        let (h, w) = layout.tangent_shape();
        let c = self.check_erp(erp.shape())?;
        let data = contiguous(erp, "erp")?;
        let out = output_array(py, &[layout.cameras.len(), h, w, c])?;
        {
            let mut rw = out.readwrite();
            let dst = writable(&mut rw)?;
            detached(py, || {
                resample::erp_to_tangents(self.inner.tangent_taps(), layout, data, c, dst)
            })?;
        }
        Ok(out)
    }

    fn check_erp(&self, shape: &[usize]) -> PyResult<usize> {
        let layout = self.inner.layout();
        let c = shape[2];
        if !(1..=4).contains(&c) {
            return Err(input_error(format!(
                "erp has {c} channels, expected 1 to 4"
            )));
        }
        check_shape("erp", shape, &[layout.erp_height, layout.erp_width, c])?;
        Ok(c)
    }

    fn check_tangents(&self, name: &str, shape: &[usize]) -> PyResult<()> {
        let layout = self.inner.layout();
        let (h, w) = layout.tangent_shape();
        check_shape(name, shape, &[layout.cameras.len(), h, w])
    }
}

#[pymodule]
mod _core {
    #[pymodule_export]
    use super::{get_num_threads, icosahedron_cameras, poisson_blend, set_num_threads, Plan};

    #[pymodule_init]
    fn init(m: &pyo3::Bound<'_, pyo3::types::PyModule>) -> pyo3::PyResult<()> {
        use pyo3::types::PyModuleMethods;
        // faer would otherwise run its own thread pool inside calls that already run on m360's
        // rayon pool; m360 parallelises over its own data, so faer's kernels run sequentially.
        faer::set_global_parallelism(faer::Par::Seq);
        m.add("__version__", env!("CARGO_PKG_VERSION"))
    }
}
