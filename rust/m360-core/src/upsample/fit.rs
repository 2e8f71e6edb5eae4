//! The working-resolution fit of the guided upsampling: the seven planes (p0, m, e, a, b, lo, hi)
//! that [`super::upsample`] evaluates at full resolution, computed one band of rows at a time.
//!
//! Per working pixel, with the valid pixels (finite disparity p) of its (2r+1)² window (columns
//! wrapping in longitude, rows reflected at the poles as OpenCV's `BORDER_REFLECT`,
//! `fedcba|abcdefgh|hgfedcb`) and the grey level I of the photo shrunk to the working size
//! (0–255 → [0, 1]):
//!
//! - the least-squares fit p ≈ a·I + b over the window, regularised by ε on a:
//!   a = cov(I, p) / (var(I) + ε), b = mean(p) − a·mean(I) (none where the window has no valid
//!   pixel);
//! - the planes' a and b are the means of those fits over the same window (the fast guided
//!   filter's coefficients; 0 where no fit is in the window);
//! - lo and hi are the minimum and maximum of p over the 3 × 3 window (wrapping in longitude,
//!   cut at the top and bottom rows), and e the edge weight: with the relative jump
//!   J = (hi − lo) / max(|hi|, |lo|), e = clamp((J − edge_low) / (edge_high − edge_low), 0, 1);
//!   e, lo and hi are 0 where the 3 × 3 window holds an invalid pixel;
//! - p0 is p where valid and 0 elsewhere, m the validity (1 or 0).
//!
//! Both box filters are separable running sums in f64 (column sums slid down the band's rows,
//! window sums slid along each row), so a window costs the same at any radius and nothing the
//! size of the image is allocated: each thread keeps a few rows of sums and the band's fits.

use crate::error::{CoreError, Result};
use std::ops::Range;
use std::sync::{Mutex, PoisonError};

/// Working rows per band of [`fit_planes`] (and about that many per band of the fused
/// upsampling): the windows' overlap recomputes 4r rows per band, a few per cent at r = 1.
pub(super) const BAND_ROWS: usize = 32;

/// Parameters of the guided fit, checked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuidedFit {
    radius: usize,
    eps: f64,
    edge_low: f32,
    edge_span: f32,
}

impl GuidedFit {
    /// The fit with window radius `radius` (working pixels, 1 ≤ radius < the map's height
    /// `h`), regularisation `eps` (> 0, squared grey levels of [0, 1]) and the relative jumps
    /// `edge_low` < `edge_high` (≥ 0) between which the edge weight rises from 0 to 1.
    ///
    /// # Errors
    /// [`CoreError::InvalidOption`] naming the first parameter out of range.
    pub fn new(radius: usize, eps: f64, edge_low: f64, edge_high: f64, h: usize) -> Result<Self> {
        if radius == 0 || radius >= h {
            return Err(CoreError::option(
                "radius",
                format!(
                    "must be at least 1 and less than the disparity's height {h}, got {radius}"
                ),
            ));
        }
        if !(eps.is_finite() && eps > 0.0) {
            return Err(CoreError::option(
                "eps",
                format!("must be a positive number, got {eps}"),
            ));
        }
        if !(edge_low.is_finite()
            && edge_high.is_finite()
            && 0.0 <= edge_low
            && edge_low < edge_high)
        {
            return Err(CoreError::option(
                "edge_low",
                format!("need 0 <= edge_low < edge_high, got {edge_low}, {edge_high}"),
            ));
        }
        // The edge weight is evaluated in f32 like the float32 arrays it was first written for:
        // (J − low) / (high − low) with both constants rounded to f32.
        Ok(Self {
            radius,
            eps,
            edge_low: edge_low as f32,
            edge_span: (edge_high - edge_low) as f32,
        })
    }

    /// The window radius.
    #[must_use]
    pub fn radius(&self) -> usize {
        self.radius
    }
}

