//! Tangent images → ERP: [`ErpTaps`] (for every ERP row, the [`Run`]s of pixels each face sees
//! and their taps, each ranked by nearness to its face's axis), built by cone culling and
//! [`tap_at`]; sampling of tangent stacks along the runs; and [`tangents_to_erp`].

#[cfg(target_arch = "x86_64")]
use super::simd;
#[cfg(not(target_arch = "x86_64"))]
use super::taps::{lerp_f32, lerp_f32_edges, prefetch, PREFETCH_DISTANCE};
use super::taps::{Sampling, Tap, OFFSET_MASK, RANK_SHIFT};
use crate::camera::TangentCamera;
use crate::layout::Layout;
use crate::plan_array::PlanArray;
use crate::sphere::ErpGrid;
use rayon::prelude::*;

/// Most tangents one ERP pixel can be seen by (the icosahedron layout needs 5).
pub(crate) const MAX_FACES_PER_PIXEL: usize = 16;

/// Consecutive pixels of one ERP row that one face sees: columns `start..start + len`, whose
/// taps are `start_tap..start_tap + len` of the row (see [`ErpTaps::runs`]).
///
/// `repr(C)`: plan files store runs as these four words.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[repr(C)]
pub struct Run {
    /// Index of the tangent (camera) in the layout.
    pub face: u32,
    /// First ERP column.
    pub start: u32,
    /// Number of columns (≥ 1).
    pub len: u32,
    /// Index of the first column's tap (and sample) in the row.
    pub start_tap: u32,
}

// SAFETY: `repr(C)` of four u32: no padding, every bit pattern is a value (the loader checks
// a plan file's runs before use).
unsafe impl bytemuck::Zeroable for Run {}
// SAFETY: as above.
unsafe impl bytemuck::Pod for Run {}

impl Run {
    /// The run's columns.
    #[inline]
    #[must_use]
    pub fn columns(&self) -> std::ops::Range<usize> {
        self.start as usize..(self.start + self.len) as usize
    }

    /// The run's taps (and samples) in the row.
    #[inline]
    #[must_use]
    pub fn taps(&self) -> std::ops::Range<usize> {
        self.start_tap as usize..(self.start_tap + self.len) as usize
    }
}

/// Tangents → ERP map: for every ERP pixel, the tangent images that see it and where.
///
/// Stored face by face within each ERP row: a row is a list of [`Run`]s (sorted by face, then
/// column) over one array of taps. Blending walks a face's consecutive pixels without
/// per-pixel branching, the per-face images of `tangents_to_erp` are written as whole runs,
/// and the Poisson blend finds a face's neighbour sample one tap along. Per-face data is never
/// expanded to ERP size. Each tap carries its rank among the faces that see the pixel, nearest
/// axis first (for the icosahedron, rank 0 is the face whose triangle contains the pixel).
#[derive(Debug, Clone)]
pub struct ErpTaps {
    /// Number of taps of each ERP pixel.
    counts: PlanArray<u8>,
    rows: ErpRows,
    tangent_width: usize,
    tangent_pixels: usize,
    faces: usize,
}

#[derive(Debug, Clone, Default)]
struct ErpRow {
    runs: Vec<Run>,
    taps: Vec<Tap>,
}

/// The runs and taps of every ERP row.
#[derive(Debug, Clone)]
enum ErpRows {
    /// As built, row by row: gathering them into one array would cost a second copy of the
    /// largest structure of the plan.
    Built(Vec<ErpRow>),
    /// All rows' runs, then all rows' taps, as a plan file stores them; row `i` has runs
    /// `run_at[i]..run_at[i + 1]` and taps `tap_at[i]..tap_at[i + 1]`.
    Flat {
        runs: PlanArray<Run>,
        taps: PlanArray<Tap>,
        run_at: Vec<usize>,
        tap_at: Vec<usize>,
    },
}

