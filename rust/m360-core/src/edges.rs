//! Photo-guided refinement of blurred depth edges: a confidence-weighted mode filter.
//!
//! A depth network that runs below the resolution of its tile returns depth edges smeared over
//! a few pixels; the photo at full resolution still has them sharp. Near disparity jumps only,
//! each pixel here takes the weighted mode of the log disparities in its window (a weighted mode
//! filter, Min, Lu & Do, TIP 2012), each sample weighted by
//! - space: a gaussian of the offset, of std radius / 2;
//! - colour: a gaussian of the RGB distance to the pixel's own colour, of std `colour_sigma`
//!   (0-255 levels), cut at 3 std: the sample must look like the same surface;
//! - flatness: exp(−(|∇ log d| · radius / transition)²): a sample inside a smeared transition
//!   (its log disparity changes by about `transition` or more over the radius) carries
//!   little weight, so the value comes from the flat sides of the edge.
//!
//! The window's log disparities are put in [`BINS`] bins over their own range; the heaviest
//! run of three adjacent bins wins (the first one on ties), and the mode is the weighted mean
//! of its samples. The result, in log disparity, is f · own + (1 − f) · mode with f the pixel's
//! own flatness weight: a pixel inside a transition takes the mode, one on a smooth ramp keeps
//! its value (a mode alone cuts ramps into terraces). Where the window's range is at most
//! `jump` the pixel is kept, so smooth surfaces are never touched, and so is a pixel whose
//! window has no weight. Invalid pixels (NaN or ≤ 0) stay as they are and are never samples.
//! Windows wrap in longitude (docs/conventions.md) and are cut at the top and bottom rows; a
//! radius above [`FULL_TAPS`] samples every `ceil(radius / FULL_TAPS)`-th offset, so the cost
//! per pixel is bounded. Every output pixel is a function of the inputs alone (fixed sample
//! order, sequential sums), so the result is the same for any number of threads.

use crate::error::{CoreError, Result};
use rayon::prelude::*;

/// Bins of the log-disparity histogram of a window.
pub const BINS: usize = 24;
/// Largest radius whose every offset is sampled.
pub const FULL_TAPS: usize = 3;
/// Largest accepted radius.
pub const MAX_RADIUS: usize = 256;
/// Colour distances beyond this many standard deviations weigh nothing.
const COLOUR_CUT: f64 = 3.0;
/// Samples of a smaller flatness weight than this are left out (exp(−7)).
const MIN_FLATNESS: f32 = 1e-3;

/// Options of [`refine_edges`], checked.
#[derive(Debug, Clone)]
pub struct EdgeRefine {
    radius: usize,
    step: usize,
    transition: f64,
    jump: f32,
    /// exp(−d² / 2σ²) for the integer squared RGB distances d² up to the cut.
    colour_weight: Vec<f32>,
    /// (dy, dx, spatial weight) of the sampled offsets, in the order they are summed.
    taps: Vec<(isize, isize, f32)>,
}

