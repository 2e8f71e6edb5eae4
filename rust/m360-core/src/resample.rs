//! Bilinear resampling between the ERP image and the tangent images, both ways.
//!
//! Both directions use precomputed taps (see [`crate::plan::Plan`]): the position of every output
//! pixel in the source image, stored as the index of its top-left source pixel and two fixed-point
//! fractions (8 bytes a pixel). Nothing is rounded to whole pixels (reference pitfall B8,
//! docs/reference-pitfalls.md).

use crate::camera::TangentCamera;
use crate::layout::Layout;
use crate::plan_array::PlanArray;
use crate::sphere::{direction_to_pixel, ErpGrid};
use rayon::prelude::*;

/// Fixed-point scale of bilinear fractions: 2⁻¹⁵ pixel resolution.
const FRAC_SCALE: f32 = 32768.0;
/// Flag on [`Tap::index`] of a tangent tap whose four ERP neighbours are not in the plain
/// 2×2 arrangement (longitude wrap or across a pole); the rest of the index points into
/// [`TangentTaps::wrapped`].
pub(crate) const WRAPPED: u32 = 1 << 31;

/// A bilinear sampling position: top-left source index and fractions in units of 2⁻¹⁵.
///
/// `repr(C)`: the SIMD kernels load taps as pairs of 32-bit lanes (index, fx | fy << 16).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[repr(C)]
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
        let q = |f: f64| (f * f64::from(FRAC_SCALE) + 0.5) as u16;
        Self {
            index,
            fx: q(fx),
            fy: q(fy),
        }
    }

    /// Whether both fractions are at most one pixel (true of every tap built; a plan file's
    /// taps are checked).
    #[inline]
    pub(crate) fn fractions_in_range(self) -> bool {
        let one = FRAC_SCALE as u16;
        self.fx <= one && self.fy <= one
    }

    /// Weights of the top-left, top-right, bottom-left and bottom-right neighbours.
    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    fn weights(self) -> [f32; 4] {
        let fx = f32::from(self.fx) * (1.0 / FRAC_SCALE);
        let fy = f32::from(self.fy) * (1.0 / FRAC_SCALE);
        let (gx, gy) = (1.0 - fx, 1.0 - fy);
        [gx * gy, fx * gy, gx * fy, fx * fy]
    }
}

