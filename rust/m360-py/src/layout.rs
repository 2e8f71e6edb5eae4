//! Layouts and plans: the icosahedron's cameras, and the `Plan` class whose methods run every
//! per-image operation on one layout's cached maps.

use crate::arrays::{check_shape, contiguous, output_array, to_numpy, writable, ErpImage};
use crate::errors::{core, input_error};
use crate::threads::on_pool;
use crate::{align, blend};
use m360_core::layout::Layout;
use m360_core::options::Choice;
use m360_core::plan::Need;
use m360_core::{resample, stitch, TangentCamera};
use numpy::{
    PyArray3, PyArrayDyn, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// The icosahedron layout's cameras (each face split `subdivisions` times into 4): (rotations
/// (N,3,3), intrinsics (N,4) as fx, fy, cx, cy, (height, width), face triangles (N,3,2) in
/// gnomonic coordinates).
#[pyfunction]
#[pyo3(signature = (erp_width, padding=0.3, tangent_width=None, subdivisions=0))]
#[allow(clippy::type_complexity)]
pub(crate) fn icosahedron_cameras(
    py: Python<'_>,
    erp_width: usize,
    padding: f64,
    tangent_width: Option<usize>,
    subdivisions: usize,
) -> PyResult<(
    Bound<'_, PyArrayDyn<f64>>,
    Bound<'_, PyArrayDyn<f64>>,
    (usize, usize),
    Bound<'_, PyArrayDyn<f64>>,
)> {
    let layout = core(Layout::icosahedron_subdivided(
        erp_width,
        padding,
        tangent_width,
        subdivisions,
    ))?;
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
pub(crate) struct Plan {
    pub(crate) inner: m360_core::Plan,
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
        let layout = core(Layout::new(erp_shape.0, erp_shape.1, cameras, vec![]))?;
        Ok(Self {
            inner: m360_core::Plan::new(layout),
        })
    }

    /// Build the sampling maps now instead of on first use ("tangents", "erp", "all" for both,
    /// or "estimate": both, the default blend's weights and the default alignment's samples).
    #[pyo3(signature = (which="all"))]
    fn prepare(&self, py: Python<'_>, which: &str) -> PyResult<()> {
        let defaults = m360_core::align::Options::default();
        let estimate = [
            Need::TangentTaps,
            Need::ErpTaps,
            Need::WeightMaps(m360_core::blend::Weighting::Frustum),
            Need::Overlaps(defaults.sample_fraction, defaults.pole_cap_deg),
        ];
        let needs: &[Need] = match which {
            "tangents" => &[Need::TangentTaps],
            "erp" => &[Need::ErpTaps],
            "all" => &[Need::TangentTaps, Need::ErpTaps],
            "estimate" => &estimate,
            _ => {
                return Err(input_error(format!(
                    "unknown map {which:?}: 'tangents', 'erp', 'all' or 'estimate'"
                )))
            }
        };
        on_pool(py, Some((&self.inner, needs)), || ())
    }

    /// Keep this plan's maps in the folder `path` (look there before building, write every map
    /// built), or not (`None`). See `m360.plan_cache`.
    #[pyo3(signature = (path=None))]
    fn set_cache_dir(&self, path: Option<std::path::PathBuf>) {
        self.inner.set_disk_cache(path);
    }

    /// The folder of the disk cache, or `None`.
    fn cache_dir(&self) -> Option<std::path::PathBuf> {
        self.inner.disk_cache()
    }

    /// How many maps were loaded from disk, built, saved, how many files were rejected, and how
    /// many loaded maps read their file in place (memory-mapped, not copied).
    fn cache_stats(&self) -> std::collections::HashMap<&'static str, usize> {
        let s = self.inner.disk_stats();
        [
            ("loaded", s.loaded),
            ("built", s.built),
            ("saved", s.saved),
            ("rejected", s.rejected),
            ("mapped", s.mapped),
        ]
        .into()
    }

    /// Bytes held by the maps built so far.
    fn memory_bytes(&self) -> usize {
        self.inner.memory_bytes()
    }

    /// (H, W) number of tangents that see each ERP pixel.
    fn coverage<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<u8>>> {
        let plan = &self.inner;
        let counts = on_pool(py, Some((plan, &[Need::ErpTaps])), || {
            plan.erp_taps().counts().to_vec()
        })?;
        let layout = plan.layout();
        to_numpy(py, counts, &[layout.erp_height, layout.erp_width])
    }

    /// (N, h, w) float32 length |q| of every tangent pixel's ray q = ((x − cx)/fx,
    /// (y − cy)/fy, 1): spherical disparity = perspective disparity / |q|.
    fn ray_lengths<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let layout = self.inner.layout();
        let (h, w) = layout.tangent_shape();
        let lengths = on_pool(py, None, || stitch::ray_lengths(layout))?;
        to_numpy(py, lengths, &[layout.cameras.len(), h, w])
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

    /// Tangents (N,h,w) float32 → per-face ERP maps (N,H,W) float32, NaN where a face is blind;
    /// `sampling` "bilinear" or "depth_edges" (as the blends read disparity).
    #[pyo3(signature = (tangents, sampling="bilinear"))]
    fn tangents_to_erp<'py>(
        &self,
        py: Python<'py>,
        tangents: PyReadonlyArray3<'py, f32>,
        sampling: &str,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let sampling = core(resample::Sampling::parse(sampling))?;
        let plan = &self.inner;
        let layout = plan.layout();
        self.check_tangents("tangents", tangents.shape())?;
        let data = contiguous(&tangents, "tangents")?;
        let out = output_array(
            py,
            &[layout.cameras.len(), layout.erp_height, layout.erp_width],
        )?;
        {
            let mut rw = out.readwrite();
            let dst = writable(&mut rw)?;
            on_pool(py, Some((plan, &[Need::ErpTaps])), || {
                resample::tangents_to_erp(plan.erp_taps(), layout, data, sampling, dst);
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
        self.check_tangents("tangents", perspective.shape())?;
        let data = contiguous(&perspective, "tangents")?;
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
            on_pool(py, None, || {
                stitch::spherical_disparity(layout, data, mask, dst);
            })?;
        }
        Ok(out)
    }

    /// Align spherical disparity maps (N,h,w) float32 (NaN = invalid) with the options in the
    /// dict `align` (see `stitch_options`): the aligned maps, and per level a report dict and
    /// the fields (N, rows, cols, 2) as (s, o), and the fallback taken for lack of overlap
    /// samples (`"none"`, `"coarser_grid"`, `"affine"` or `"unaligned"`). With `in_place`
    /// the maps (writable, C-contiguous) are aligned where they are and returned.
    #[pyo3(signature = (maps, align, in_place=false))]
    #[allow(clippy::type_complexity)]
    fn align<'py>(
        &self,
        py: Python<'py>,
        maps: &Bound<'py, PyArray3<f32>>,
        align: &Bound<'py, PyDict>,
        in_place: bool,
    ) -> PyResult<(
        Bound<'py, PyArrayDyn<f32>>,
        Vec<Bound<'py, PyDict>>,
        Vec<Bound<'py, PyArrayDyn<f64>>>,
        &'static str,
    )> {
        self.check_tangents("maps", maps.shape())?;
        align::align(py, &self.inner, maps, align, in_place)
    }

    /// `align` with a global prior (docs/method.md, "Global prior"): `prior` (Hp, 2·Hp) float32
    /// spherical disparity (NaN = unknown), `prior_confidence` the same shape in [0, 1] or None,
    /// `absolute` whether the result is to be expressed in the prior's units. Returns what
    /// `align` does and the prior's fit: a dict `affine` (a, b: the prior in the result's units
    /// is a·P + b), `samples`, `outvoted` (share of the prior's pull lost to its IRLS weights),
    /// `weight`, `residual` (median |residual|, standardised), `tangent_spread` (the tangents'
    /// relative spread after the first level, or None), `tangent_share` (how much of their
    /// low-frequency disagreement moved the prior), `consensus_outvoted` (the share of prior
    /// samples their consensus outvoted), `low_order_gap` and `low_order_share` (the prior's
    /// disagreement with that consensus at the sphere's largest scales, and how much of it
    /// moved the prior), or None when no level ran.
    #[pyo3(signature = (maps, align, prior, prior_confidence=None, absolute=false, in_place=false))]
    #[allow(clippy::type_complexity, clippy::too_many_arguments)]
    fn align_with_prior<'py>(
        &self,
        py: Python<'py>,
        maps: &Bound<'py, PyArray3<f32>>,
        align: &Bound<'py, PyDict>,
        prior: PyReadonlyArray2<'py, f32>,
        prior_confidence: Option<PyReadonlyArray2<'py, f32>>,
        absolute: bool,
        in_place: bool,
    ) -> PyResult<(
        Bound<'py, PyArrayDyn<f32>>,
        Vec<Bound<'py, PyDict>>,
        Vec<Bound<'py, PyArrayDyn<f64>>>,
        &'static str,
        Option<Bound<'py, PyDict>>,
    )> {
        self.check_tangents("maps", maps.shape())?;
        let prior = align::prior_from(&prior, prior_confidence.as_ref(), absolute)?;
        align::align_with_prior(py, &self.inner, maps, align, in_place, Some(&prior))
    }

    /// Energy and gradient of the first-level alignment problem of `maps` on `grid` with the
    /// options in `align`, at `x` (None: identity fields; the unknowns node-interleaved, then
    /// the prior's (α, β)), with a prior term when `prior` (float32 ERP, see `align_with_prior`)
    /// is given, its samples reweighted at `reweight_at` (default `x`): (energy, gradient, x).
    /// For gradient checks.
    #[pyo3(signature = (maps, grid, align, x=None, prior=None, prior_confidence=None, reweight_at=None))]
    #[allow(clippy::type_complexity, clippy::too_many_arguments)]
    fn alignment_energy<'py>(
        &self,
        py: Python<'py>,
        maps: PyReadonlyArray3<'py, f32>,
        grid: (usize, usize),
        align: &Bound<'py, PyDict>,
        x: Option<Vec<f64>>,
        prior: Option<PyReadonlyArray2<'py, f32>>,
        prior_confidence: Option<PyReadonlyArray2<'py, f32>>,
        reweight_at: Option<Vec<f64>>,
    ) -> PyResult<(
        f64,
        Bound<'py, PyArrayDyn<f64>>,
        Bound<'py, PyArrayDyn<f64>>,
    )> {
        self.check_tangents("maps", maps.shape())?;
        let prior = prior
            .map(|p| align::prior_from(&p, prior_confidence.as_ref(), false))
            .transpose()?;
        align::alignment_energy(
            py,
            &self.inner,
            &maps,
            grid,
            align,
            x,
            prior.as_ref(),
            reweight_at,
        )
    }

    /// The first-level alignment problem of `maps` (standardised as `align` does) on grid
    /// (cols, rows) with the options in `align`: a dict with `nodes` (K,8) uint32, `coef_s`,
    /// `coef_o` (K,8) float64, `edges` (E,3) float64 as (p, q, weight), `scale_weight`,
    /// `gauge_weight`, `unknowns`; unknowns are node-interleaved (s, o). For benchmarks and
    /// independent checks of the energy.
    fn alignment_problem<'py>(
        &self,
        py: Python<'py>,
        maps: PyReadonlyArray3<'py, f32>,
        grid: (usize, usize),
        align: &Bound<'py, PyDict>,
    ) -> PyResult<Bound<'py, PyDict>> {
        self.check_tangents("maps", maps.shape())?;
        align::alignment_problem(py, &self.inner, &maps, grid, align)
    }

    /// Blend per-tangent maps (N,h,w) float32 (NaN = invalid) onto the ERP grid with the
    /// method and options in the dict `blend` (see `stitch_options`): (disparity (H,W)
    /// float32, confidence (H,W) float32 or None without `confidence`, report dict). With
    /// `prior` (Hp, 2·Hp) float32 (and optionally `prior_confidence`), the prior mapped into
    /// the tangents' units by `prior_affine` = (a, b) (a·P + b, the alignment's fit) votes in
    /// the consensus blend, and the confidence includes the disagreement with it,
    /// √(c² + (d − a·P − b)²) (docs/method.md, "Global prior").
    #[pyo3(signature = (tangents, blend, confidence=true, prior=None, prior_confidence=None, prior_affine=(1.0, 0.0)))]
    #[allow(clippy::type_complexity, clippy::too_many_arguments)]
    fn blend<'py>(
        &self,
        py: Python<'py>,
        tangents: PyReadonlyArray3<'py, f32>,
        blend: &Bound<'py, PyDict>,
        confidence: bool,
        prior: Option<PyReadonlyArray2<'py, f32>>,
        prior_confidence: Option<PyReadonlyArray2<'py, f32>>,
        prior_affine: (f64, f64),
    ) -> PyResult<(
        Bound<'py, PyArrayDyn<f32>>,
        Option<Bound<'py, PyArrayDyn<f32>>>,
        Bound<'py, PyDict>,
    )> {
        self.check_tangents("tangents", tangents.shape())?;
        let prior = prior
            .as_ref()
            .map(|p| align::prior_from(p, prior_confidence.as_ref(), false))
            .transpose()?;
        let vote = prior.as_ref().map(|prior| m360_core::blend::PriorVote {
            prior,
            scale: prior_affine.0,
            offset: prior_affine.1,
        });
        blend::blend(py, &self.inner, &tangents, blend, confidence, vote.as_ref())
    }

    /// Per-face blending weights (N,h,w) float32 of `kind` (one of `CHOICES["weights"]`), on
    /// each tangent's pixel grid.
    fn blend_weights<'py>(
        &self,
        py: Python<'py>,
        kind: &str,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        blend::weights(py, &self.inner, kind)
    }
}

impl Plan {
    fn sample_tangents<'py, T: resample::Texel + numpy::Element>(
        &self,
        py: Python<'py>,
        erp: &PyReadonlyArray3<'py, T>,
    ) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
        let plan = &self.inner;
        let layout = plan.layout();
        let (h, w) = layout.tangent_shape();
        let c = self.check_erp(erp.shape())?;
        let data = contiguous(erp, "erp")?;
        let out = output_array(py, &[layout.cameras.len(), h, w, c])?;
        {
            let mut rw = out.readwrite();
            let dst = writable(&mut rw)?;
            on_pool(py, Some((plan, &[Need::TangentTaps])), || {
                resample::erp_to_tangents(plan.tangent_taps(), layout, data, c, dst);
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