impl EdgeRefine {
    /// Checks and prepares the options: `radius` in pixels (1..=[`MAX_RADIUS`]),
    /// `colour_sigma` in 0-255 levels, `transition` and `jump` relative (log) changes, all > 0.
    ///
    /// # Errors
    /// [`CoreError::InvalidOption`] naming the first option out of its range.
    pub fn new(radius: usize, colour_sigma: f64, transition: f64, jump: f64) -> Result<Self> {
        if radius == 0 || radius > MAX_RADIUS {
            return Err(CoreError::option(
                "radius",
                format!("must be between 1 and {MAX_RADIUS} pixels, got {radius}"),
            ));
        }
        if !(colour_sigma.is_finite() && colour_sigma > 0.0 && colour_sigma <= 1000.0) {
            return Err(CoreError::option(
                "colour_sigma",
                format!("must be a number in (0, 1000] (0-255 levels), got {colour_sigma}"),
            ));
        }
        if !(transition.is_finite() && transition > 0.0) {
            return Err(CoreError::option(
                "transition",
                format!("must be a positive number, got {transition}"),
            ));
        }
        if !(jump.is_finite() && jump > 0.0) {
            return Err(CoreError::option(
                "jump",
                format!("must be a positive number, got {jump}"),
            ));
        }
        let two_var = 2.0 * colour_sigma * colour_sigma;
        let cut = (COLOUR_CUT * COLOUR_CUT * colour_sigma * colour_sigma).ceil() as usize;
        let cut = cut.min(3 * 255 * 255);
        let colour_weight = (0..=cut)
            .map(|d2| (-(d2 as f64) / two_var).exp() as f32)
            .collect();
        let step = radius.div_ceil(FULL_TAPS);
        let reach = (radius / step) as isize;
        let space_var = 2.0 * (radius as f64 / 2.0).powi(2);
        let mut taps = Vec::with_capacity((2 * reach as usize + 1).pow(2));
        for ky in -reach..=reach {
            for kx in -reach..=reach {
                let (dy, dx) = (ky * step as isize, kx * step as isize);
                let d2 = (dy * dy + dx * dx) as f64;
                taps.push((dy, dx, (-d2 / space_var).exp() as f32));
            }
        }
        Ok(Self {
            radius,
            step,
            transition,
            jump: jump as f32,
            colour_weight,
            taps,
        })
    }

    /// The window radius in pixels.
    #[must_use]
    pub fn radius(&self) -> usize {
        self.radius
    }

    /// The distance in pixels between sampled offsets (1 up to [`FULL_TAPS`]).
    #[must_use]
    pub fn step(&self) -> usize {
        self.step
    }

    /// Sampled offsets on each side of the centre, per axis.
    fn reach(&self) -> usize {
        self.radius / self.step
    }
}

/// Log disparity, NaN where the disparity is invalid (NaN, infinite or ≤ 0).
fn log_disparity(disparity: &[f32]) -> Vec<f32> {
    disparity
        .par_iter()
        .map(|&d| {
            if d.is_finite() && d > 0.0 {
                d.ln()
            } else {
                f32::NAN
            }
        })
        .collect()
}

/// Flatness weight exp(−(|∇ log d| · radius / transition)²) per pixel, central differences
/// (one-sided at the top and bottom rows, wrapping in longitude); 0 where a difference needs
/// an invalid pixel.
fn flatness(logd: &[f32], (h, w): (usize, usize), opts: &EdgeRefine) -> Vec<f32> {
    let scale = (opts.radius as f64 / opts.transition) as f32;
    let mut out = vec![0.0f32; h * w];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let (up, down) = (y.saturating_sub(1), (y + 1).min(h - 1));
        let dy_span = (down - up).max(1) as f32;
        for (x, o) in row.iter_mut().enumerate() {
            let (left, right) = ((x + w - 1) % w, (x + 1) % w);
            let gx = (logd[y * w + right] - logd[y * w + left]) * 0.5;
            let gy = if h > 1 {
                (logd[down * w + x] - logd[up * w + x]) / dy_span
            } else {
                0.0
            };
            let g2 = (gx * gx + gy * gy) * scale * scale;
            *o = if g2.is_finite() { (-g2).exp() } else { 0.0 };
        }
    });
    out
}

/// Scratch of one band of output rows: the row pass of the window's range.
#[derive(Default)]
struct BandScratch {
    /// Per source row of the band: the minimum / maximum over the sampled columns.
    lo: Vec<f32>,
    hi: Vec<f32>,
    /// One row padded by the window's reach on both sides (wrapping in longitude).
    padded: Vec<f32>,
    /// The window's range along the output row.
    range_lo: Vec<f32>,
    range_hi: Vec<f32>,
    samples: Vec<(f32, f32)>,
}

/// Output rows per band: the row pass is shared by the band's rows.
const BAND_ROWS: usize = 32;

