//! Bilinear resampling between the ERP image and the tangent images, both ways.
//!
//! Both directions use precomputed taps (see [`crate::plan::Plan`]): the position of every output
//! pixel in the source image, stored as the index of its top-left source pixel and two fixed-point
//! fractions (8 bytes a pixel). Nothing is rounded to whole pixels (reference bug B8).

use crate::camera::TangentCamera;
use crate::layout::Layout;
use crate::sphere::{direction_to_pixel, ErpGrid};
use rayon::prelude::*;

/// Fixed-point scale of bilinear fractions: 2⁻¹⁵ pixel resolution.
const FRAC_SCALE: f32 = 32768.0;
/// Flag on [`Tap::index`] of a tangent tap whose four ERP neighbours are not in the plain
/// 2×2 arrangement (longitude wrap or across a pole); the rest of the index points into
/// [`TangentTaps::wrapped`].
const WRAPPED: u32 = 1 << 31;

/// A bilinear sampling position: top-left source index and fractions in units of 2⁻¹⁵.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Tap {
    /// Flat index of the top-left source pixel (meaning depends on the map).
    pub index: u32,
    fx: u16,
    fy: u16,
}

impl Tap {
    fn new(index: u32, fx: f64, fy: f64) -> Self {
        debug_assert!((0.0..=1.0).contains(&fx) && (0.0..=1.0).contains(&fy));
        // `as` truncates; for f ≥ 0 this rounds without a libm call (no SSE4.1 in baseline x86-64).
        let q = |f: f64| (f * FRAC_SCALE as f64 + 0.5) as u16;
        Self {
            index,
            fx: q(fx),
            fy: q(fy),
        }
    }

    /// Weights of the top-left, top-right, bottom-left and bottom-right neighbours.
    #[inline(always)]
    fn weights(self) -> [f32; 4] {
        let fx = self.fx as f32 * (1.0 / FRAC_SCALE);
        let fy = self.fy as f32 * (1.0 / FRAC_SCALE);
        let (gx, gy) = (1.0 - fx, 1.0 - fy);
        [gx * gy, fx * gy, gx * fy, fx * fy]
    }
}

/// A pixel type that can be resampled.
pub trait Texel: Copy + Send + Sync + 'static {
    /// Bilinear combination of the top-left, top-right, bottom-left and bottom-right values at
    /// the fractions of `tap`.
    fn bilinear(p: [Self; 4], tap: Tap) -> Self;

    /// Sample one run of tangent pixels (`out` holds `taps.len()` pixels of `C` channels).
    #[inline]
    fn sample_run<const C: usize>(src: &ErpSource<'_, Self>, taps: &[Tap], out: &mut [Self]) {
        sample_run_scalar::<Self, C>(src, taps, out);
    }
}

impl Texel for u8 {
    /// Fixed-point arithmetic: the four weights are integers summing exactly to 2¹⁵.
    #[inline(always)]
    fn bilinear(p: [Self; 4], tap: Tap) -> Self {
        const ONE: u32 = FRAC_SCALE as u32;
        let (fx, fy) = (tap.fx as u32, tap.fy as u32);
        let w11 = (fx * fy) >> 15;
        let (w01, w10) = (fx - w11, fy - w11);
        // w11 ≥ fx + fy − ONE, so adding first never underflows.
        let w00 = ONE + w11 - fx - fy;
        let v = w00 * p[0] as u32 + w01 * p[1] as u32 + w10 * p[2] as u32 + w11 * p[3] as u32;
        ((v + ONE / 2) >> 15) as u8
    }

    #[inline]
    fn sample_run<const C: usize>(src: &ErpSource<'_, Self>, taps: &[Tap], out: &mut [Self]) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { simd::sample_run_u8_avx2::<C>(src, taps, out) };
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("ssse3") {
            // SAFETY: the CPU supports SSSE3 (checked just above).
            unsafe { simd::sample_run_u8::<C>(src, taps, out) };
            return;
        }
        sample_run_scalar::<u8, C>(src, taps, out);
    }
}