impl ErpTaps {
    /// Taps for every ERP pixel of `layout`.
    ///
    /// # Panics
    /// If a tangent has more pixels than a tap can index (2^28; a layout check keeps them far
    /// smaller).
    pub fn build(layout: &Layout) -> Self {
        let (h, w) = layout.tangent_shape();
        assert!(
            h * w <= OFFSET_MASK as usize,
            "tangent images too large for ERP taps"
        );
        let (eh, ew) = (layout.erp_height, layout.erp_width);
        let grid = ErpGrid::new(eh, ew);
        let cones: Vec<Cone> = layout.cameras.iter().map(Cone::of).collect();
        let rows: Vec<(Vec<u8>, ErpRow)> = (0..eh)
            .into_par_iter()
            .map(|i| {
                let lat = crate::sphere::row_latitude(i as f64, eh);
                let mut counts = vec![0u8; ew];
                let mut row = ErpRow::default();
                // Four faces see a pixel on average.
                row.taps.reserve(ew * 4);
                let mut cosines: Vec<f64> = Vec::with_capacity(ew * 4);
                let (sp, cp) = grid.row_sin_cos(i);
                for (k, (cone, cam)) in cones.iter().zip(&layout.cameras).enumerate() {
                    // Along the row, the camera-frame ray R·d(λ) = sin λ·u + cos λ·v + c, and
                    // its z is the cosine to the axis: no trigonometry, one product per pixel.
                    let r = &cam.rotation;
                    let (u, v) = (r.column(0) * cp, r.column(2) * cp);
                    let c = r.column(1) * -sp;
                    for columns in cone.columns(lat, ew) {
                        let mut open = false;
                        for j in columns {
                            let (sl, cl) = grid.column_sin_cos(j);
                            let p = u * sl + v * cl + c;
                            let seen = p.z >= cone.min_cos
                                && p.z > 0.0
                                && (counts[j] as usize) < MAX_FACES_PER_PIXEL;
                            let tap = seen.then(|| {
                                let inv_z = 1.0 / p.z;
                                let x = cam.fx * p.x * inv_z + cam.cx;
                                tap_at(cam, x, cam.fy * p.y * inv_z + cam.cy, 0)
                            });
                            let Some(tap) = tap.flatten() else {
                                open = false;
                                continue;
                            };
                            if !open {
                                row.runs.push(Run {
                                    face: k as u32,
                                    start: j as u32,
                                    len: 0,
                                    start_tap: row.taps.len() as u32,
                                });
                                open = true;
                            }
                            if let Some(run) = row.runs.last_mut() {
                                run.len += 1;
                            }
                            row.taps.push(tap);
                            cosines.push(p.z);
                            counts[j] += 1;
                        }
                    }
                }
                rank_taps(&mut row, &cosines, &counts);
                (counts, row)
            })
            .collect();
        let mut counts = Vec::with_capacity(eh * ew);
        let mut taps = Vec::with_capacity(eh);
        for (row_counts, row) in rows {
            counts.extend(row_counts);
            taps.push(row);
        }
        Self {
            counts: counts.into(),
            rows: ErpRows::Built(taps),
            tangent_width: w,
            tangent_pixels: h * w,
            faces: layout.cameras.len(),
        }
    }

    /// Bytes held by the map (in memory, or mapped from a plan file).
    #[must_use]
    pub fn memory_bytes(&self) -> usize {
        let taps = self.len() * std::mem::size_of::<Tap>();
        let runs = (0..self.rows())
            .map(|i| std::mem::size_of_val(self.runs(i)) + 48)
            .sum::<usize>();
        taps + runs + self.counts.len()
    }

    /// Whether the map is read in place from a mapped plan file.
    #[must_use]
    pub fn is_mapped(&self) -> bool {
        matches!(&self.rows, ErpRows::Flat { taps, .. } if taps.is_mapped())
    }

    /// The runs and taps of ERP row `i`: what a plan file stores (see [`crate::plan_cache`]).
    #[inline]
    pub(crate) fn row_parts(&self, i: usize) -> (&[Run], &[Tap]) {
        match &self.rows {
            ErpRows::Built(rows) => (&rows[i].runs, &rows[i].taps),
            ErpRows::Flat {
                runs,
                taps,
                run_at,
                tap_at,
            } => (
                &runs[run_at[i]..run_at[i + 1]],
                &taps[tap_at[i]..tap_at[i + 1]],
            ),
        }
    }

