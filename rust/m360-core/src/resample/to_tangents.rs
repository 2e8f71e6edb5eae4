//! ERP → tangent images: [`TangentTaps`] (one tap into the ERP per tangent pixel, with the
//! corners of taps that wrap in longitude or over a pole), [`erp_to_tangents`], and the scalar
//! run sampling with its prefetch (the u8 SIMD paths are in `simd.rs`).

use super::taps::{prefetch, Tap, Texel, PREFETCH_DISTANCE, WRAPPED};
use crate::camera::TangentCamera;
use crate::layout::Layout;
use crate::plan_array::PlanArray;
use crate::sphere::direction_to_pixel;
use rayon::prelude::*;

/// ERP → tangent map: one tap into the ERP image per tangent pixel, in (face, row, column) order.
#[derive(Debug, Clone)]
pub struct TangentTaps {
    taps: PlanArray<Tap>,
    /// ERP pixel indices (top-left, top-right, bottom-left, bottom-right) of wrapped taps.
    wrapped: PlanArray<[u32; 4]>,
    erp_width: usize,
    erp_pixels: usize,
}

impl TangentTaps {
    /// Taps for every pixel of every camera of `layout`.
    ///
    /// ERP positions cost two `atan2` per pixel, so they are computed once per set of cameras
    /// that differ only by a turn about the vertical axis (the five faces of each icosahedron
    /// band): such a camera sees the same positions shifted in longitude.
    #[must_use]
    pub fn build(layout: &Layout) -> Self {
        let (h, w) = layout.tangent_shape();
        let (eh, ew) = (layout.erp_height, layout.erp_width);
        let bases = vertical_symmetry(layout);
        let base_ids: Vec<usize> = (0..layout.cameras.len())
            .filter(|&k| bases[k].0 == k)
            .collect();
        let base_rows: Vec<Vec<(f64, f64)>> = (0..base_ids.len() * h)
            .into_par_iter()
            .map(|at| {
                let cam = &layout.cameras[base_ids[at / h]];
                let r = (at % h) as f64;
                (0..w)
                    .map(|c| direction_to_pixel(&cam.pixel_direction(c as f64, r), eh, ew))
                    .collect()
            })
            .collect();
        let slot = |k: usize| base_ids.iter().position(|&b| b == k).unwrap_or(0);
        let rows: Vec<(Vec<Tap>, Vec<[u32; 4]>)> = (0..layout.cameras.len() * h)
            .into_par_iter()
            .map(|face_row| {
                let (base, shift) = bases[face_row / h];
                let positions = &base_rows[slot(base) * h + face_row % h];
                let mut taps = Vec::with_capacity(w);
                let mut wrapped = Vec::new();
                for &(u, v) in positions {
                    // Shifted longitudes stay in [−0.5, W − 0.5), where the grid starts.
                    let u = (u + shift + 0.5).rem_euclid(ew as f64) - 0.5;
                    // u, v ≥ −0.5, so truncating u + 1 is floor(u) + 1 without a libm call.
                    let (j0, i0) = ((u + 1.0) as i64 - 1, (v + 1.0) as i64 - 1);
                    let (fx, fy) = (u - j0 as f64, v - i0 as f64);
                    if j0 >= 0 && i0 >= 0 && j0 + 1 < ew as i64 && i0 + 1 < eh as i64 {
                        taps.push(Tap::new((i0 as usize * ew + j0 as usize) as u32, fx, fy));
                    } else {
                        let at = |i: i64, j: i64| erp_index_wrapped(i, j, eh, ew);
                        let corners = [
                            at(i0, j0),
                            at(i0, j0 + 1),
                            at(i0 + 1, j0),
                            at(i0 + 1, j0 + 1),
                        ];
                        taps.push(Tap::new(WRAPPED | wrapped.len() as u32, fx, fy));
                        wrapped.push(corners);
                    }
                }
                (taps, wrapped)
            })
            .collect();
        let mut taps = Vec::with_capacity(layout.cameras.len() * h * w);
        let mut wrapped = Vec::new();
        for (row_taps, row_wrapped) in rows {
            let offset = wrapped.len() as u32;
            taps.extend(row_taps.into_iter().map(|t| {
                if t.index & WRAPPED != 0 {
                    Tap {
                        index: WRAPPED | ((t.index & !WRAPPED) + offset),
                        ..t
                    }
                } else {
                    t
                }
            }));
            wrapped.extend(row_wrapped);
        }
        Self {
            taps: taps.into(),
            wrapped: wrapped.into(),
            erp_width: ew,
            erp_pixels: eh * ew,
        }
    }