/// The working-resolution inputs of the fit: the disparity (NaN or ±inf = invalid) and the
/// photo's grey levels at the same size, both h × w row-major.
#[derive(Clone, Copy, Debug)]
pub struct WorkingMaps<'a> {
    /// Disparity, h × w.
    pub disparity: &'a [f32],
    /// Grey levels 0–255, h × w.
    pub grey: &'a [u8],
    /// Rows.
    pub h: usize,
    /// Columns.
    pub w: usize,
}

/// OpenCV's `BORDER_REFLECT` of row index `k` into `0..n` (`fedcba|abcdefgh|hgfedcb`).
pub(super) fn reflect(k: isize, n: usize) -> usize {
    let n = n as isize;
    let mut k = k;
    if n == 1 {
        return 0;
    }
    while k < 0 || k >= n {
        k = if k < 0 { -k - 1 } else { 2 * n - 1 - k };
    }
    k as usize
}

/// Row buffers of the separable box sums (f64, w × C for C ≤ 5).
#[derive(Debug, Default)]
pub(super) struct BoxScratch {
    column: Vec<f64>,
    window: Vec<f64>,
}

/// Window sums over (2r+1)² windows of the C interleaved channels of an h × w map, for the
/// rows `rows`: columns wrap, rows reflect (see [`reflect`]). `add_row(i, sign, sums)` adds
/// `sign` × row i's channels (w × C) to `sums`; `emit(i, window)` receives row i's sums.
///
/// The column sums are slid down the rows (one row added, one removed per step) and the window
/// sums along each row, in f64: exact for 0/1 counts, and far from drifting for the rest.
pub(super) fn box_rows<const C: usize>(
    (h, w): (usize, usize),
    radius: usize,
    rows: Range<usize>,
    scratch: &mut BoxScratch,
    mut add_row: impl FnMut(usize, f64, &mut [f64]),
    mut emit: impl FnMut(usize, &[f64]),
) {
    if rows.is_empty() {
        return;
    }
    scratch.column.clear();
    scratch.column.resize(w * C, 0.0);
    scratch.window.resize(w * C, 0.0);
    let (column, window) = (&mut scratch.column, &mut scratch.window[..w * C]);
    let r = radius as isize;
    let first = rows.start as isize;
    for k in first - r..=first + r {
        add_row(reflect(k, h), 1.0, column);
    }
    for i in rows.clone() {
        window_sums::<C>(column, w, radius, window);
        emit(i, window);
        if i + 1 < rows.end {
            let i = i as isize;
            add_row(reflect(i + r + 1, h), 1.0, column);
            add_row(reflect(i - r, h), -1.0, column);
        }
    }
}

/// Sums over the 2r+1 columns around each column of `column` (w × C), wrapping, into `window`.
fn window_sums<const C: usize>(column: &[f64], w: usize, radius: usize, window: &mut [f64]) {
    let mut sum = [0.0f64; C];
    for k in 0..=2 * radius {
        // Columns −r … r around column 0.
        let c = (k + w * (radius / w + 1) - radius) % w;
        for (s, v) in sum.iter_mut().zip(&column[c * C..c * C + C]) {
            *s += v;
        }
    }
    // The column entering and the one leaving the window as it moves right, kept in 0..w
    // without a division per pixel.
    let mut enter = (radius + 1) % w;
    let mut leave = (w * (radius / w + 1) - radius) % w;
    for out in window.chunks_exact_mut(C) {
        out.copy_from_slice(&sum);
        let (add, sub) = (
            &column[enter * C..enter * C + C],
            &column[leave * C..leave * C + C],
        );
        for ((s, a), b) in sum.iter_mut().zip(add).zip(sub) {
            *s += a - b;
        }
        enter = if enter + 1 == w { 0 } else { enter + 1 };
        leave = if leave + 1 == w { 0 } else { leave + 1 };
    }
}