    /// Number of ERP rows.
    pub(crate) fn rows(&self) -> usize {
        match &self.rows {
            ErpRows::Built(rows) => rows.len(),
            ErpRows::Flat { run_at, .. } => run_at.len().saturating_sub(1),
        }
    }

    /// The map of per-pixel `counts` and all rows' `runs` and `taps` of `layout`, row `i`
    /// holding runs `run_at[i]..run_at[i + 1]` and taps `tap_at[i]..tap_at[i + 1]` (a plan
    /// file's arrays); the caller has checked them against the layout.
    pub(crate) fn from_parts(
        layout: &Layout,
        counts: PlanArray<u8>,
        (runs, run_at): (PlanArray<Run>, Vec<usize>),
        (taps, tap_at): (PlanArray<Tap>, Vec<usize>),
    ) -> Self {
        let (h, w) = layout.tangent_shape();
        Self {
            counts,
            rows: ErpRows::Flat {
                runs,
                taps,
                run_at,
                tap_at,
            },
            tangent_width: w,
            tangent_pixels: h * w,
            faces: layout.cameras.len(),
        }
    }

    /// Total number of (ERP pixel, tangent) pairs.
    #[must_use]
    pub fn len(&self) -> usize {
        match &self.rows {
            ErpRows::Built(rows) => rows.iter().map(|r| r.taps.len()).sum(),
            ErpRows::Flat { taps, .. } => taps.len(),
        }
    }

    /// Whether no ERP pixel is seen by any tangent.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Number of tangents that see each ERP pixel (H·W, row-major).
    #[must_use]
    pub fn counts(&self) -> &[u8] {
        &self.counts
    }

    /// The runs of ERP row `i`, sorted by face, then column.
    #[must_use]
    pub fn runs(&self, i: usize) -> &[Run] {
        self.row_parts(i).0
    }

    /// Nearness rank (0 = nearest axis) of every tap of ERP row `i`, in tap order, into `out`.
    pub fn ranks(&self, i: usize, out: &mut Vec<u8>) {
        out.clear();
        out.extend(Ranks(self.row_parts(i).1.iter()));
    }

    /// The value of a tangent stack (N·h·w) at every tap of ERP row `i`, in tap order, into
    /// `out`, interpolated as `sampling` says: NaN when any of the four neighbours is NaN.
    ///
    /// # Panics
    /// If `stack` is not the size the taps were built for (the bindings check shapes first).
    pub fn sample(&self, stack: &[f32], sampling: Sampling, i: usize, out: &mut Vec<f32>) {
        self.sample_many([stack], sampling, i, [out]);
    }

    /// [`ErpTaps::sample`] of several stacks of the same size (a map and its blending weights)
    /// at once: each tap is decoded once for all of them. `first` is how the first stack is
    /// interpolated; the others are bilinear.
    ///
    /// # Panics
    /// If a stack is not the size the taps were built for.
    pub fn sample_many<const M: usize>(
        &self,
        stacks: [&[f32]; M],
        first: Sampling,
        i: usize,
        mut outs: [&mut Vec<f32>; M],
    ) {
        for stack in stacks {
            self.assert_stack(stack);
        }
        let (runs, taps) = self.row_parts(i);
        for out in &mut outs {
            out.clear();
            out.resize(taps.len(), 0.0);
        }
        for run in runs {
            let parts = outs.each_mut().map(|o| &mut o[run.taps()]);
            // SAFETY: the stacks have the size the taps were built for (asserted above).
            unsafe { self.sample_run(stacks, first, &taps[run.taps()], run, parts) };
        }
    }