impl Texel for f32 {
    #[inline(always)]
    fn bilinear(p: [Self; 4], tap: Tap) -> Self {
        let w = tap.weights();
        w[0] * p[0] + w[1] * p[1] + w[2] * p[2] + w[3] * p[3]
    }
}

/// ERP → tangent map: one tap into the ERP image per tangent pixel, in (face, row, column) order.
#[derive(Debug, Clone)]
pub struct TangentTaps {
    taps: Vec<Tap>,
    /// ERP pixel indices (top-left, top-right, bottom-left, bottom-right) of wrapped taps.
    wrapped: Vec<[u32; 4]>,
    erp_width: usize,
    erp_pixels: usize,
}

impl TangentTaps {
    /// Taps for every pixel of every camera of `layout`.
    ///
    /// ERP positions cost two `atan2` per pixel, so they are computed once per set of cameras
    /// that differ only by a turn about the vertical axis (the five faces of each icosahedron
    /// band): such a camera sees the same positions shifted in longitude.
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
            taps,
            wrapped,
            erp_width: ew,
            erp_pixels: eh * ew,
        }
    }

    /// Bytes held by the map.
    pub fn memory_bytes(&self) -> usize {
        self.taps.len() * std::mem::size_of::<Tap>() + self.wrapped.len() * 16
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

/// The ERP image being sampled, with what its taps need to find their four neighbours.
pub struct ErpSource<'a, T> {
    /// (H, W, C) interleaved pixels; its size was checked against the taps.
    erp: &'a [T],
    width: usize,
    /// Corner indices of the wrapped taps.
    wrapped: &'a [[u32; 4]],
}

