//! The tap encoding shared by both directions: [`Tap`] (a top-left source index whose top bits
//! carry [`WRAPPED`] or a nearness rank, and two fixed-point fractions), how a pixel type
//! combines four neighbours at a tap ([`Texel`], [`lerp_f32`]), and the prefetch helper.

#[cfg(target_arch = "x86_64")]
use super::simd;
use super::to_tangents::{sample_run_scalar, ErpSource};

/// Fixed-point scale of bilinear fractions: 2⁻¹⁵ pixel resolution.
pub(super) const FRAC_SCALE: f32 = 32768.0;
/// Flag on [`Tap::index`] of a tangent tap whose four ERP neighbours are not in the plain
/// 2×2 arrangement (longitude wrap or across a pole); the rest of the index points into
/// [`TangentTaps::wrapped`](super::TangentTaps::wrapped).
pub(crate) const WRAPPED: u32 = 1 << 31;

/// ERP taps keep the tap's nearness rank at its pixel (0: the face whose axis is nearest) in
/// the index's top bits; the rest is the offset of the top-left neighbour within the face.
pub(crate) const RANK_SHIFT: u32 = 28;
pub(crate) const OFFSET_MASK: u32 = (1 << RANK_SHIFT) - 1;

/// A bilinear sampling position: top-left source index and fractions in units of 2⁻¹⁵.
///
/// `repr(C)`: the SIMD kernels load taps as pairs of 32-bit lanes (index, fx | fy << 16).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[repr(C)]
pub struct Tap {
    /// Flat index of the top-left source pixel (meaning depends on the map).
    pub index: u32,
    pub(super) fx: u16,
    pub(super) fy: u16,
}

impl Tap {
    pub(super) fn new(index: u32, fx: f64, fy: f64) -> Self {
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
pub(super) unsafe fn lerp_f32(stack: &[f32], k: usize, w: usize, tap: Tap) -> f32 {
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

/// How many pixels ahead the ERP rows of a tap are prefetched: the taps say exactly which cache
/// lines the next pixels need, which the hardware prefetcher cannot guess along a curved path.
pub(super) const PREFETCH_DISTANCE: usize = 32;

/// Hint the CPU to load the cache line holding `data[index]` (no-op where unsupported).
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
#[inline(always)]
pub(super) fn prefetch<T>(data: &[T], index: usize) {
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

#[cfg(test)]
mod tests {
    use super::*;

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