    /// Bytes held by the map (in memory, or mapped from a plan file).
    #[must_use]
    pub fn memory_bytes(&self) -> usize {
        self.taps.len() * std::mem::size_of::<Tap>() + self.wrapped.len() * 16
    }

    /// Whether the map is read in place from a mapped plan file.
    #[must_use]
    pub fn is_mapped(&self) -> bool {
        self.taps.is_mapped()
    }

    /// (taps, wrapped corners): what a plan file stores (see [`crate::plan_cache`]).
    pub(crate) fn parts(&self) -> (&[Tap], &[[u32; 4]]) {
        (&self.taps, &self.wrapped)
    }

    /// The map of [`TangentTaps::parts`] for an ERP of `erp_height` × `erp_width`; the caller
    /// has checked every index against that size.
    pub(crate) fn from_parts(
        taps: PlanArray<Tap>,
        wrapped: PlanArray<[u32; 4]>,
        erp_height: usize,
        erp_width: usize,
    ) -> Self {
        Self {
            taps,
            wrapped,
            erp_width,
            erp_pixels: erp_height * erp_width,
        }
    }

    /// Sample an ERP image of `C` interleaved channels into `out` ((N·h·w·C), same order as taps).
    ///
    /// # Panics
    /// If `erp` is not the size the taps were built for (the bindings check shapes first).
    pub fn sample<T: Texel, const C: usize>(&self, erp: &[T], out: &mut [T], tangent_width: usize) {
        let ew = self.erp_width;
        assert_eq!(
            erp.len(),
            self.erp_pixels * C,
            "ERP size does not match the plan"
        );
        assert_eq!(
            out.len(),
            self.taps.len() * C,
            "output size does not match the plan"
        );
        let src = ErpSource {
            erp,
            width: ew,
            wrapped: &self.wrapped,
        };
        out.par_chunks_mut(tangent_width * C)
            .zip(self.taps.par_chunks(tangent_width))
            .for_each(|(row, taps)| T::sample_run::<C>(&src, taps, row));
    }
}

/// Sample an ERP image into the tangent images of `layout` through `taps`.
/// `erp` is (H, W, C) interleaved; `out` is (N, h, w, C) and is overwritten.
pub fn erp_to_tangents<T: Texel>(
    taps: &TangentTaps,
    layout: &Layout,
    erp: &[T],
    channels: usize,
    out: &mut [T],
) {
    let (_, w) = layout.tangent_shape();
    match channels {
        1 => taps.sample::<T, 1>(erp, out, w),
        2 => taps.sample::<T, 2>(erp, out, w),
        3 => taps.sample::<T, 3>(erp, out, w),
        4 => taps.sample::<T, 4>(erp, out, w),
        _ => unreachable!("channels are validated to be 1..=4"),
    }
}

/// The ERP image being sampled, with what its taps need to find their four neighbours.
pub struct ErpSource<'a, T> {
    /// (H, W, C) interleaved pixels; its size was checked against the taps.
    pub(super) erp: &'a [T],
    pub(super) width: usize,
    /// Corner indices of the wrapped taps.
    pub(super) wrapped: &'a [[u32; 4]],
}