    /// [`ErpTaps::sample`] one run at a time: calls `visit(run, values, ranks)` for each run of
    /// ERP row `i` with the run's values (in a buffer the size of one run, which stays in
    /// cache) and an iterator over their nearness ranks.
    ///
    /// # Panics
    /// If `stack` is not the size the taps were built for.
    #[inline]
    pub fn sample_runs(
        &self,
        stack: &[f32],
        sampling: Sampling,
        i: usize,
        buffer: &mut Vec<f32>,
        mut visit: impl FnMut(&Run, &[f32], Ranks<'_>),
    ) {
        self.sample_runs_many([stack], sampling, i, [buffer], |run, [values], ranks| {
            visit(run, values, ranks);
        });
    }

    /// [`ErpTaps::sample_runs`] of several stacks of the same size at once (see
    /// [`ErpTaps::sample_many`]): `visit` gets the run's values of each.
    ///
    /// # Panics
    /// If a stack is not the size the taps were built for.
    #[inline]
    pub fn sample_runs_many<const M: usize>(
        &self,
        stacks: [&[f32]; M],
        first: Sampling,
        i: usize,
        mut buffers: [&mut Vec<f32>; M],
        mut visit: impl FnMut(&Run, [&[f32]; M], Ranks<'_>),
    ) {
        for stack in stacks {
            self.assert_stack(stack);
        }
        let (runs, row_taps) = self.row_parts(i);
        for run in runs {
            let taps = &row_taps[run.taps()];
            for buffer in &mut buffers {
                buffer.clear();
                buffer.resize(taps.len(), 0.0);
            }
            let parts = buffers.each_mut().map(|b| &mut b[..]);
            // SAFETY: the stacks have the size the taps were built for (asserted above).
            unsafe { self.sample_run(stacks, first, taps, run, parts) };
            visit(run, buffers.each_ref().map(|b| &b[..]), Ranks(taps.iter()));
        }
    }

    fn assert_stack(&self, stack: &[f32]) {
        assert_eq!(
            stack.len(),
            self.tangent_pixels * self.faces,
            "tangent stack size mismatch"
        );
    }

    /// Values of each of `stacks` at the taps of `run` into `outs` (each as long as `taps`):
    /// the first as `first` says, the others bilinear.
    ///
    /// # Safety
    /// Each stack must have the size the taps were built for.
    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    unsafe fn sample_run<const M: usize>(
        &self,
        stacks: [&[f32]; M],
        first: Sampling,
        taps: &[Tap],
        run: &Run,
        outs: [&mut [f32]; M],
    ) {
        let (w, base) = (self.tangent_width, run.face as usize * self.tangent_pixels);
        #[cfg(target_arch = "x86_64")]
        {
            // SAFETY: the caller's contract is the kernel's.
            unsafe { simd::lerp_run_f32(stacks, first, base, w, taps, outs) };
        }
        #[cfg(not(target_arch = "x86_64"))]
        for (m, (stack, out)) in stacks.iter().zip(outs).enumerate() {
            let edges = m == 0 && first == Sampling::DepthEdges;
            for (t, (&tap, v)) in taps.iter().zip(out.iter_mut()).enumerate() {
                if let Some(ahead) = taps.get(t + PREFETCH_DISTANCE) {
                    let k = base + (ahead.index & OFFSET_MASK) as usize;
                    prefetch(stack, k);
                    prefetch(stack, k + w);
                }
                // SAFETY: taps of this map satisfy `lerp_f32`'s contract for a stack of the
                // size they were built for (the caller's contract).
                let k = base + (tap.index & OFFSET_MASK) as usize;
                *v = unsafe {
                    if edges {
                        lerp_f32_edges(stack, k, w, tap)
                    } else {
                        lerp_f32(stack, k, w, tap)
                    }
                };
            }
        }
    }
}

/// The nearness ranks (0 = nearest axis) of the taps of one run, in tap order.
#[derive(Debug, Clone)]
pub struct Ranks<'a>(std::slice::Iter<'a, Tap>);

impl Iterator for Ranks<'_> {
    type Item = u8;

    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    fn next(&mut self) -> Option<u8> {
        self.0.next().map(|t| (t.index >> RANK_SHIFT) as u8)
    }
}