/// Per-thread buffers of the fit (a few rows; the band's fits).
#[derive(Debug, Default)]
pub(super) struct FitScratch {
    boxes: BoxScratch,
    /// The per-window fits (counted, a, b) of the rows the band's second box filter reads.
    fits: Vec<f64>,
    /// Per column of a row: the 3-row minimum, maximum and all-valid flag.
    strip: Vec<(f32, f32, bool)>,
}

/// Buffers for each thread of the pool running a parallel loop (a thread takes its own, so the
/// lock is never contended; allocated once per call, not once per band).
pub(super) struct PerThread<T>(Vec<Mutex<T>>);

impl<T: Default> PerThread<T> {
    pub(super) fn new() -> Self {
        Self(
            (0..rayon::current_num_threads())
                .map(|_| Mutex::default())
                .collect(),
        )
    }

    /// This thread's buffers.
    pub(super) fn get(&self) -> std::sync::MutexGuard<'_, T> {
        let slot = rayon::current_thread_index().unwrap_or(0) % self.0.len();
        self.0[slot].lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// Grey level 0–255 → [0, 1], rounded through f32 as the float32 image it stands for.
fn grey_levels() -> [f64; 256] {
    std::array::from_fn(|v| f64::from(v as f32 / 255.0))
}

/// The planes (p0, m, e, a, b, lo, hi) of working rows `rows` into `planes`
/// (`rows.len()` × w × 7).
pub(super) fn fit_band(
    maps: WorkingMaps<'_>,
    fit: &GuidedFit,
    rows: Range<usize>,
    scratch: &mut FitScratch,
    planes: &mut [f32],
) {
    let WorkingMaps {
        disparity,
        grey,
        h,
        w,
    } = maps;
    let r = fit.radius;
    debug_assert_eq!(planes.len(), rows.len() * w * 7);
    let levels = grey_levels();
    // The rows whose fits the second box filter reads: the band widened by r (its reflections
    // at the poles fall inside this range as r < h).
    let fit_rows = rows.start.saturating_sub(r)..(rows.end + r).min(h);
    let FitScratch { boxes, fits, strip } = scratch;
    fits.resize(fit_rows.len() * w * 3, 0.0);
    let first = fit_rows.start;
    // Sums of m, m·I, p0, m·I·p0, m·I² over each window, and the fit from them.
    box_rows::<5>(
        (h, w),
        r,
        fit_rows.clone(),
        boxes,
        |i, sign, sums| {
            let row = &disparity[i * w..(i + 1) * w];
            let levels_row = &grey[i * w..(i + 1) * w];
            for ((s, &p), &g) in sums.chunks_exact_mut(5).zip(row).zip(levels_row) {
                if p.is_finite() {
                    let (p, g) = (f64::from(p), levels[usize::from(g)]);
                    let sg = sign * g;
                    s[0] += sign;
                    s[1] += sg;
                    s[2] += sign * p;
                    s[3] += sg * p;
                    s[4] += sg * g;
                }
            }
        },
        |i, window| {
            let out = &mut fits[(i - first) * w * 3..(i - first + 1) * w * 3];
            for (f, s) in out.chunks_exact_mut(3).zip(window.chunks_exact(5)) {
                // The counts are exact integers: > 0.5 is "at least one valid pixel".
                if s[0] > 0.5 {
                    let inv = 1.0 / s[0];
                    let (mean_i, mean_p) = (s[1] * inv, s[2] * inv);
                    let cov = s[3] * inv - mean_i * mean_p;
                    let var = (s[4] * inv - mean_i * mean_i).max(0.0);
                    let a = cov / (var + fit.eps);
                    f.copy_from_slice(&[1.0, a, mean_p - a * mean_i]);
                } else {
                    f.copy_from_slice(&[0.0; 3]);
                }
            }
        },
    );
    let fits = &*fits;
    strip.resize(w, (0.0, 0.0, false));
    // The window means of the fits' a and b, then the 3 × 3 range and edge weight, per row.
    box_rows::<3>(
        (h, w),
        r,
        rows.clone(),
        boxes,
        |i, sign, sums| {
            let row = &fits[(i - first) * w * 3..(i - first + 1) * w * 3];
            for (s, f) in sums.iter_mut().zip(row) {
                *s += sign * f;
            }
        },
        |i, window| {
            let out = &mut planes[(i - rows.start) * w * 7..(i - rows.start + 1) * w * 7];
            for (px, s) in out.chunks_exact_mut(7).zip(window.chunks_exact(3)) {
                let (a, b) = if s[0] > 0.5 {
                    (s[1] / s[0], s[2] / s[0])
                } else {
                    (0.0, 0.0)
                };
                px[3] = a as f32;
                px[4] = b as f32;
            }
            edge_row(disparity, (h, w), i, fit, strip, out);
        },
    );
}

/// Planes p0, m, e, lo, hi of row `i` into `out` (w × 7; a and b are left as they are).
fn edge_row(
    disparity: &[f32],
    (h, w): (usize, usize),
    i: usize,
    fit: &GuidedFit,
    strip: &mut [(f32, f32, bool)],
    out: &mut [f32],
) {
    // Down each column over rows i−1 … i+1 (those that exist: the window is cut at the poles).
    let rows = i.saturating_sub(1)..(i + 2).min(h);
    for (j, s) in strip.iter_mut().enumerate() {
        let mut acc = (f32::INFINITY, f32::NEG_INFINITY, true);
        for k in rows.clone() {
            let p = disparity[k * w + j];
            acc = (acc.0.min(p), acc.1.max(p), acc.2 && p.is_finite());
        }
        *s = acc;
    }
    let row = &disparity[i * w..(i + 1) * w];
    for (j, (px, &p)) in out.chunks_exact_mut(7).zip(row).enumerate() {
        let valid = p.is_finite();
        px[0] = if valid { p } else { 0.0 };
        px[1] = f32::from(u8::from(valid));
        // Across the three columns around j, wrapping in longitude.
        let left = if j == 0 { w - 1 } else { j - 1 };
        let right = if j + 1 == w { 0 } else { j + 1 };
        let (mut lo, mut hi, mut all_valid) = strip[j];
        for &(l, u, v) in [&strip[left], &strip[right]] {
            (lo, hi, all_valid) = (lo.min(l), hi.max(u), all_valid && v);
        }
        let (e, lo, hi) = if all_valid {
            let jump = (hi - lo) / hi.abs().max(lo.abs());
            let weight = ((jump - fit.edge_low) / fit.edge_span).clamp(0.0, 1.0);
            // 0 / 0 on a flat zero window: no jump.
            (if weight.is_finite() { weight } else { 0.0 }, lo, hi)
        } else {
            (0.0, 0.0, 0.0)
        };
        px[2] = e;
        px[5] = lo;
        px[6] = hi;
    }
}

/// The planes (p0, m, e, a, b, lo, hi) of the whole working map into `planes` (h × w × 7,
/// interleaved), as [`super::guided_upsample`] computes them band by band.
///
/// # Panics
/// If the slice sizes do not match `maps.h` × `maps.w` (the bindings check them first).
pub fn fit_planes(maps: WorkingMaps<'_>, fit: &GuidedFit, planes: &mut [f32]) {
    use rayon::prelude::*;
    let (h, w) = (maps.h, maps.w);
    assert_eq!(maps.disparity.len(), h * w, "disparity size");
    assert_eq!(maps.grey.len(), h * w, "grey size");
    assert_eq!(planes.len(), h * w * 7, "planes size");
    let scratch = PerThread::<FitScratch>::new();
    planes
        .par_chunks_mut(BAND_ROWS * w * 7)
        .enumerate()
        .for_each(|(band, chunk)| {
            let start = band * BAND_ROWS;
            let rows = start..start + chunk.len() / (w * 7);
            fit_band(maps, fit, rows, &mut scratch.get(), chunk);
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reflect_is_opencv_border_reflect() {
        // fedcba|abcdefgh|hgfedcb on 8 samples.
        let got: Vec<usize> = (-6..14).map(|k| reflect(k, 8)).collect();
        let want = [5, 4, 3, 2, 1, 0, 0, 1, 2, 3, 4, 5, 6, 7, 7, 6, 5, 4, 3, 2];
        assert_eq!(got, want);
        // Windows wider than the map bounce more than once; one sample is always itself.
        assert_eq!(reflect(-4, 3), 2);
        assert_eq!(reflect(7, 3), 1);
        assert_eq!(reflect(-5, 1), 0);
    }

    /// Box sums of two channels with wrap and reflect against a direct sum over each window,
    /// for whole maps and bands, radii 1–4 on maps as narrow as the window.
    #[test]
    fn box_sums_match_direct_window_sums() {
        for (h, w) in [(3, 6), (5, 9), (8, 16), (6, 5)] {
            let value =
                |i: usize, j: usize, c: usize| ((i * 31 + j * 7 + c * 13) % 17) as f64 - 4.5;
            for radius in 1..=4 {
                let direct = |i: usize, j: usize, c: usize| {
                    let r = radius as isize;
                    let mut sum = 0.0;
                    for di in -r..=r {
                        for dj in -r..=r {
                            let row = reflect(i as isize + di, h);
                            let col = (j as isize + dj).rem_euclid(w as isize) as usize;
                            sum += value(row, col, c);
                        }
                    }
                    sum
                };
                for rows in [0..h, 1..h - 1, h - 1..h] {
                    let mut scratch = BoxScratch::default();
                    let mut seen = Vec::new();
                    box_rows::<2>(
                        (h, w),
                        radius,
                        rows.clone(),
                        &mut scratch,
                        |i, sign, sums| {
                            for (j, s) in sums.chunks_exact_mut(2).enumerate() {
                                s[0] += sign * value(i, j, 0);
                                s[1] += sign * value(i, j, 1);
                            }
                        },
                        |i, window| {
                            seen.push(i);
                            for (j, s) in window.chunks_exact(2).enumerate() {
                                for (c, &got) in s.iter().enumerate() {
                                    let want = direct(i, j, c);
                                    assert!(
                                        (got - want).abs() < 1e-9,
                                        "{h}x{w} r={radius} ({i}, {j}, {c}): {got} vs {want}"
                                    );
                                }
                            }
                        },
                    );
                    assert_eq!(seen, rows.collect::<Vec<_>>());
                }
            }
        }
    }

    fn scene(h: usize, w: usize) -> (Vec<f32>, Vec<u8>) {
        let mut state = 0x9e37_79b9_u32;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            state
        };
        let disparity = (0..h * w)
            .map(|_| {
                let v = next();
                if v % 5 == 0 {
                    f32::NAN
                } else {
                    0.5 + (v >> 8) as f32 / (1u32 << 24) as f32
                }
            })
            .collect();
        let grey = (0..h * w).map(|_| (next() >> 24) as u8).collect();
        (disparity, grey)
    }

    /// The planes against the definitions evaluated per pixel (direct window loops in f64).
    #[test]
    #[expect(
        clippy::float_cmp,
        reason = "p0, m, lo and hi are copies of input values: exactly equal"
    )]
    fn planes_match_direct_evaluation() {
        let (h, w) = (9, 18);
        let (disparity, grey) = scene(h, w);
        let maps = WorkingMaps {
            disparity: &disparity,
            grey: &grey,
            h,
            w,
        };
        for radius in 1..=3 {
            let fit = GuidedFit::new(radius, 1e-3, 0.05, 0.15, h).expect("valid fit");
            let mut planes = vec![0.0; h * w * 7];
            fit_planes(maps, &fit, &mut planes);
            let r = radius as isize;
            let at = |i: isize, j: isize| {
                let (i, j) = (reflect(i, h), j.rem_euclid(w as isize) as usize);
                (disparity[i * w + j], f64::from(grey[i * w + j]) / 255.0)
            };
            // The fit of the window around (i, j): Some((a, b)) if it has a valid pixel.
            let fit_at = |i: isize, j: isize| {
                let mut s = [0.0f64; 5];
                for di in -r..=r {
                    for dj in -r..=r {
                        let (p, g) = at(i + di, j + dj);
                        if p.is_finite() {
                            let p = f64::from(p);
                            for (acc, v) in s.iter_mut().zip([1.0, g, p, g * p, g * g]) {
                                *acc += v;
                            }
                        }
                    }
                }
                (s[0] > 0.0).then(|| {
                    let (mi, mp) = (s[1] / s[0], s[2] / s[0]);
                    let var = (s[4] / s[0] - mi * mi).max(0.0);
                    let a = (s[3] / s[0] - mi * mp) / (var + 1e-3);
                    (a, mp - a * mi)
                })
            };
            for i in 0..h {
                for j in 0..w {
                    let (mut n, mut sa, mut sb) = (0.0, 0.0, 0.0);
                    for di in -r..=r {
                        for dj in -r..=r {
                            let row = reflect(i as isize + di, h) as isize;
                            if let Some((a, b)) = fit_at(row, j as isize + dj) {
                                (n, sa, sb) = (n + 1.0, sa + a, sb + b);
                            }
                        }
                    }
                    let (a, b) = if n > 0.0 {
                        (sa / n, sb / n)
                    } else {
                        (0.0, 0.0)
                    };
                    let px = &planes[(i * w + j) * 7..(i * w + j) * 7 + 7];
                    let close = |got: f32, want: f64| {
                        (f64::from(got) - want).abs() <= 1e-5 * want.abs().max(1.0)
                    };
                    assert!(close(px[3], a) && close(px[4], b), "r={radius} ({i}, {j})");
                    // The 3 × 3 range, cut at the poles, wrapping in longitude.
                    let mut window = Vec::new();
                    for k in i.saturating_sub(1)..(i + 2).min(h) {
                        for dj in -1..=1 {
                            window.push(at(k as isize, j as isize + dj).0);
                        }
                    }
                    let p = disparity[i * w + j];
                    assert_eq!(px[0], if p.is_finite() { p } else { 0.0 });
                    assert_eq!(px[1], if p.is_finite() { 1.0 } else { 0.0 });
                    if window.iter().all(|v| v.is_finite()) {
                        let lo = window.iter().copied().fold(f32::INFINITY, f32::min);
                        let hi = window.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                        let jump = f64::from(hi - lo) / f64::from(hi.abs().max(lo.abs()));
                        let e = ((jump - 0.05) / 0.1).clamp(0.0, 1.0);
                        assert_eq!((px[5], px[6]), (lo, hi));
                        assert!(close(px[2], e), "e at ({i}, {j}): {} vs {e}", px[2]);
                    } else {
                        assert_eq!((px[2], px[5], px[6]), (0.0, 0.0, 0.0));
                    }
                }
            }
        }
    }

    #[test]
    fn parameters_out_of_range_are_refused() {
        assert!(GuidedFit::new(0, 1e-4, 0.05, 0.15, 8).is_err());
        assert!(GuidedFit::new(8, 1e-4, 0.05, 0.15, 8).is_err());
        assert!(GuidedFit::new(1, 0.0, 0.05, 0.15, 8).is_err());
        assert!(GuidedFit::new(1, f64::NAN, 0.05, 0.15, 8).is_err());
        assert!(GuidedFit::new(1, 1e-4, 0.15, 0.15, 8).is_err());
        assert!(GuidedFit::new(1, 1e-4, -0.1, 0.15, 8).is_err());
        assert!(GuidedFit::new(7, 1e-4, 0.0, 0.15, 8).is_ok());
    }
}
