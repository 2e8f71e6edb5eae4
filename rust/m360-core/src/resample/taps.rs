//! The tap encoding shared by both directions: [`Tap`] (a top-left source index whose top bits
//! carry [`WRAPPED`] or a nearness rank, and two fixed-point fractions), how a pixel type
//! combines four neighbours at a tap ([`Texel`], [`lerp_f32`]), and the prefetch helper.

#[cfg(target_arch = "x86_64")]
use super::simd;
use super::to_tangents::{sample_run_scalar, ErpSource};
use crate::options::choice;

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

/// How a stack of tangent values is interpolated at an ERP tap.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sampling {
    /// Bilinear: for smooth quantities (blending weights, masks, anything a caller maps).
    Bilinear,
    /// Bilinear, but not across a depth edge: where the four neighbours span a jump of more
    /// than [`EDGE_JUMP`], only the side holding most of the bilinear weight is interpolated
    /// ([`lerp_f32_edges`]). For disparity: a value between the two sides is a point in
    /// mid-air (a "flying pixel"), on neither surface.
    DepthEdges,
}

choice!(
    Sampling,
    "sampling",
    [
        (Sampling::Bilinear, "bilinear"),
        (Sampling::DepthEdges, "depth_edges")
    ]
);

/// Smallest relative jump between the four neighbours of a tap, (hi − lo)/max(|hi|, |lo|), that
/// [`Sampling::DepthEdges`] treats as a depth edge: 5 %, the jump `m360.eval.edge_band` and the
/// benches call an edge. Within one pixel a smooth surface changes this much only at grazing
/// angles (on a plane, within about 3.5° of its horizon at 2K; docs/method.md, "Sampling
/// across depth edges").
pub(crate) const EDGE_JUMP: f32 = 0.05;

/// Whether neighbours from `lo` to `hi` span a depth edge (false when either is NaN).
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
#[inline(always)]
fn spans_edge(lo: f32, hi: f32) -> bool {
    hi - lo > EDGE_JUMP * hi.abs().max(lo.abs())
}

/// [`lerp_f32`] that does not interpolate across a depth edge ([`Sampling::DepthEdges`]): when
/// the neighbours span one, they are split at the middle of their range and the side with the
/// larger sum of bilinear weights is interpolated alone (the nearer side on a tie). Otherwise,
/// and whenever a neighbour is NaN, `lerp_f32`'s value and bits.
///
/// # Safety
/// As [`lerp_f32`].
#[inline]
pub(super) unsafe fn lerp_f32_edges(stack: &[f32], k: usize, w: usize, tap: Tap) -> f32 {
    debug_assert!(k + w + 1 < stack.len());
    // SAFETY: see the function's contract.
    let corners = unsafe {
        [
            *stack.get_unchecked(k),
            *stack.get_unchecked(k + 1),
            *stack.get_unchecked(k + w),
            *stack.get_unchecked(k + w + 1),
        ]
    };
    let lo = corners.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = corners.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    if corners.iter().any(|v| v.is_nan()) || !spans_edge(lo, hi) {
        // SAFETY: the same contract.
        return unsafe { lerp_f32(stack, k, w, tap) };
    }
    let middle = 0.5 * (lo + hi);
    let (mut near, mut near_weight, mut far, mut far_weight) = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
    for (&v, weight) in corners.iter().zip(tap.weights()) {
        if v >= middle {
            near += weight * v;
            near_weight += weight;
        } else {
            far += weight * v;
            far_weight += weight;
        }
    }
    // The weights sum to one, so the heavier side weighs at least ½.
    if near_weight >= far_weight {
        near / near_weight
    } else {
        far / far_weight
    }
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

    /// Edge-aware sampling of one 2 × 2 cell `[tl, tr, bl, br]` at fractions (fx, fy).
    fn across(cell: [f32; 4], fx: f64, fy: f64) -> (f32, f32) {
        // Rows of width 2 with a padding row, so the cell is the top-left 2 × 2 of a 2 × 3 stack.
        let stack = [cell[0], cell[1], cell[2], cell[3], 0.0, 0.0];
        let tap = Tap::new(0, fx, fy);
        // SAFETY: k + w + 1 = 3 < 6.
        unsafe {
            (
                lerp_f32_edges(&stack, 0, 2, tap),
                lerp_f32(&stack, 0, 2, tap),
            )
        }
    }

    /// At a step between the columns, a tap takes the side it is nearer to, interpolated along
    /// that side alone (checked against the side's own linear interpolation), never a value in
    /// between; the nearer (larger) side on a tie.
    #[test]
    fn depth_edge_sampling_takes_one_side_of_a_step() {
        // Far side on the left (disparity 1.0 → 1.1 down), near side on the right (3.0 → 3.3).
        let cell = [1.0, 3.0, 1.1, 3.3];
        for (fx, fy) in [
            (0.1, 0.0),
            (0.3, 0.5),
            (0.49, 0.9),
            (0.51, 0.2),
            (0.8, 0.7),
            (1.0, 1.0),
        ] {
            let (got, bilinear) = across(cell, fx, fy);
            let q = |f: f64| (f * 32768.0).round() / 32768.0;
            let side = if fx < 0.5 { (1.0, 1.1) } else { (3.0, 3.3) };
            let want = side.0 + q(fy) * (side.1 - side.0);
            assert!(
                (f64::from(got) - want).abs() < 1e-6,
                "({fx}, {fy}): {got} vs {want}"
            );
            assert!((got - bilinear).abs() > 0.1 || fx <= 0.1 || fx >= 0.9);
        }
        assert_eq!(
            across(cell, 0.5, 0.0).0.to_bits(),
            3.0f32.to_bits(),
            "a tie goes to the nearer side"
        );
        // A corner alone across the edge (a diagonal edge): it wins only where it weighs most.
        let corner = [2.0, 1.0, 1.0, 1.0];
        assert_eq!(across(corner, 0.0, 0.0).0.to_bits(), 2.0f32.to_bits());
        assert_eq!(across(corner, 0.4, 0.4).0.to_bits(), 1.0f32.to_bits());
    }

    /// Below a 5 % jump, and wherever a neighbour is NaN, the bilinear value's exact bits; the
    /// jump is relative, so it does not depend on the units.
    #[test]
    fn depth_edge_sampling_is_bilinear_off_edges() {
        for scale in [1e-3, 1.0, 250.0] {
            let smooth = [1.0, 1.04, 0.99, 1.02].map(|v| v * scale);
            let step = [1.0, 1.06, 1.0, 1.06].map(|v| v * scale);
            for (fx, fy) in [(0.2, 0.3), (0.5, 0.5), (0.7, 0.1)] {
                let (got, bilinear) = across(smooth, fx, fy);
                assert_eq!(got.to_bits(), bilinear.to_bits());
                let (got, bilinear) = across(step, fx, fy);
                assert_ne!(got.to_bits(), bilinear.to_bits());
            }
        }
        let (got, _) = across([1.0, f32::NAN, 3.0, 3.0], 0.9, 0.9);
        assert!(got.is_nan());
    }
}