/// Set each tap's nearness rank at its pixel: taps sorted by the cosine to their camera's
/// axis, largest first, ties to the lower face index (the order faces were visited in).
fn rank_taps(row: &mut ErpRow, cosines: &[f64], counts: &[u8]) {
    // The taps of each pixel, in face order, as a compressed-row list.
    let mut first = Vec::with_capacity(counts.len() + 1);
    let mut total = 0usize;
    first.push(0);
    for &n in counts {
        total += n as usize;
        first.push(total);
    }
    let mut fill = first.clone();
    let mut by_pixel = vec![0u32; total];
    for run in &row.runs {
        for (j, t) in run.columns().zip(run.taps()) {
            by_pixel[fill[j]] = t as u32;
            fill[j] += 1;
        }
    }
    for j in 0..counts.len() {
        let taps = &mut by_pixel[first[j]..first[j + 1]];
        // Stable: equal cosines keep face order.
        taps.sort_by(|&a, &b| cosines[b as usize].total_cmp(&cosines[a as usize]));
        for (rank, &t) in taps.iter().enumerate() {
            row.taps[t as usize].index |= (rank as u32) << RANK_SHIFT;
        }
    }
}

/// The cone around a camera's axis that holds every ray through its image.
struct Cone {
    min_cos: f64,
    /// Latitude and longitude of the axis.
    lat: f64,
    lon: f64,
}

impl Cone {
    fn of(cam: &TangentCamera) -> Self {
        let axis = cam.axis();
        Self {
            min_cos: cone_cosine(cam),
            lat: (-axis.y).asin(),
            lon: axis.x.atan2(axis.z),
        }
    }

    /// The columns of an ERP row at latitude `lat` (W columns) that may lie inside the cone, as
    /// two ascending ranges, either may be empty (a superset: one column of margin each side).
    fn columns(&self, lat: f64, width: usize) -> [std::ops::Range<usize>; 2] {
        const NONE: std::ops::Range<usize> = 0..0;
        // cos(angle to axis) = sin φ sin φ_a + cos φ cos φ_a cos(λ − λ_a) ≥ min_cos.
        let (sp, cp) = lat.sin_cos();
        let (sa, ca) = self.lat.sin_cos();
        let denom = cp * ca;
        let half = if denom <= 1e-12 {
            // At a pole (of the row or the axis) every column has the same angle.
            if sp * sa >= self.min_cos - 1e-9 {
                std::f64::consts::PI
            } else {
                return [NONE, NONE];
            }
        } else {
            let c = (self.min_cos - sp * sa) / denom;
            if c > 1.0 + 1e-9 {
                return [NONE, NONE];
            }
            c.clamp(-1.0, 1.0).acos()
        };
        let per_radian = width as f64 / std::f64::consts::TAU;
        let centre = (self.lon + std::f64::consts::PI) * per_radian - 0.5;
        let lo = (centre - half * per_radian).floor() as i64 - 1;
        let hi = (centre + half * per_radian).ceil() as i64 + 1; // inclusive
        let w = width as i64;
        if hi - lo + 1 >= w {
            return [0..width, NONE];
        }
        let a = lo.rem_euclid(w);
        let b = a + (hi - lo);
        if b < w {
            [a as usize..(b + 1) as usize, NONE]
        } else {
            [0..(b + 1 - w) as usize, a as usize..width]
        }
    }
}

/// Cosine of the widest angle between the axis of `cam` and a ray through its image (a corner),
/// lowered slightly so rounding can never reject a visible direction.
fn cone_cosine(cam: &TangentCamera) -> f64 {
    let (w, h) = (cam.width as f64 - 0.5, cam.height as f64 - 0.5);
    [(-0.5, -0.5), (w, -0.5), (-0.5, h), (w, h)]
        .iter()
        .map(|&(x, y)| cam.spherical_factor(x, y))
        .fold(1.0, f64::min)
        - 1e-9
}

/// Tap of the tangent pixel grid of `cam` (flat offset `base`) at continuous position (x, y),
/// if on the image; positions within half a pixel of the border are clamped onto the outermost
/// pixel centres.
#[inline]
fn tap_at(cam: &TangentCamera, x: f64, y: f64, base: usize) -> Option<Tap> {
    if !cam.contains(x, y) {
        return None;
    }
    let (w, h) = (cam.width, cam.height);
    let x = x.clamp(0.0, (w - 1) as f64);
    let y = y.clamp(0.0, (h - 1) as f64);
    let x0 = (x as usize).min(w - 2); // x ≥ 0: truncation is floor
    let y0 = (y as usize).min(h - 2);
    Some(Tap::new(
        (base + y0 * w + x0) as u32,
        x - x0 as f64,
        y - y0 as f64,
    ))
}