impl<T: Copy> ErpSource<'_, T> {
    /// The four neighbours (top-left, top-right, bottom-left, bottom-right) of channel `ch`.
    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    pub(super) fn corners<const C: usize>(&self, tap: Tap, ch: usize) -> [T; 4] {
        let corners = if tap.index & WRAPPED == 0 {
            let (i, w) = (tap.index as usize, self.width);
            [i, i + 1, i + w, i + w + 1]
        } else {
            self.wrapped[(tap.index & !WRAPPED) as usize].map(|i| i as usize)
        };
        // SAFETY: every corner index is < erp_pixels by construction of the taps (plain taps
        // have i0 + 1 < H and j0 + 1 < W; wrapped ones are reduced modulo the grid), ch < C, and
        // erp.len() == erp_pixels·C was asserted by the caller.
        corners.map(|k| unsafe { *self.erp.get_unchecked(k * C + ch) })
    }
}

/// [`Texel::sample_run`] one channel at a time, for any pixel type.
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
#[inline(always)]
pub(super) fn sample_run_scalar<T: Texel, const C: usize>(
    src: &ErpSource<'_, T>,
    taps: &[Tap],
    out: &mut [T],
) {
    for (n, (px, &tap)) in out.chunks_exact_mut(C).zip(taps).enumerate() {
        if let Some(ahead) = taps.get(n + PREFETCH_DISTANCE) {
            prefetch_tap::<T, C>(src, *ahead);
        }
        for (ch, o) in px.iter_mut().enumerate() {
            *o = T::bilinear(src.corners::<C>(tap, ch), tap);
        }
    }
}

/// Prefetch the two ERP rows a plain tap reads.
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
#[inline(always)]
pub(super) fn prefetch_tap<T, const C: usize>(src: &ErpSource<'_, T>, tap: Tap) {
    if tap.index & WRAPPED == 0 {
        let i = tap.index as usize * C;
        prefetch(src.erp, i);
        prefetch(src.erp, i + src.width * C);
    }
}

/// For each camera, the first camera with the same intrinsics that it equals up to a turn about
/// the world's vertical axis, and that turn as a shift in ERP columns; (itself, 0) if none.
fn vertical_symmetry(layout: &Layout) -> Vec<(usize, f64)> {
    let cams = &layout.cameras;
    let columns_per_radian = layout.erp_width as f64 / std::f64::consts::TAU;
    let mut bases: Vec<(usize, f64)> = Vec::with_capacity(cams.len());
    for (k, cam) in cams.iter().enumerate() {
        let found = (0..k)
            .filter(|&j| bases[j].0 == j)
            .find_map(|j| turn_about_vertical(&cams[j], cam).map(|turn| (j, turn)));
        bases.push(found.map_or((k, 0.0), |(j, turn)| (j, turn * columns_per_radian)));
    }
    bases
}

/// The angle α such that `b` is `a` turned by α about the world y axis (same intrinsics).
fn turn_about_vertical(a: &TangentCamera, b: &TangentCamera) -> Option<f64> {
    // Equal up to rounding: each face's intrinsics come from its own bounding box.
    let close = |p: f64, q: f64| (p - q).abs() <= 1e-9 * p.abs().max(1.0);
    if !(close(a.fx, b.fx) && close(a.fy, b.fy) && close(a.cx, b.cx) && close(a.cy, b.cy)) {
        return None;
    }
    // b sees Q·d where a sees d when R_b Q = R_a, i.e. Q = R_bᵀ R_a.
    let q = b.rotation.transpose() * a.rotation;
    let tol = 1e-12;
    let about_y = (q[(1, 1)] - 1.0).abs() < tol
        && [q[(0, 1)], q[(1, 0)], q[(1, 2)], q[(2, 1)]]
            .iter()
            .all(|v| v.abs() < tol);
    about_y.then(|| q[(0, 2)].atan2(q[(0, 0)]))
}

/// Flat index of ERP pixel (i, j) where i may be −1 or H and j any integer: longitude wraps, and
/// a row beyond a pole is the pole row on the opposite meridian.
fn erp_index_wrapped(i: i64, j: i64, height: usize, width: usize) -> u32 {
    let (h, w) = (height as i64, width as i64);
    let (i, j) = if i < 0 {
        (-1 - i, j + w / 2)
    } else if i >= h {
        (2 * h - 1 - i, j + w / 2)
    } else {
        (i, j)
    };
    (i * w + j.rem_euclid(w)) as u32
}

#[cfg(test)]
mod tests {
    use super::*;
    #[cfg(target_arch = "x86_64")]
    use crate::resample::simd;