/// Row pass of the window range: `lo`/`hi` get the minimum/maximum of `row` over the offsets
/// k · step, |k| ≤ reach, wrapping in longitude; invalid (NaN) values are left out.
fn row_extremes(
    row: &[f32],
    opts: &EdgeRefine,
    scratch: &mut Vec<f32>,
    lo: &mut [f32],
    hi: &mut [f32],
) {
    let w = row.len();
    let pad = opts.reach() * opts.step;
    scratch.clear();
    scratch.extend((0..w + 2 * pad).map(|i| row[(i + w * pad.div_ceil(w) - pad) % w]));
    lo.fill(f32::INFINITY);
    hi.fill(f32::NEG_INFINITY);
    for k in 0..=2 * opts.reach() {
        let shifted = &scratch[k * opts.step..k * opts.step + w];
        // Comparisons with NaN are false: invalid pixels drop out by themselves.
        for ((l, u), &v) in lo.iter_mut().zip(hi.iter_mut()).zip(shifted) {
            *l = if v < *l { v } else { *l };
            *u = if v > *u { v } else { *u };
        }
    }
}

/// Refines the disparity (h, w) near its jumps along the edges of the photo `rgb` (h, w, 3)
/// uint8, row-major, into `out` (h, w); see the module documentation.
///
/// # Panics
/// If the slice sizes do not match (the bindings check them first).
pub fn refine_edges(
    disparity: &[f32],
    rgb: &[u8],
    (h, w): (usize, usize),
    opts: &EdgeRefine,
    out: &mut [f32],
) {
    assert_eq!(disparity.len(), h * w, "disparity size");
    assert_eq!(rgb.len(), h * w * 3, "photo size");
    assert_eq!(out.len(), h * w, "output size");
    let logd = log_disparity(disparity);
    let flat = flatness(&logd, (h, w), opts);
    let cut = opts.colour_weight.len() - 1;
    let span = opts.reach() * opts.step;
    out.par_chunks_mut(BAND_ROWS * w).enumerate().for_each_init(
        BandScratch::default,
        |scratch, (band, chunk)| {
            let first = band * BAND_ROWS;
            let rows = first..first + chunk.len() / w;
            let source = rows.start.saturating_sub(span)..(rows.end + span).min(h);
            let BandScratch {
                lo,
                hi,
                padded,
                range_lo,
                range_hi,
                samples,
            } = scratch;
            lo.resize(source.len() * w, 0.0);
            hi.resize(source.len() * w, 0.0);
            range_lo.resize(w, 0.0);
            range_hi.resize(w, 0.0);
            for (k, y) in source.clone().enumerate() {
                let (l, u) = (&mut lo[k * w..(k + 1) * w], &mut hi[k * w..(k + 1) * w]);
                row_extremes(&logd[y * w..(y + 1) * w], opts, padded, l, u);
            }
            for (y, out_row) in rows.zip(chunk.chunks_exact_mut(w)) {
                out_row.copy_from_slice(&disparity[y * w..(y + 1) * w]);
                // Column pass: the window's range along this row.
                range_lo.fill(f32::INFINITY);
                range_hi.fill(f32::NEG_INFINITY);
                for (dy, _, _) in opts.taps.iter().step_by(2 * opts.reach() + 1) {
                    let yy = y as isize + dy;
                    if !(0..h as isize).contains(&yy) {
                        continue;
                    }
                    let k = yy as usize - source.start;
                    let (l, u) = (&lo[k * w..(k + 1) * w], &hi[k * w..(k + 1) * w]);
                    for (((rl, ru), &vl), &vu) in
                        range_lo.iter_mut().zip(range_hi.iter_mut()).zip(l).zip(u)
                    {
                        *rl = if vl < *rl { vl } else { *rl };
                        *ru = if vu > *ru { vu } else { *ru };
                    }
                }
                for (x, o) in out_row.iter_mut().enumerate() {
                    let i = y * w + x;
                    let (lo_x, hi_x) = (range_lo[x], range_hi[x]);
                    // The range is −∞ when the window has no valid pixel.
                    if hi_x - lo_x <= opts.jump || !logd[i].is_finite() {
                        continue;
                    }
                    let c = &rgb[3 * i..3 * i + 3];
                    samples.clear();
                    for &(dy, dx, space) in &opts.taps {
                        let yy = y as isize + dy;
                        if !(0..h as isize).contains(&yy) {
                            continue;
                        }
                        let xx = x as isize + dx;
                        // A division only across the seam.
                        let xx = if (0..w as isize).contains(&xx) {
                            xx
                        } else {
                            xx.rem_euclid(w as isize)
                        };
                        let j = yy as usize * w + xx as usize;
                        let (v, flat_j) = (logd[j], flat[j]);
                        // Samples inside a transition weigh (next to) nothing: skip them early.
                        if !v.is_finite() || flat_j < MIN_FLATNESS {
                            continue;
                        }
                        let q = &rgb[3 * j..3 * j + 3];
                        let d2: usize = (0..3)
                            .map(|k| (i32::from(c[k]) - i32::from(q[k])).pow(2) as usize)
                            .sum();
                        if d2 <= cut {
                            samples.push((v, space * opts.colour_weight[d2] * flat_j));
                        }
                    }
                    if let Some(v) = weighted_mode(samples, lo_x, hi_x) {
                        // A pixel outside any transition keeps its value: a smooth ramp is
                        // not cut into terraces.
                        let keep = flat[i];
                        *o = (keep * logd[i] + (1.0 - keep) * v).exp();
                    }
                }
            }
        },
    );
}