/// Each tangent image mapped onto the ERP grid, read as `sampling` says: `out` (N, H, W) is
/// overwritten, NaN where a face does not see the pixel (or a bilinear neighbour is NaN).
///
/// One pass over the output: each row of each face plane is written once, runs and NaN gaps in
/// column order, while the row's samples are still in cache.
///
/// # Panics
/// If `out` is not N·H·W long or `tangents` not N·h·w.
pub fn tangents_to_erp(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    sampling: Sampling,
    out: &mut [f32],
) {
    let (eh, ew) = (layout.erp_height, layout.erp_width);
    let (faces, plane) = (layout.cameras.len(), eh * ew);
    assert_eq!(
        out.len(),
        faces * plane,
        "output size does not match the plan"
    );
    let ptr = SharedMut(out.as_mut_ptr());
    (0..eh)
        .into_par_iter()
        .for_each_init(Vec::new, |values, i| {
            let ptr = &ptr;
            taps.sample(tangents, sampling, i, values);
            let mut runs = taps.runs(i).iter().peekable();
            for face in 0..faces {
                // SAFETY: face < N and i < H, so the row lies inside `out` (length asserted
                // above); each (face, row) is written by exactly one iteration, so no two
                // slices alias.
                let row =
                    unsafe { std::slice::from_raw_parts_mut(ptr.0.add(face * plane + i * ew), ew) };
                let mut at = 0;
                while let Some(run) = runs.next_if(|r| r.face as usize == face) {
                    row[at..run.start as usize].fill(f32::NAN);
                    row[run.columns()].copy_from_slice(&values[run.taps()]);
                    at = run.columns().end;
                }
                row[at..].fill(f32::NAN);
            }
        });
}