    #[test]
    fn icosahedron_bands_share_positions() {
        // Five faces per band differ by 72° turns: 4 cameras compute positions, 16 reuse them.
        let layout = Layout::icosahedron(512, 0.3, None).expect("layout");
        let bases = vertical_symmetry(&layout);
        let roots: Vec<usize> = (0..20).filter(|&k| bases[k].0 == k).collect();
        assert_eq!(roots, vec![0, 5, 10, 15]);
        for (k, &(base, shift)) in bases.iter().enumerate() {
            // The turn is (k − base)·72°, i.e. (k − base)·W/5 columns, modulo W.
            let expected = (k - base) as f64 * 512.0 / 5.0;
            let diff = (shift - expected).rem_euclid(512.0);
            assert!(diff.min(512.0 - diff) < 1e-9, "camera {k}: shift {shift}");
        }
    }

    #[test]
    fn wrapped_index_crosses_the_pole_and_the_seam() {
        let (h, w) = (4, 8);
        assert_eq!(erp_index_wrapped(-1, 1, h, w), 5); // above row 0, col 1 → row 0, col 5
        assert_eq!(erp_index_wrapped(4, 6, h, w), 3 * 8 + 2); // below the last row
        assert_eq!(erp_index_wrapped(2, 8, h, w), 2 * 8); // past the last column
        assert_eq!(erp_index_wrapped(2, -1, h, w), 2 * 8 + 7);
    }

    /// Every u8 path against the scalar one on full-range noise, on runs of even and odd length.
    fn simd_paths_match_scalar<const C: usize>() {
        let layout = Layout::icosahedron(256, 0.3, None).expect("layout");
        let taps = TangentTaps::build(&layout);
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let erp: Vec<u8> = (0..128 * 256 * C)
            .map(|_| {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                (state >> 56) as u8
            })
            .collect();
        let src = ErpSource {
            erp: &erp,
            width: 256,
            wrapped: &taps.wrapped,
        };
        let mut want = vec![0u8; taps.taps.len() * C];
        sample_run_scalar::<u8, C>(&src, &taps.taps, &mut want);
        let w = layout.tangent_shape().1;
        let mut got = vec![0u8; want.len()];
        #[cfg(target_arch = "x86_64")]
        for path in ["ssse3", "avx2"] {
            let supported = match path {
                "ssse3" => std::arch::is_x86_feature_detected!("ssse3"),
                _ => std::arch::is_x86_feature_detected!("avx2"),
            };
            if !supported {
                continue;
            }
            got.fill(0);
            for (run, (out, taps)) in got.chunks_mut(w * C).zip(taps.taps.chunks(w)).enumerate() {
                // Odd rows: a run of odd length, then a single pixel.
                let split = if run % 2 == 1 { w - 1 } else { w };
                let (out0, out1) = out.split_at_mut(split * C);
                let (taps0, taps1) = taps.split_at(split);
                for (out, taps) in [(out0, taps0), (out1, taps1)] {
                    // SAFETY: the CPU supports the path's instructions (checked above).
                    unsafe {
                        match path {
                            "ssse3" => simd::sample_run_u8::<C>(&src, taps, out),
                            _ => simd::sample_run_u8_avx2::<C>(&src, taps, out),
                        }
                    }
                }
            }
            // Both round the same value: 2⁻¹⁵ weights vs 1/128-level steps differ by < 0.05.
            let worst = want.iter().zip(&got).map(|(a, b)| a.abs_diff(*b)).max();
            assert!(worst <= Some(1), "{path}, {C} channels: {worst:?}");
            let exact = want.iter().zip(&got).filter(|(a, b)| a == b).count();
            assert!(
                exact * 100 > want.len() * 95,
                "{path}, {C} channels: {exact}"
            );
        }
    }

    #[test]
    fn simd_paths_match_the_scalar_path() {
        simd_paths_match_scalar::<1>();
        simd_paths_match_scalar::<2>();
        simd_paths_match_scalar::<3>();
        simd_paths_match_scalar::<4>();
    }
}