// SAFETY: `repr(C)` of a u32 and two u16: no padding, and every bit pattern is a value (plan
// files store taps as these bytes; the loader checks the index and fractions before use).
unsafe impl bytemuck::Zeroable for Tap {}
// SAFETY: as above.
unsafe impl bytemuck::Pod for Tap {}

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
        let (fx, fy) = (u32::from(tap.fx), u32::from(tap.fy));
        let w11 = (fx * fy) >> 15;
        let (w01, w10) = (fx - w11, fy - w11);
        // w11 ≥ fx + fy − ONE, so adding first never underflows.
        let w00 = ONE + w11 - fx - fy;
        let v = w00 * u32::from(p[0])
            + w01 * u32::from(p[1])
            + w10 * u32::from(p[2])
            + w11 * u32::from(p[3]);
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
    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    fn bilinear(p: [Self; 4], tap: Tap) -> Self {
        let w = tap.weights();
        w[0] * p[0] + w[1] * p[1] + w[2] * p[2] + w[3] * p[3]
    }
}

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
    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
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
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
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
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
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
    use std::arch::x86_64::{
        __m128, __m128i, _mm256_add_epi16, _mm256_broadcastsi128_si256, _mm256_extract_epi32,
        _mm256_mulhrs_epi16, _mm256_packus_epi16, _mm256_set1_epi16, _mm256_set_m128i,
        _mm256_shuffle_epi8, _mm256_slli_epi16, _mm256_srli_epi16, _mm256_sub_epi16, _mm_add_epi16,
        _mm_add_ps, _mm_and_si128, _mm_castpd_ps, _mm_castps_si128, _mm_castsi128_ps,
        _mm_cvtepi32_ps, _mm_cvtsi128_si32, _mm_load_sd, _mm_loadl_epi64, _mm_loadu_si128,
        _mm_movehl_ps, _mm_movelh_ps, _mm_mul_ps, _mm_mulhrs_epi16, _mm_packus_epi16,
        _mm_set1_epi16, _mm_set1_epi32, _mm_set1_ps, _mm_shuffle_epi8, _mm_shuffle_ps,
        _mm_slli_epi16, _mm_srli_epi16, _mm_srli_epi32, _mm_storeu_ps, _mm_sub_epi16, _mm_sub_ps,
        _mm_unpacklo_epi64, _mm_unpacklo_ps,
    };

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
            #[expect(clippy::items_after_statements, reason = "used only by the mask below")]
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

    /// [`super::lerp_f32`] of ERP taps in each of `M` stacks of the same size (a map and
    /// its blending weights), four taps at a time with SSE2 (baseline x86-64): the same
    /// operations in the same order, so the same bits. Each tap's two rows are read as 64-bit
    /// pairs (top-left and top-right, bottom-left and bottom-right), and the fractions and
    /// offsets of four taps are decoded once for all stacks. Prefetches once per four taps.
    ///
    /// # Safety
    /// Every tap, its offset in the low [`super::RANK_SHIFT`] bits plus `base`, must satisfy
    /// `lerp_f32`'s contract for each stack; each `outs[m]` is as long as `taps`.
    #[target_feature(enable = "sse2")]
    pub(super) unsafe fn lerp_run_f32<const M: usize>(
        stacks: [&[f32]; M],
        base: usize,
        w: usize,
        taps: &[Tap],
        mut outs: [&mut [f32]; M],
    ) {
        debug_assert!(outs.iter().all(|o| o.len() == taps.len()));
        let scale = _mm_set1_ps(1.0 / super::FRAC_SCALE);
        let low16 = _mm_set1_epi32(0xffff);
        let offset = |tap: &Tap| base + (tap.index & super::OFFSET_MASK) as usize;
        let full = taps.len() / 4 * 4;
        for at in (0..full).step_by(4) {
            let quad = &taps[at..at + 4];
            if let Some(ahead) = taps.get(at + super::PREFETCH_DISTANCE) {
                for stack in stacks {
                    super::prefetch(stack, offset(ahead));
                    super::prefetch(stack, offset(ahead) + w);
                }
            }
            // SAFETY: four taps are 32 readable bytes; a Tap is (index, fx | fy << 16) (repr(C)).
            let (a, b) = unsafe {
                #[expect(clippy::cast_ptr_alignment, reason = "read with unaligned loads")]
                let p = quad.as_ptr().cast::<__m128i>();
                (_mm_loadu_si128(p), _mm_loadu_si128(p.add(1)))
            };
            let fracs = _mm_castps_si128(_mm_shuffle_ps::<0b11_01_11_01>(
                _mm_castsi128_ps(a),
                _mm_castsi128_ps(b),
            ));
            let fx = _mm_mul_ps(_mm_cvtepi32_ps(_mm_and_si128(fracs, low16)), scale);
            let fy = _mm_mul_ps(_mm_cvtepi32_ps(_mm_srli_epi32::<16>(fracs)), scale);
            let k = [
                offset(&quad[0]),
                offset(&quad[1]),
                offset(&quad[2]),
                offset(&quad[3]),
            ];
            // Rows of four (v0, v1, v2, v3) from four (left, right) pairs.
            let split = |p: [__m128; 4]| {
                let (lo, hi) = (_mm_unpacklo_ps(p[0], p[1]), _mm_unpacklo_ps(p[2], p[3]));
                (_mm_movelh_ps(lo, hi), _mm_movehl_ps(hi, lo))
            };
            let lerp =
                |p: __m128, q: __m128, f: __m128| _mm_add_ps(p, _mm_mul_ps(f, _mm_sub_ps(q, p)));
            for (stack, out) in stacks.iter().zip(outs.iter_mut()) {
                let src = stack.as_ptr();
                // SAFETY (both loads): `offset(tap) + w + 1 < stack.len()` (contract), so both
                // 8-byte pairs of a tap are inside `stack`.
                #[expect(
                    clippy::cast_ptr_alignment,
                    reason = "_mm_load_sd is an unaligned load"
                )]
                let pair =
                    |k: usize| unsafe { _mm_castpd_ps(_mm_load_sd(src.add(k).cast::<f64>())) };
                let (tl, tr) = split(k.map(pair));
                let (bl, br) = split(k.map(|k| pair(k + w)));
                let value = lerp(lerp(tl, tr, fx), lerp(bl, br, fx), fy);
                // SAFETY: `at + 4 ≤ out.len()`.
                unsafe { _mm_storeu_ps(out.as_mut_ptr().add(at), value) };
            }
        }
        for (t, tap) in taps.iter().enumerate().skip(full) {
            for (stack, out) in stacks.iter().zip(outs.iter_mut()) {
                // SAFETY: the tap satisfies `lerp_f32`'s contract.
                out[t] = unsafe { super::lerp_f32(stack, offset(tap), w, *tap) };
            }
        }
    }
}

/// Bilinear value of `stack` at top-left neighbour `k` (rows `w` apart) with the fractions of
/// `tap`: along the rows, then down. NaN when any neighbour is NaN.
///
/// # Safety
/// `k + w + 1 < stack.len()`: ERP taps point at a top-left neighbour with x0 ≤ w − 2 and
/// y0 ≤ h − 2 of a face inside the stack they were built for.
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
#[inline(always)]
unsafe fn lerp_f32(stack: &[f32], k: usize, w: usize, tap: Tap) -> f32 {
    debug_assert!(k + w + 1 < stack.len());
    let fx = f32::from(tap.fx) * (1.0 / FRAC_SCALE);
    let fy = f32::from(tap.fy) * (1.0 / FRAC_SCALE);
    // SAFETY: see the function's contract.
    let [tl, tr, bl, br] = unsafe {
        [
            *stack.get_unchecked(k),
            *stack.get_unchecked(k + 1),
            *stack.get_unchecked(k + w),
            *stack.get_unchecked(k + w + 1),
        ]
    };
    let top = tl + fx * (tr - tl);
    let bottom = bl + fx * (br - bl);
    top + fy * (bottom - top)
}