/// A raw pointer that may be shared between threads for provably disjoint writes.
struct SharedMut<T>(*mut T);
// SAFETY: only used for writes to disjoint elements, see the call sites.
unsafe impl<T> Sync for SharedMut<T> {}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::resample::taps::{lerp_f32, lerp_f32_edges};

    /// The runs hold exactly the taps a brute-force search over every camera finds, each
    /// pixel's taps ranked by angle to the axis, and runs are sorted, disjoint and unwrapped.
    #[test]
    fn runs_match_a_brute_force_search() {
        for (width, padding) in [(256, 0.3), (300, 0.0), (512, 0.6)] {
            let layout = Layout::icosahedron(width, padding, None).expect("layout");
            let taps = ErpTaps::build(&layout);
            let (eh, ew) = (layout.erp_height, layout.erp_width);
            let grid = ErpGrid::new(eh, ew);
            for i in 0..eh {
                let (runs, row_taps) = taps.row_parts(i);
                assert!(runs
                    .windows(2)
                    .all(|p| (p[0].face, p[0].start + p[0].len) <= (p[1].face, p[1].start)));
                assert!(runs
                    .iter()
                    .all(|r| r.len > 0 && (r.start + r.len) as usize <= ew));
                // (face, tap, rank) per pixel from the runs...
                let mut got = vec![Vec::new(); ew];
                for run in runs {
                    for (j, t) in run.columns().zip(run.taps()) {
                        let tap = row_taps[t];
                        let rank = tap.index >> RANK_SHIFT;
                        got[j].push((
                            run.face as usize,
                            tap.index & OFFSET_MASK,
                            tap.fx,
                            tap.fy,
                            rank,
                        ));
                    }
                }
                // ... and from every camera, ranked by the cosine to its axis: the projection
                // of the pixel's direction, computed here the plain way. Rounding may flip a
                // position lying on an image edge or change a fraction's last unit.
                for (j, got) in got.iter_mut().enumerate() {
                    let d = grid.direction(i, j);
                    let mut want: Vec<(f64, usize, Tap, (f64, f64))> = layout
                        .cameras
                        .iter()
                        .enumerate()
                        .filter_map(|(k, cam)| {
                            let (x, y) = cam.project(&d)?;
                            Some((-cam.axis().dot(&d), k, tap_at(cam, x, y, 0)?, (x, y)))
                        })
                        .collect();
                    want.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                    let ranked: Vec<_> = want
                        .iter()
                        .enumerate()
                        .map(|(rank, &(_, k, tap, _))| (k, tap.index, tap.fx, tap.fy, rank as u32))
                        .collect();
                    got.sort_unstable();
                    let on_edge = |&(_, k, _, (x, y)): &(f64, usize, Tap, (f64, f64))| {
                        let cam = &layout.cameras[k];
                        let (w, h) = (cam.width as f64 - 0.5, cam.height as f64 - 0.5);
                        [x + 0.5, w - x, y + 0.5, h - y]
                            .iter()
                            .any(|e| e.abs() < 1e-9)
                    };
                    if got.len() != ranked.len() {
                        assert!(want.iter().any(on_edge), "width {width}, pixel ({i}, {j})");
                        continue;
                    }
                    let mut ranked = ranked;
                    ranked.sort_unstable();
                    for (g, r) in got.iter().zip(&ranked) {
                        assert_eq!((g.0, g.1, g.4), (r.0, r.1, r.4), "pixel ({i}, {j})");
                        assert!(g.2.abs_diff(r.2) <= 1 && g.3.abs_diff(r.3) <= 1);
                    }
                    assert_eq!(taps.counts()[i * ew + j] as usize, got.len());
                }
            }
        }
    }

    /// The vectorised run sampling gives the scalar value's exact bits (NaN where a
    /// neighbour is NaN), bilinear and across depth edges, on noise with scattered NaNs (its
    /// neighbours nearly always span an edge): a swapped lane or pair would differ. Sampling
    /// two stacks at once (`sample_many`) gives each one's bits too, the second bilinear.
    #[test]
    fn run_sampling_matches_the_scalar_lerp_bit_for_bit() {
        let layout = Layout::icosahedron(256, 0.3, None).expect("layout");
        let taps = ErpTaps::build(&layout);
        let (h, w) = layout.tangent_shape();
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        let stack: Vec<f32> = (0..20 * h * w)
            .map(|p| {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                if p % 97 == 0 {
                    f32::NAN
                } else {
                    (state >> 40) as f32 / (1u64 << 24) as f32
                }
            })
            .collect();
        let other: Vec<f32> = stack.iter().rev().map(|v| 2.0 * v).collect();
        let same = |a: f32, b: f32| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
        let (mut got, mut nan, mut edges) = (Vec::new(), 0, 0);
        let (mut first, mut second) = (Vec::new(), Vec::new());
        for sampling in [Sampling::Bilinear, Sampling::DepthEdges] {
            for i in 0..layout.erp_height {
                taps.sample(&stack, sampling, i, &mut got);
                taps.sample_many([&stack, &other], sampling, i, [&mut first, &mut second]);
                let (runs, row_taps) = taps.row_parts(i);
                for run in runs {
                    for t in run.taps() {
                        let tap = row_taps[t];
                        let k = run.face as usize * h * w + (tap.index & OFFSET_MASK) as usize;
                        // SAFETY: a tap of these taps, on stacks of their size.
                        let (want, want_other, bilinear) = unsafe {
                            let want = match sampling {
                                Sampling::Bilinear => lerp_f32(&stack, k, w, tap),
                                Sampling::DepthEdges => lerp_f32_edges(&stack, k, w, tap),
                            };
                            (
                                want,
                                lerp_f32(&other, k, w, tap),
                                lerp_f32(&stack, k, w, tap),
                            )
                        };
                        nan += usize::from(want.is_nan());
                        edges += usize::from(!same(want, bilinear));
                        assert!(same(got[t], want), "row {i}, tap {t}: {} vs {want}", got[t]);
                        assert!(
                            same(first[t], want) && same(second[t], want_other),
                            "row {i}"
                        );
                    }
                }
            }
        }
        assert!(nan > 0, "the NaN path was not exercised");
        assert!(edges > 0, "the depth-edge path was not exercised");
    }
}