impl<T: Copy> ErpSource<'_, T> {
    /// The four neighbours (top-left, top-right, bottom-left, bottom-right) of channel `ch`.
    #[inline(always)]
    fn corners<const C: usize>(&self, tap: Tap, ch: usize) -> [T; 4] {
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
#[inline(always)]
fn sample_run_scalar<T: Texel, const C: usize>(
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
#[inline(always)]
fn prefetch_tap<T, const C: usize>(src: &ErpSource<'_, T>, tap: Tap) {
    if tap.index & WRAPPED == 0 {
        let i = tap.index as usize * C;
        prefetch(src.erp, i);
        prefetch(src.erp, i + src.width * C);
    }
}

/// Fixed-point u8 bilinear sampling with x86 SIMD: one pixel's four neighbours in 128 bits
/// (SSSE3), two pixels in 256 bits (AVX2).
///
/// Each value is interpolated in 1/128 steps of a grey level with the taps' 2⁻¹⁵ fractions
/// (pmulhrsw), first along rows, then down: within 1/128 of the exact bilinear value before the
/// final rounding.
#[cfg(target_arch = "x86_64")]
mod simd {
    use super::{prefetch_tap, ErpSource, Tap, Texel, PREFETCH_DISTANCE, WRAPPED};
    use std::arch::x86_64::*;

    /// What every pixel of a run needs.
    struct Kernel {
        /// Plain taps below this index have 8 readable bytes at both rows; wrapped taps (flag
        /// in bit 31) and the last few pixels of the image take the scalar path.
        fast_limit: usize,
        /// Byte offset of the bottom row from the top row.
        row: usize,
        /// Shuffles of the 16 bytes [8 from the top row | 8 from the bottom row] read at a tap:
        /// the left pixels as u16 lanes (top channels, then bottom channels), the right ones,
        /// and the lanes of the bottom row moved down onto the top's.
        left: __m128i,
        right: __m128i,
        down: __m128i,
    }

    impl Kernel {
        #[target_feature(enable = "ssse3")]
        fn new<const C: usize>(src: &ErpSource<'_, u8>) -> Self {
            let (len, row) = (src.erp.len(), src.width * C);
            let fast_limit = if len >= row + 8 {
                ((len - row - 8) / C + 1).min(WRAPPED as usize)
            } else {
                0
            };
            const ZERO: i8 = -128; // pshufb writes 0 for a set high bit
            let mut m = [[ZERO; 16]; 3];
            for k in 0..2 * C {
                let (bottom, ch) = (k / C, k % C);
                m[0][2 * k] = (8 * bottom + ch) as i8;
                m[1][2 * k] = (8 * bottom + C + ch) as i8;
            }
            for k in 0..C {
                m[2][2 * k] = (2 * (C + k)) as i8;
                m[2][2 * k + 1] = (2 * (C + k) + 1) as i8;
            }
            // SAFETY: 16-byte unaligned loads of 16-byte arrays.
            let [left, right, down] = m.map(|v| unsafe { _mm_loadu_si128(v.as_ptr().cast()) });
            Self {
                fast_limit,
                row,
                left,
                right,
                down,
            }
        }

        /// The 8 bytes at the tap's top-left pixel, then the 8 below.
        ///
        /// # Safety
        /// `i < self.fast_limit` and `erp` is the image the kernel was made for.
        #[target_feature(enable = "ssse3")]
        #[inline]
        unsafe fn rows<const C: usize>(&self, erp: &[u8], i: usize) -> __m128i {
            // SAFETY: i < fast_limit, so i·C + row + 8 ≤ erp.len(): both reads are in bounds.
            unsafe {
                let top = _mm_loadl_epi64(erp.as_ptr().add(i * C).cast());
                let bottom = _mm_loadl_epi64(erp.as_ptr().add(i * C + self.row).cast());
                _mm_unpacklo_epi64(top, bottom)
            }
        }

        /// One pixel of `C` channels, by SSSE3 or (wrapped and last taps) by the scalar path.
        #[target_feature(enable = "ssse3")]
        #[inline]
        fn pixel<const C: usize>(&self, src: &ErpSource<'_, u8>, tap: Tap, px: &mut [u8]) {
            if tap.index as usize >= self.fast_limit {
                for (ch, o) in px.iter_mut().enumerate() {
                    *o = u8::bilinear(src.corners::<C>(tap, ch), tap);
                }
                return;
            }
            // SAFETY: the index is below fast_limit (checked above).
            let both = unsafe { self.rows::<C>(src.erp, tap.index as usize) };
            let a = _mm_shuffle_epi8(both, self.left);
            let b = _mm_shuffle_epi8(both, self.right);
            // Values in 1/128 grey levels: a·128 + (b − a)·128·f, |(b − a)·128| < 2¹⁵.
            let step = _mm_slli_epi16::<7>(_mm_sub_epi16(b, a));
            let across = _mm_add_epi16(_mm_slli_epi16::<7>(a), _mm_mulhrs_epi16(step, q15(tap.fx)));
            let step = _mm_sub_epi16(_mm_shuffle_epi8(across, self.down), across);
            let value = _mm_add_epi16(across, _mm_mulhrs_epi16(step, q15(tap.fy)));
            let value = _mm_srli_epi16::<7>(_mm_add_epi16(value, _mm_set1_epi16(64)));
            let bytes = (_mm_cvtsi128_si32(_mm_packus_epi16(value, value)) as u32).to_le_bytes();
            px.copy_from_slice(&bytes[..C]);
        }
    }

    /// A fraction broadcast as a Q15 factor: pmulhrsw takes factors below 1.0, so a fraction of
    /// exactly 1 loses 2⁻¹⁵.
    #[target_feature(enable = "ssse3")]
    #[inline]
    fn q15(f: u16) -> __m128i {
        _mm_set1_epi16(f.min(i16::MAX as u16) as i16)
    }

    /// [`Texel::sample_run`] for u8, one pixel at a time.
    ///
    /// # Safety
    /// The CPU must support SSSE3.
    #[target_feature(enable = "ssse3")]
    pub(super) unsafe fn sample_run_u8<const C: usize>(
        src: &ErpSource<'_, u8>,
        taps: &[Tap],
        out: &mut [u8],
    ) {
        let kernel = Kernel::new::<C>(src);
        for (n, (px, &tap)) in out.chunks_exact_mut(C).zip(taps).enumerate() {
            if let Some(ahead) = taps.get(n + PREFETCH_DISTANCE) {
                prefetch_tap::<u8, C>(src, *ahead);
            }
            kernel.pixel::<C>(src, tap, px);
        }
    }

    /// [`Texel::sample_run`] for u8, two pixels at a time (one per 128-bit lane).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn sample_run_u8_avx2<const C: usize>(
        src: &ErpSource<'_, u8>,
        taps: &[Tap],
        out: &mut [u8],
    ) {
        let k = Kernel::new::<C>(src);
        let (left, right, down) = (
            _mm256_broadcastsi128_si256(k.left),
            _mm256_broadcastsi128_si256(k.right),
            _mm256_broadcastsi128_si256(k.down),
        );
        let half = _mm256_set1_epi16(64);
        let mut pairs = out.chunks_exact_mut(2 * C).zip(taps.chunks_exact(2));
        for (n, (px, pair)) in pairs.by_ref().enumerate() {
            for ahead in taps.iter().skip(2 * n + PREFETCH_DISTANCE).take(2) {
                prefetch_tap::<u8, C>(src, *ahead);
            }
            let (t0, t1) = (pair[0], pair[1]);
            if t0.index as usize >= k.fast_limit || t1.index as usize >= k.fast_limit {
                let (p0, p1) = px.split_at_mut(C);
                k.pixel::<C>(src, t0, p0);
                k.pixel::<C>(src, t1, p1);
                continue;
            }
            // SAFETY: both indices are below fast_limit (checked above).
            let both = unsafe {
                _mm256_set_m128i(
                    k.rows::<C>(src.erp, t1.index as usize),
                    k.rows::<C>(src.erp, t0.index as usize),
                )
            };
            let fx = _mm256_set_m128i(q15(t1.fx), q15(t0.fx));
            let fy = _mm256_set_m128i(q15(t1.fy), q15(t0.fy));
            let a = _mm256_shuffle_epi8(both, left);
            let b = _mm256_shuffle_epi8(both, right);
            let step = _mm256_slli_epi16::<7>(_mm256_sub_epi16(b, a));
            let across = _mm256_add_epi16(_mm256_slli_epi16::<7>(a), _mm256_mulhrs_epi16(step, fx));
            let step = _mm256_sub_epi16(_mm256_shuffle_epi8(across, down), across);
            let value = _mm256_add_epi16(across, _mm256_mulhrs_epi16(step, fy));
            let value = _mm256_srli_epi16::<7>(_mm256_add_epi16(value, half));
            let packed = _mm256_packus_epi16(value, value);
            let first = (_mm256_extract_epi32::<0>(packed) as u32).to_le_bytes();
            let second = (_mm256_extract_epi32::<4>(packed) as u32).to_le_bytes();
            px[..C].copy_from_slice(&first[..C]);
            px[C..].copy_from_slice(&second[..C]);
        }
        if taps.len() % 2 == 1 {
            let n = taps.len() - 1;
            k.pixel::<C>(src, taps[n], &mut out[n * C..(n + 1) * C]);
        }
    }
}

/// Most tangents one ERP pixel can be seen by (the icosahedron layout needs 5).
const MAX_FACES_PER_PIXEL: usize = 16;

/// How many pixels ahead the ERP rows of a tap are prefetched: the taps say exactly which cache
/// lines the next pixels need, which the hardware prefetcher cannot guess along a curved path.
const PREFETCH_DISTANCE: usize = 32;

/// Hint the CPU to load the cache line holding `data[index]` (no-op where unsupported).
#[inline(always)]
fn prefetch<T>(data: &[T], index: usize) {
    #[cfg(target_arch = "x86_64")]
    if index < data.len() {
        // SAFETY: the pointer is in bounds (checked), and prefetching never faults or writes.
        unsafe {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            _mm_prefetch::<_MM_HINT_T0>(data.as_ptr().add(index).cast());
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (data, index);
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

/// Tangents → ERP map: for every ERP pixel, the tangent images that see it and where.
///
/// Stored per ERP pixel (a compressed-row layout), so blending runs over ERP rows in parallel
/// without write conflicts and per-face data is never expanded to ERP size. Each pixel's taps are
/// ordered by angular distance from the camera axis, nearest first: the first valid tap is the
/// nearest face (for the icosahedron, the face whose triangle contains the pixel).
#[derive(Debug, Clone)]
pub struct ErpTaps {
    /// Number of taps of each ERP pixel.
    counts: Vec<u8>,
    /// Per ERP row, its pixels' taps into the flat tangent stack (face·h·w + y·w + x of the
    /// top-left neighbour). Kept as built, row by row: gathering them into one array would
    /// cost a second copy of the largest structure of the plan.
    rows: Vec<Vec<Tap>>,
    tangent_width: usize,
    tangent_pixels: usize,
    faces: usize,
    erp_width: usize,
}

impl ErpTaps {
    /// Taps for every ERP pixel of `layout`.
    pub fn build(layout: &Layout) -> Self {
        let (h, w) = layout.tangent_shape();
        let (eh, ew) = (layout.erp_height, layout.erp_width);
        let grid = ErpGrid::new(eh, ew);
        // A direction outside a camera's bounding cone cannot land on its image: per row, the
        // latitude gap to the axis rejects about half the cameras, and per pixel one dot product
        // rejects most of the rest before any projection.
        let cones: Vec<(nalgebra::Vector3<f64>, f64, f64, f64)> = layout
            .cameras
            .iter()
            .map(|cam| {
                let (axis, min_cos) = (cam.axis(), cone_cosine(cam));
                (axis, min_cos, (-axis.y).asin(), min_cos.acos())
            })
            .collect();
        let rows: Vec<(Vec<u8>, Vec<Tap>)> = (0..eh)
            .into_par_iter()
            .map(|i| {
                let lat = crate::sphere::row_latitude(i as f64, eh);
                let candidates: Vec<usize> = (0..cones.len())
                    .filter(|&k| (lat - cones[k].2).abs() <= cones[k].3 + 1e-9)
                    .collect();
                let mut counts = Vec::with_capacity(ew);
                // Four faces see a pixel on average; the row vector is sized once.
                let mut taps = Vec::with_capacity(ew * 4);
                let mut seen = [(0.0f64, Tap::default()); MAX_FACES_PER_PIXEL];
                for j in 0..ew {
                    let d = grid.direction(i, j);
                    let mut n = 0;
                    for &k in &candidates {
                        let (axis, min_cos, _, _) = &cones[k];
                        let cos = axis.dot(&d);
                        if cos < *min_cos || n == MAX_FACES_PER_PIXEL {
                            continue;
                        }
                        if let Some(tap) = tangent_tap(&layout.cameras[k], &d, k * h * w) {
                            // Insertion keeps the pixel's taps nearest-axis first.
                            let mut at = n;
                            while at > 0 && seen[at - 1].0 < cos {
                                seen[at] = seen[at - 1];
                                at -= 1;
                            }
                            seen[at] = (cos, tap);
                            n += 1;
                        }
                    }
                    taps.extend(seen[..n].iter().map(|s| s.1));
                    counts.push(n as u8);
                }
                (counts, taps)
            })
            .collect();
        let mut counts = Vec::with_capacity(eh * ew);
        let mut taps = Vec::with_capacity(eh);
        for (row_counts, row_taps) in rows {
            counts.extend(row_counts);
            taps.push(row_taps);
        }
        Self {
            counts,
            rows: taps,
            tangent_width: w,
            tangent_pixels: h * w,
            faces: layout.cameras.len(),
            erp_width: ew,
        }
    }

    /// Bytes held by the map.
    pub fn memory_bytes(&self) -> usize {
        self.len() * std::mem::size_of::<Tap>() + self.counts.len() + self.rows.len() * 24
    }

    /// Total number of (ERP pixel, tangent) pairs.
    pub fn len(&self) -> usize {
        self.rows.iter().map(Vec::len).sum()
    }

    /// Whether no ERP pixel is seen by any tangent.
    pub fn is_empty(&self) -> bool {
        self.rows.iter().all(Vec::is_empty)
    }

    /// Number of tangents that see each ERP pixel (H·W, row-major).
    pub fn counts(&self) -> &[u8] {
        &self.counts
    }

    /// The (face, bilinear value) samples of every pixel of ERP row `i`, in pixel order: calls
    /// `visit(j, samples)` with the samples of pixel (i, j), nearest face first. A sample is NaN
    /// when any of its four tangent neighbours is NaN.
    ///
    /// # Panics
    /// If `tangents` is not the size the taps were built for (the bindings check shapes first).
    #[inline]
    pub fn visit_row(&self, tangents: &[f32], i: usize, visit: impl FnMut(usize, &[(usize, f32)])) {
        self.assert_stack(tangents, "tangent");
        // SAFETY: `tangents` has the size the taps were built for (asserted above).
        let sample = |tap: Tap| {
            (tap.index as usize / self.tangent_pixels, unsafe {
                self.lerp(tangents, tap)
            })
        };
        self.walk_row(tangents, i, sample, visit);
    }

    /// Like [`ErpTaps::visit_row`], but each sample also carries the bilinear value of a second
    /// per-tangent map (`weights`, same layout as `tangents`) at the same position: the blending
    /// weight of that face there. Calls `visit(j, samples)` nearest face first.
    ///
    /// # Panics
    /// If `tangents` or `weights` is not the size the taps were built for.
    #[inline]
    pub fn visit_row_weighted(
        &self,
        tangents: &[f32],
        weights: &[f32],
        i: usize,
        visit: impl FnMut(usize, &[WeightedSample]),
    ) {
        self.assert_stack(tangents, "tangent");
        self.assert_stack(weights, "weight");
        let sample = |tap: Tap| WeightedSample {
            face: (tap.index as usize / self.tangent_pixels) as u32,
            // SAFETY: both stacks have the size the taps were built for (asserted above).
            value: unsafe { self.lerp(tangents, tap) },
            weight: unsafe { self.lerp(weights, tap) },
        };
        self.walk_row(tangents, i, sample, visit);
    }

    fn assert_stack(&self, stack: &[f32], what: &str) {
        assert_eq!(
            stack.len(),
            self.tangent_pixels * self.faces,
            "{what} stack size mismatch"
        );
    }

    /// Bilinear value of a tangent stack at `tap`.
    ///
    /// # Safety
    /// `stack` must be faces·h·w long: taps point at a top-left neighbour with x0 ≤ w − 2 and
    /// y0 ≤ h − 2 of a face < faces, so all four neighbours are then in bounds.
    #[inline(always)]
    unsafe fn lerp(&self, stack: &[f32], tap: Tap) -> f32 {
        let (k, w, wts) = (tap.index as usize, self.tangent_width, tap.weights());
        debug_assert!(k + w + 1 < stack.len());
        // SAFETY: see the function's contract.
        unsafe {
            wts[0] * stack.get_unchecked(k)
                + wts[1] * stack.get_unchecked(k + 1)
                + wts[2] * stack.get_unchecked(k + w)
                + wts[3] * stack.get_unchecked(k + w + 1)
        }
    }

    /// Walk ERP row `i`: for each pixel, `sample` each of its taps (nearest face first) and
    /// `visit(j, samples)`; the tangent rows of taps further along are prefetched from `ahead_in`.
    #[inline(always)]
    fn walk_row<S>(
        &self,
        ahead_in: &[f32],
        i: usize,
        mut sample: impl FnMut(Tap) -> S,
        mut visit: impl FnMut(usize, &[S]),
    ) {
        let w = self.tangent_width;
        let row = &self.rows[i];
        let counts = &self.counts[i * self.erp_width..(i + 1) * self.erp_width];
        let mut at = 0;
        let mut samples: Vec<S> = Vec::with_capacity(MAX_FACES_PER_PIXEL);
        for (j, &n) in counts.iter().enumerate() {
            let n = n as usize;
            samples.clear();
            for (t, &tap) in row[at..at + n].iter().enumerate() {
                if let Some(ahead) = row.get(at + t + PREFETCH_DISTANCE) {
                    let k = ahead.index as usize;
                    prefetch(ahead_in, k);
                    prefetch(ahead_in, k + w);
                }
                samples.push(sample(tap));
            }
            at += n;
            visit(j, &samples);
        }
    }
}

/// One tangent's bilinear value at an ERP pixel, with that tangent's blending weight there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WeightedSample {
    /// Index of the tangent (camera) in the layout.
    pub face: u32,
    /// Bilinear value; NaN when any of the four neighbours is NaN.
    pub value: f32,
    /// Bilinear weight of the face at the same position.
    pub weight: f32,
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

/// Tap of the tangent pixel grid of `cam` (flat offset `base`) seen by direction `d`, if any.
/// Positions within half a pixel of the border are clamped onto the outermost pixel centres.
fn tangent_tap(cam: &TangentCamera, d: &nalgebra::Vector3<f64>, base: usize) -> Option<Tap> {
    let (x, y) = cam.project(d)?;
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

/// Each tangent image mapped onto the ERP grid: `out` (N, H, W) is overwritten, NaN where a face
/// does not see the pixel (or a bilinear neighbour is NaN).
///
/// # Panics
/// If `out` is not N·H·W long.
pub fn tangents_to_erp(taps: &ErpTaps, layout: &Layout, tangents: &[f32], out: &mut [f32]) {
    let (eh, ew) = (layout.erp_height, layout.erp_width);
    let plane = eh * ew;
    assert_eq!(
        out.len(),
        layout.cameras.len() * plane,
        "output size does not match the plan"
    );
    out.par_chunks_mut(1 << 16)
        .for_each(|chunk| chunk.fill(f32::NAN));
    let ptr = SharedMut(out.as_mut_ptr());
    (0..eh).into_par_iter().for_each(|i| {
        let ptr = &ptr;
        taps.visit_row(tangents, i, |j, samples| {
            for &(face, v) in samples {
                // SAFETY: face < N, i < H and j < W, so the index is in bounds (length asserted
                // above); each (face, i, j) element is written by exactly one iteration (rows are
                // disjoint across threads, a face appears once per pixel).
                unsafe { *ptr.0.add(face * plane + i * ew + j) = v };
            }
        });
    });
}

/// A raw pointer that may be shared between threads for provably disjoint writes.
struct SharedMut<T>(*mut T);
// SAFETY: only used for writes to disjoint elements, see the call sites.
unsafe impl<T> Sync for SharedMut<T> {}

#[cfg(test)]
mod tests {
    use super::*;

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
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
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

    #[test]
    fn fixed_point_weights_sum_to_one() {
        for (fx, fy) in [(0.0, 0.0), (1.0, 1.0), (0.3, 0.9), (0.999, 0.001)] {
            let tap = Tap::new(0, fx, fy);
            let w = tap.weights();
            assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
            assert_eq!(u8::bilinear([200, 200, 200, 200], tap), 200);
        }
    }
}
