//! Fixed-point u8 bilinear sampling with x86 SIMD: one pixel's four neighbours in 128 bits
//! (SSSE3), two pixels in 256 bits (AVX2).
//!
//! Each value is interpolated in 1/128 steps of a grey level with the taps' 2⁻¹⁵ fractions
//! (pmulhrsw), first along rows, then down: within 1/128 of the exact bilinear value before the
//! final rounding.

use super::taps::{
    lerp_f32, lerp_f32_edges, prefetch, Sampling, Tap, Texel, EDGE_JUMP, FRAC_SCALE, OFFSET_MASK,
    PREFETCH_DISTANCE, WRAPPED,
};
use super::to_tangents::{prefetch_tap, ErpSource};
use std::arch::x86_64::{
    __m128, __m128i, _mm256_add_epi16, _mm256_broadcastsi128_si256, _mm256_extract_epi32,
    _mm256_mulhrs_epi16, _mm256_packus_epi16, _mm256_set1_epi16, _mm256_set_m128i,
    _mm256_shuffle_epi8, _mm256_slli_epi16, _mm256_srli_epi16, _mm256_sub_epi16, _mm_add_epi16,
    _mm_add_ps, _mm_and_ps, _mm_and_si128, _mm_andnot_ps, _mm_castpd_ps, _mm_castps_si128,
    _mm_castsi128_ps, _mm_cmpge_ps, _mm_cmpgt_ps, _mm_cmpord_ps, _mm_cvtepi32_ps,
    _mm_cvtsi128_si32, _mm_div_ps, _mm_load_sd, _mm_loadl_epi64, _mm_loadu_si128, _mm_max_ps,
    _mm_min_ps, _mm_movehl_ps, _mm_movelh_ps, _mm_movemask_ps, _mm_mul_ps, _mm_mulhrs_epi16,
    _mm_or_ps, _mm_packus_epi16, _mm_set1_epi16, _mm_set1_epi32, _mm_set1_ps, _mm_setzero_ps,
    _mm_shuffle_epi8, _mm_shuffle_ps, _mm_slli_epi16, _mm_srli_epi16, _mm_srli_epi32,
    _mm_storeu_ps, _mm_sub_epi16, _mm_sub_ps, _mm_unpacklo_epi64, _mm_unpacklo_ps,
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

/// [`lerp_f32_edges`] on four lanes, branch-free: the lanes of `bilinear` whose neighbours
/// `[tl, tr, bl, br]` span a depth edge (none NaN) are replaced by the heavier side's
/// interpolation. The same operations in the same order as the scalar kernel, so the same bits
/// (a corner on the other side adds an exact +0).
#[target_feature(enable = "sse2")]
#[inline]
fn across_edges(
    bilinear: __m128,
    corners: [__m128; 4],
    fx: __m128,
    fy: __m128,
    jump: __m128,
    magnitude: __m128,
) -> __m128 {
    let [tl, tr, bl, br] = corners;
    let lo = _mm_min_ps(_mm_min_ps(tl, tr), _mm_min_ps(bl, br));
    let hi = _mm_max_ps(_mm_max_ps(tl, tr), _mm_max_ps(bl, br));
    let size = _mm_max_ps(_mm_and_ps(hi, magnitude), _mm_and_ps(lo, magnitude));
    let finite = _mm_and_ps(_mm_cmpord_ps(tl, tr), _mm_cmpord_ps(bl, br));
    let across = _mm_and_ps(
        finite,
        _mm_cmpgt_ps(_mm_sub_ps(hi, lo), _mm_mul_ps(jump, size)),
    );
    if _mm_movemask_ps(across) == 0 {
        return bilinear;
    }
    let middle = _mm_mul_ps(_mm_set1_ps(0.5), _mm_add_ps(lo, hi));
    let one = _mm_set1_ps(1.0);
    let (gx, gy) = (_mm_sub_ps(one, fx), _mm_sub_ps(one, fy));
    let weights = [
        _mm_mul_ps(gx, gy),
        _mm_mul_ps(fx, gy),
        _mm_mul_ps(gx, fy),
        _mm_mul_ps(fx, fy),
    ];
    let zero = _mm_setzero_ps();
    let (mut near, mut near_weight, mut far, mut far_weight) = (zero, zero, zero, zero);
    for (v, weight) in corners.into_iter().zip(weights) {
        let is_near = _mm_cmpge_ps(v, middle);
        let product = _mm_mul_ps(weight, v);
        near = _mm_add_ps(near, _mm_and_ps(is_near, product));
        near_weight = _mm_add_ps(near_weight, _mm_and_ps(is_near, weight));
        far = _mm_add_ps(far, _mm_andnot_ps(is_near, product));
        far_weight = _mm_add_ps(far_weight, _mm_andnot_ps(is_near, weight));
    }
    let take_near = _mm_cmpge_ps(near_weight, far_weight);
    let side = select(
        take_near,
        _mm_div_ps(near, near_weight),
        _mm_div_ps(far, far_weight),
    );
    select(across, side, bilinear)
}

/// Lanes of `a` where `mask` is set, of `b` elsewhere (SSE2 has no blendv).
#[target_feature(enable = "sse2")]
#[inline]
fn select(mask: __m128, a: __m128, b: __m128) -> __m128 {
    _mm_or_ps(_mm_and_ps(mask, a), _mm_andnot_ps(mask, b))
}

/// [`lerp_f32`] of ERP taps in each of `M` stacks of the same size (a map and
/// its blending weights), four taps at a time with SSE2 (baseline x86-64): the same
/// operations in the same order, so the same bits. With `first` = [`Sampling::DepthEdges`]
/// the first stack is read as [`lerp_f32_edges`] reads it, four lanes at a time
/// ([`across_edges`]), with its bits. Each tap's two rows are
/// read as 64-bit pairs (top-left and top-right, bottom-left and bottom-right), and the
/// fractions and offsets of four taps are decoded once for all stacks. Prefetches once per four
/// taps.
///
/// # Safety
/// Every tap, its offset in the low [`RANK_SHIFT`](super::taps::RANK_SHIFT) bits plus `base`,
/// must satisfy `lerp_f32`'s contract for each stack; each `outs[m]` is as long as `taps`.
#[target_feature(enable = "sse2")]
pub(super) unsafe fn lerp_run_f32<const M: usize>(
    stacks: [&[f32]; M],
    first: Sampling,
    base: usize,
    w: usize,
    taps: &[Tap],
    mut outs: [&mut [f32]; M],
) {
    let edges = first == Sampling::DepthEdges;
    let jump = _mm_set1_ps(EDGE_JUMP);
    let magnitude = _mm_castsi128_ps(_mm_set1_epi32(0x7fff_ffff));
    debug_assert!(outs.iter().all(|o| o.len() == taps.len()));
    let scale = _mm_set1_ps(1.0 / FRAC_SCALE);
    let low16 = _mm_set1_epi32(0xffff);
    let offset = |tap: &Tap| base + (tap.index & OFFSET_MASK) as usize;
    let full = taps.len() / 4 * 4;
    for at in (0..full).step_by(4) {
        let quad = &taps[at..at + 4];
        if let Some(ahead) = taps.get(at + PREFETCH_DISTANCE) {
            for stack in stacks {
                prefetch(stack, offset(ahead));
                prefetch(stack, offset(ahead) + w);
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
        let lerp = |p: __m128, q: __m128, f: __m128| _mm_add_ps(p, _mm_mul_ps(f, _mm_sub_ps(q, p)));
        for (m, (stack, out)) in stacks.iter().zip(outs.iter_mut()).enumerate() {
            let src = stack.as_ptr();
            // SAFETY (both loads): `offset(tap) + w + 1 < stack.len()` (contract), so both
            // 8-byte pairs of a tap are inside `stack`.
            #[expect(
                clippy::cast_ptr_alignment,
                reason = "_mm_load_sd is an unaligned load"
            )]
            let pair = |k: usize| unsafe { _mm_castpd_ps(_mm_load_sd(src.add(k).cast::<f64>())) };
            let (tl, tr) = split(k.map(pair));
            let (bl, br) = split(k.map(|k| pair(k + w)));
            let mut value = lerp(lerp(tl, tr, fx), lerp(bl, br, fx), fy);
            if edges && m == 0 {
                value = across_edges(value, [tl, tr, bl, br], fx, fy, jump, magnitude);
            }
            // SAFETY: `at + 4 ≤ out.len()`.
            unsafe { _mm_storeu_ps(out.as_mut_ptr().add(at), value) };
        }
    }
    for (t, tap) in taps.iter().enumerate().skip(full) {
        for (m, (stack, out)) in stacks.iter().zip(outs.iter_mut()).enumerate() {
            // SAFETY: the tap satisfies `lerp_f32`'s contract.
            out[t] = unsafe {
                if edges && m == 0 {
                    lerp_f32_edges(stack, offset(tap), w, *tap)
                } else {
                    lerp_f32(stack, offset(tap), w, *tap)
                }
            };
        }
    }
}