/// Most tangents one ERP pixel can be seen by (the icosahedron layout needs 5).
pub(crate) const MAX_FACES_PER_PIXEL: usize = 16;

/// How many pixels ahead the ERP rows of a tap are prefetched: the taps say exactly which cache
/// lines the next pixels need, which the hardware prefetcher cannot guess along a curved path.
const PREFETCH_DISTANCE: usize = 32;

/// Hint the CPU to load the cache line holding `data[index]` (no-op where unsupported).
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
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

/// ERP taps keep the tap's nearness rank at its pixel (0: the face whose axis is nearest) in
/// the index's top bits; the rest is the offset of the top-left neighbour within the face.
pub(crate) const RANK_SHIFT: u32 = 28;
pub(crate) const OFFSET_MASK: u32 = (1 << RANK_SHIFT) - 1;

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

    /// The bilinear value of a tangent stack (N·h·w) at every tap of ERP row `i`, in tap order,
    /// into `out`: NaN when any of the four neighbours is NaN.
    ///
    /// # Panics
    /// If `stack` is not the size the taps were built for (the bindings check shapes first).
    pub fn sample(&self, stack: &[f32], i: usize, out: &mut Vec<f32>) {
        self.sample_many([stack], i, [out]);
    }

    /// [`ErpTaps::sample`] of several stacks of the same size (a map and its blending weights)
    /// at once: each tap is decoded once for all of them.
    ///
    /// # Panics
    /// If a stack is not the size the taps were built for.
    pub fn sample_many<const M: usize>(
        &self,
        stacks: [&[f32]; M],
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
            unsafe { self.sample_run(stacks, &taps[run.taps()], run, parts) };
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
        i: usize,
        buffer: &mut Vec<f32>,
        mut visit: impl FnMut(&Run, &[f32], Ranks<'_>),
    ) {
        self.sample_runs_many([stack], i, [buffer], |run, [values], ranks| {
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
            unsafe { self.sample_run(stacks, taps, run, parts) };
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

    /// Bilinear values of each of `stacks` at the taps of `run` into `outs` (each as long as
    /// `taps`).
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
        taps: &[Tap],
        run: &Run,
        outs: [&mut [f32]; M],
    ) {
        let (w, base) = (self.tangent_width, run.face as usize * self.tangent_pixels);
        #[cfg(target_arch = "x86_64")]
        {
            // SAFETY: the caller's contract is the kernel's.
            unsafe { simd::lerp_run_f32(stacks, base, w, taps, outs) };
        }
        #[cfg(not(target_arch = "x86_64"))]
        for (stack, out) in stacks.iter().zip(outs) {
            for (t, (&tap, v)) in taps.iter().zip(out.iter_mut()).enumerate() {
                if let Some(ahead) = taps.get(t + PREFETCH_DISTANCE) {
                    let k = base + (ahead.index & OFFSET_MASK) as usize;
                    prefetch(stack, k);
                    prefetch(stack, k + w);
                }
                // SAFETY: taps of this map satisfy `lerp_f32`'s contract for a stack of the
                // size they were built for (the caller's contract).
                *v = unsafe { lerp_f32(stack, base + (tap.index & OFFSET_MASK) as usize, w, tap) };
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
/// One pass over the output: each row of each face plane is written once, runs and NaN gaps in
/// column order, while the row's samples are still in cache.
///
/// # Panics
/// If `out` is not N·H·W long or `tangents` not N·h·w.
pub fn tangents_to_erp(taps: &ErpTaps, layout: &Layout, tangents: &[f32], out: &mut [f32]) {
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
            taps.sample(tangents, i, values);
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

    /// The vectorised run sampling gives the scalar bilinear value's exact bits (NaN where a
    /// neighbour is NaN), on noise with scattered NaNs: a swapped lane or pair would differ.
    /// Sampling two stacks at once (`sample_many`) gives each one's bits too.
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
        let (mut got, mut nan) = (Vec::new(), 0);
        let (mut first, mut second) = (Vec::new(), Vec::new());
        for i in 0..layout.erp_height {
            taps.sample(&stack, i, &mut got);
            taps.sample_many([&stack, &other], i, [&mut first, &mut second]);
            let (runs, row_taps) = taps.row_parts(i);
            for run in runs {
                for t in run.taps() {
                    let tap = row_taps[t];
                    let k = run.face as usize * h * w + (tap.index & OFFSET_MASK) as usize;
                    // SAFETY: a tap of these taps, on stacks of their size.
                    let (want, want_other) =
                        unsafe { (lerp_f32(&stack, k, w, tap), lerp_f32(&other, k, w, tap)) };
                    nan += usize::from(want.is_nan());
                    assert!(same(got[t], want), "row {i}, tap {t}: {} vs {want}", got[t]);
                    assert!(
                        same(first[t], want) && same(second[t], want_other),
                        "row {i}"
                    );
                }
            }
        }
        assert!(nan > 0, "the NaN path was not exercised");
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