/// The weighted mean of the samples (value, weight) in the heaviest three adjacent bins of
/// [`BINS`] over [lo, hi]; None when they weigh nothing.
fn weighted_mode(samples: &[(f32, f32)], lo: f32, hi: f32) -> Option<f32> {
    let mut weight = [0.0f32; BINS];
    let mut moment = [0.0f32; BINS];
    let scale = BINS as f32 / (hi - lo);
    let bin = |v: f32| (((v - lo) * scale) as usize).min(BINS - 1);
    for &(v, wt) in samples {
        let b = bin(v);
        weight[b] += wt;
        moment[b] += wt * v;
    }
    let window = |b: usize| b.saturating_sub(1)..(b + 2).min(BINS);
    let mut best = 0;
    let mut best_weight = f32::NEG_INFINITY;
    for b in 0..BINS {
        let total: f32 = weight[window(b)].iter().sum();
        if total > best_weight {
            best_weight = total;
            best = b;
        }
    }
    let total: f32 = weight[window(best)].iter().sum();
    let sum: f32 = moment[window(best)].iter().sum();
    (total > 0.0).then(|| sum / total)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A vertical step (near on the left third) blurred by a box of `blur` pixels, and a
    /// photo with the sharp step in colour.
    fn blurred_step(h: usize, w: usize, blur: usize) -> (Vec<f32>, Vec<f32>, Vec<u8>) {
        let edge = w / 3;
        let truth: Vec<f32> = (0..h * w)
            .map(|i| if i % w < edge { 1.0 } else { 0.25 })
            .collect();
        let mut blurred = truth.clone();
        for y in 0..h {
            for x in 0..w {
                let mut s = 0.0;
                for k in 0..=2 * blur {
                    let xx = (x + w + k - blur) % w;
                    s += truth[y * w + xx];
                }
                blurred[y * w + x] = s / (2 * blur + 1) as f32;
            }
        }
        let rgb: Vec<u8> = truth
            .iter()
            .flat_map(|&t| {
                if t > 0.5 {
                    [200u8, 60, 40]
                } else {
                    [40, 90, 180]
                }
            })
            .collect();
        (truth, blurred, rgb)
    }

    #[test]
    fn a_blurred_step_is_made_sharp_where_the_photo_is() {
        let (h, w) = (24, 48);
        let (truth, blurred, rgb) = blurred_step(h, w, 3);
        let opts = EdgeRefine::new(8, 15.0, 0.1, 0.05).expect("valid options");
        let mut out = vec![0.0; h * w];
        refine_edges(&blurred, &rgb, (h, w), &opts, &mut out);
        let err = |m: &[f32]| -> f32 {
            m.iter()
                .zip(&truth)
                .map(|(a, b)| (a - b).abs() / b)
                .sum::<f32>()
                / (h * w) as f32
        };
        assert!(
            err(&blurred) > 0.05,
            "the blur must matter: {}",
            err(&blurred)
        );
        assert!(
            err(&out) < 0.01 * err(&blurred),
            "{} vs {}",
            err(&out),
            err(&blurred)
        );
    }

    #[test]
    fn flat_maps_invalid_pixels_and_a_grey_photo_far_from_jumps_are_kept() {
        let (h, w) = (16, 32);
        let ramp: Vec<f32> = (0..h * w).map(|i| 1.0 + 0.001 * (i % w) as f32).collect();
        let mut with_hole = ramp.clone();
        with_hole[5 * w + 7] = f32::NAN;
        with_hole[9 * w + 20] = -1.0;
        let rgb: Vec<u8> = (0..h * w * 3).map(|i| (i * 37 % 251) as u8).collect();
        let opts = EdgeRefine::new(4, 15.0, 0.1, 0.05).expect("valid options");
        let mut out = vec![0.0; h * w];
        refine_edges(&with_hole, &rgb, (h, w), &opts, &mut out);
        for (a, b) in out.iter().zip(&with_hole) {
            assert!(a.to_bits() == b.to_bits(), "{a} vs {b}");
        }
    }

    #[test]
    fn the_step_is_found_across_the_seam_and_large_radii_sample_sparsely() {
        let (h, w) = (30, 60);
        let (truth, blurred, rgb) = blurred_step(h, w, 2);
        // Roll by two thirds of a row: the step now straddles column 0 / w − 1.
        let roll = |v: &[f32]| -> Vec<f32> {
            (0..h * w)
                .map(|i| v[(i / w) * w + (i % w + 2 * w / 3) % w])
                .collect()
        };
        let rgb_rolled: Vec<u8> = (0..h * w)
            .flat_map(|i| {
                let j = (i / w) * w + (i % w + 2 * w / 3) % w;
                [rgb[3 * j], rgb[3 * j + 1], rgb[3 * j + 2]]
            })
            .collect();
        let (truth, blurred) = (roll(&truth), roll(&blurred));
        // Sampled every 2nd and every 3rd pixel.
        for radius in [6, 9] {
            let opts = EdgeRefine::new(radius, 15.0, 0.1, 0.05).expect("valid options");
            assert_eq!(opts.step(), radius.div_ceil(FULL_TAPS));
            let mut out = vec![0.0; h * w];
            refine_edges(&blurred, &rgb_rolled, (h, w), &opts, &mut out);
            let worst = out
                .iter()
                .zip(&truth)
                .map(|(a, b)| (a - b).abs() / b)
                .fold(0.0f32, f32::max);
            assert!(worst < 1e-3, "radius {radius}: worst {worst}");
        }
    }

    #[test]
    fn the_mode_is_the_heaviest_bin_triple_and_its_mean() {
        // Two clusters; the lighter one has more samples but less weight.
        let mut samples = vec![(0.0f32, 0.1f32); 10];
        samples.extend([(1.0, 2.0), (0.98, 2.0)]);
        let v = weighted_mode(&samples, 0.0, 1.0).expect("valid options");
        assert!((v - 0.99).abs() < 1e-6, "{v}");
        assert_eq!(weighted_mode(&[(0.5, 0.0)], 0.0, 1.0), None);
    }

    #[test]
    fn options_out_of_range_are_refused() {
        assert!(EdgeRefine::new(0, 15.0, 0.1, 0.05).is_err());
        assert!(EdgeRefine::new(MAX_RADIUS + 1, 15.0, 0.1, 0.05).is_err());
        assert!(EdgeRefine::new(4, 0.0, 0.1, 0.05).is_err());
        assert!(EdgeRefine::new(4, f64::NAN, 0.1, 0.05).is_err());
        assert!(EdgeRefine::new(4, 15.0, -1.0, 0.05).is_err());
        assert!(EdgeRefine::new(4, 15.0, 0.1, 0.0).is_err());
    }
}
