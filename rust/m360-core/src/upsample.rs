//! Upsampling an ERP map from a working resolution to the photo's: the guided filter's fit at
//! the working resolution ([`fit`]) and the full-resolution pass that evaluates it (or plain
//! NaN-aware bilinear interpolation) at every output pixel
//! (`m360.upsample.guided_upsample` describes the method).
//!
//! [`guided_upsample`] does both in one parallel loop over bands of output rows: each band fits
//! the few working rows it reads into a per-thread buffer and sweeps its output rows from there,
//! so nothing the size of the working map is allocated (fresh memory is slow to touch the first
//! time). The passes are separable, with exact (not 1/32-pixel) positions; timings in
//! benches/bench_upsample.py.

pub mod fit;

pub use fit::{fit_planes, GuidedFit, WorkingMaps};

use rayon::prelude::*;

/// Planes per working pixel of the bilinear pass: (valid value or 0, validity).
pub const BILINEAR_PLANES: usize = 2;
/// Planes per working pixel of the guided pass (see [`upsample`]).
pub const GUIDED_PLANES: usize = 7;

/// Bilinear positions of `n` output samples on a grid of `m` source samples, both covering the
/// same extent with centres at half-integers: (first index, fraction) per output sample.
fn positions(n: usize, m: usize, wrap: bool) -> Vec<(usize, usize, f32)> {
    let scale = m as f64 / n as f64;
    (0..n)
        .map(|k| {
            let x = (k as f64 + 0.5) * scale - 0.5;
            if wrap {
                let x0 = x.floor();
                let f = (x - x0) as f32;
                let a = (x0 as i64).rem_euclid(m as i64) as usize;
                (a, (a + 1) % m, f)
            } else {
                let x = x.clamp(0.0, (m - 1) as f64);
                let a = (x.floor() as usize).min(m - 1);
                let b = (a + 1).min(m - 1);
                (a, b, (x - a as f64) as f32)
            }
        })
        .collect()
}

/// Evaluate working-resolution planes at every pixel of an `out_h` × `out_w` ERP grid into
/// `out`: bilinear, half-pixel centred, wrapping in longitude, clamped at the pole rows.
///
/// `planes` is h × w × C interleaved. With C = [`BILINEAR_PLANES`] the planes are (p0, m) and
/// the value is p0/m. With C = [`GUIDED_PLANES`] they are (p0, m, e, a, b, lo, hi) and `grey`
/// (out_h × out_w, 0–255) is required: with I = grey/255 and the guided value
/// g = clamp(a·I + b, lo, hi), the value is p0/m + e·(g − p0/m), the bilinear value moved
/// towards the guided one by the edge weight e. The output is NaN where the interpolated
/// validity m is below ½.
///
/// # Panics
/// If the slice sizes do not match (the bindings check them first) or C is neither count.
#[allow(clippy::too_many_arguments)]
pub fn upsample(
    planes: &[f32],
    channels: usize,
    h: usize,
    w: usize,
    grey: Option<&[u8]>,
    out: &mut [f32],
    out_h: usize,
    out_w: usize,
) {
    assert!(channels == BILINEAR_PLANES || channels == GUIDED_PLANES);
    assert_eq!(planes.len(), h * w * channels, "planes size");
    assert_eq!(out.len(), out_h * out_w, "output size");
    if channels == GUIDED_PLANES {
        assert_eq!(grey.map(<[u8]>::len), Some(out_h * out_w), "guide size");
        sweep::<GUIDED_PLANES>(planes, w, grey, out, out_h, out_w, h);
    } else {
        sweep::<BILINEAR_PLANES>(planes, w, None, out, out_h, out_w, h);
    }
}

/// [`upsample`] with the plane count known at compile time (the per-channel loops unroll).
///
/// Separable: each output row first blends its two source rows into a row buffer (w·C lerps,
/// shared by the row's out_w pixels), then each pixel blends two neighbours of that buffer. The
/// guided channels are read only where the edge weight is not 0 (depth jumps are a small part
/// of a panorama), so most pixels cost two lerps.
#[allow(clippy::too_many_arguments)]
fn sweep<const C: usize>(
    planes: &[f32],
    w: usize,
    grey: Option<&[u8]>,
    out: &mut [f32],
    out_h: usize,
    out_w: usize,
    h: usize,
) {
    let cols = positions(out_w, w, true);
    let rows = positions(out_h, h, false);
    out.par_chunks_mut(out_w).enumerate().for_each_init(
        || vec![0.0f32; w * C],
        |blended, (i, out_row)| {
            let (y0, y1, fy) = rows[i];
            let top = &planes[y0 * w * C..(y0 + 1) * w * C];
            let bottom = &planes[y1 * w * C..(y1 + 1) * w * C];
            lerp_rows(top, bottom, fy, blended);
            let grey_row = grey.map(|g| &g[i * out_w..(i + 1) * out_w]);
            finish_row::<C>(blended, &cols, grey_row, out_row);
        },
    );
}

/// `blended` = `top` + `fy` · (`bottom` − `top`), element by element.
fn lerp_rows(top: &[f32], bottom: &[f32], fy: f32, blended: &mut [f32]) {
    for ((b, &t), &u) in blended.iter_mut().zip(top).zip(bottom) {
        *b = t + fy * (u - t);
    }
}

/// One output row from its vertically blended source row (w × C): bilinear along the row
/// (wrapping, `cols` from [`positions`]), then the value of [`upsample`]'s formula.
fn finish_row<const C: usize>(
    blended: &[f32],
    cols: &[(usize, usize, f32)],
    grey_row: Option<&[u8]>,
    out_row: &mut [f32],
) {
    for (j, (o, &(x0, x1, fx))) in out_row.iter_mut().zip(cols).enumerate() {
        let (left, right) = (&blended[x0 * C..x0 * C + C], &blended[x1 * C..x1 * C + C]);
        let at = |c: usize| left[c] + fx * (right[c] - left[c]);
        let validity = at(1);
        if validity < 0.5 {
            *o = f32::NAN;
            continue;
        }
        let mut value = at(0) / validity;
        if let Some(g) = grey_row {
            let edge = at(2);
            if edge > 0.0 {
                let level = f32::from(g[j]) * (1.0 / 255.0);
                let fitted = (at(3) * level + at(4)).clamp(at(5), at(6));
                value += edge * (fitted - value);
            }
        }
        *o = value;
    }
}

/// NaN-aware bilinear upsampling of an h × w map (NaN or ±inf = invalid) to `out`
/// (out_h × out_w): what [`upsample`] makes of the planes (p0, m), formed row by row from the
/// map instead of stored.
///
/// # Panics
/// If the slice sizes do not match (the bindings check them first).
pub fn bilinear_upsample(
    disparity: &[f32],
    (h, w): (usize, usize),
    out: &mut [f32],
    (out_h, out_w): (usize, usize),
) {
    assert_eq!(disparity.len(), h * w, "disparity size");
    assert_eq!(out.len(), out_h * out_w, "output size");
    let cols = positions(out_w, w, true);
    let rows = positions(out_h, h, false);
    let planes = |v: f32| if v.is_finite() { (v, 1.0) } else { (0.0, 0.0) };
    out.par_chunks_mut(out_w).enumerate().for_each_init(
        || vec![0.0f32; w * BILINEAR_PLANES],
        |blended, (i, out_row)| {
            let (y0, y1, fy) = rows[i];
            let top = &disparity[y0 * w..(y0 + 1) * w];
            let bottom = &disparity[y1 * w..(y1 + 1) * w];
            for ((b, &t), &u) in blended.chunks_exact_mut(2).zip(top).zip(bottom) {
                let ((tp, tm), (up, um)) = (planes(t), planes(u));
                b[0] = tp + fy * (up - tp);
                b[1] = tm + fy * (um - tm);
            }
            finish_row::<BILINEAR_PLANES>(blended, &cols, None, out_row);
        },
    );
}

/// Per-thread buffers of [`guided_upsample`]: the fit's, the band's planes, one blended row.
#[derive(Debug, Default)]
struct BandScratch {
    fit: fit::FitScratch,
    planes: Vec<f32>,
    blended: Vec<f32>,
}

/// Guided upsampling of the working maps to `out` (out_h × out_w): the planes of
/// [`fit_planes`] evaluated as [`upsample`] does with `grey_full` (out_h × out_w, 0–255), in
/// one parallel loop over bands of output rows, each fitting only the working rows it reads.
///
/// # Panics
/// If the slice sizes do not match (the bindings check them first).
pub fn guided_upsample(
    maps: WorkingMaps<'_>,
    fit: &GuidedFit,
    grey_full: &[u8],
    out: &mut [f32],
    (out_h, out_w): (usize, usize),
) {
    let (h, w) = (maps.h, maps.w);
    assert_eq!(maps.disparity.len(), h * w, "disparity size");
    assert_eq!(maps.grey.len(), h * w, "grey size");
    assert_eq!(grey_full.len(), out_h * out_w, "guide size");
    assert_eq!(out.len(), out_h * out_w, "output size");
    let cols = positions(out_w, w, true);
    let rows = positions(out_h, h, false);
    // Output rows per band: about fit::BAND_ROWS working rows each. Fixed by the sizes alone,
    // so the result does not depend on the number of threads.
    let band = (fit::BAND_ROWS * out_h).div_ceil(h).max(1);
    let scratch = fit::PerThread::<BandScratch>::new();
    out.par_chunks_mut(band * out_w)
        .enumerate()
        .for_each(|(k, chunk)| {
            let first = k * band;
            let out_rows = first..first + chunk.len() / out_w;
            // Source rows are nondecreasing in the output row, and y1 ≥ y0.
            let work_rows = rows[out_rows.start].0..rows[out_rows.end - 1].1 + 1;
            let mut guard = scratch.get();
            let BandScratch {
                fit: fit_scratch,
                planes,
                blended,
            } = &mut *guard;
            let stride = w * GUIDED_PLANES;
            planes.resize(work_rows.len() * stride, 0.0);
            blended.resize(stride, 0.0);
            fit::fit_band(maps, fit, work_rows.clone(), fit_scratch, planes);
            for (i, out_row) in out_rows.zip(chunk.chunks_exact_mut(out_w)) {
                let (y0, y1, fy) = rows[i];
                let (y0, y1) = (y0 - work_rows.start, y1 - work_rows.start);
                let top = &planes[y0 * stride..(y0 + 1) * stride];
                let bottom = &planes[y1 * stride..(y1 + 1) * stride];
                lerp_rows(top, bottom, fy, blended);
                let grey_row = &grey_full[i * out_w..(i + 1) * out_w];
                finish_row::<GUIDED_PLANES>(blended, &cols, Some(grey_row), out_row);
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Against a direct evaluation of the bilinear formula, wrapping at the seam.
    #[test]
    fn bilinear_matches_direct_evaluation_and_wraps() {
        let (h, w, out_h, out_w) = (4, 8, 12, 24);
        let value = |i: usize, j: usize| (1 + i * 8 + j) as f32;
        let mut planes = Vec::new();
        for i in 0..h {
            for j in 0..w {
                planes.extend([value(i, j), 1.0]);
            }
        }
        let mut out = vec![0.0; out_h * out_w];
        upsample(&planes, 2, h, w, None, &mut out, out_h, out_w);
        for (i, j) in [(0, 0), (5, 23), (11, 1), (6, 12)] {
            let y = ((i as f64 + 0.5) / 3.0 - 0.5).clamp(0.0, 3.0);
            let x = (j as f64 + 0.5) / 3.0 - 0.5;
            let (y0, x0) = (y.floor() as usize, x.floor());
            let (fy, fx) = (y - y0 as f64, x - x0);
            let y1 = (y0 + 1).min(3);
            let col = |k: f64| (k as i64).rem_euclid(8) as usize;
            let at = |r: usize, c: f64| f64::from(value(r, col(c)));
            let top = at(y0, x0) * (1.0 - fx) + at(y0, x0 + 1.0) * fx;
            let bottom = at(y1, x0) * (1.0 - fx) + at(y1, x0 + 1.0) * fx;
            let expected = top * (1.0 - fy) + bottom * fy;
            let got = f64::from(out[i * out_w + j]);
            assert!(
                (got - expected).abs() < 1e-4,
                "({i}, {j}): {got} vs {expected}"
            );
        }
    }

    /// The guided pass against the formula evaluated per pixel from four bilinear corners, on
    /// planes with edges on some pixels only (the pass skips the guided channels elsewhere).
    #[test]
    fn guided_matches_direct_evaluation() {
        let (h, w, out_h, out_w) = (5, 10, 13, 27);
        // A small deterministic generator: values in [0, 1).
        let mut state = 0x2545_f491_u32;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            (state >> 8) as f32 / (1u32 << 24) as f32
        };
        let mut planes = Vec::new();
        for k in 0..h * w {
            let p = 0.5 + next();
            let edge = if k % 3 == 0 { next() } else { 0.0 };
            let (lo, hi) = (p - 0.3, p + 0.3);
            planes.extend([p, 1.0, edge, 2.0 * next() - 1.0, next(), lo, hi]);
        }
        let grey: Vec<u8> = (0..out_h * out_w).map(|k| (k * 37 % 256) as u8).collect();
        let mut out = vec![0.0; out_h * out_w];
        upsample(&planes, 7, h, w, Some(&grey), &mut out, out_h, out_w);
        for i in 0..out_h {
            for j in 0..out_w {
                let y = ((i as f64 + 0.5) * h as f64 / out_h as f64 - 0.5).clamp(0.0, 4.0);
                let x = (j as f64 + 0.5) * w as f64 / out_w as f64 - 0.5;
                let (y0, x0) = (y.floor() as usize, x.floor());
                let (fy, fx) = (y - y0 as f64, x - x0);
                let y1 = (y0 + 1).min(h - 1);
                let col = |k: f64| (k as i64).rem_euclid(w as i64) as usize;
                let at = |r: usize, c: f64, ch: usize| f64::from(planes[(r * w + col(c)) * 7 + ch]);
                let v = |ch: usize| {
                    let top = at(y0, x0, ch) * (1.0 - fx) + at(y0, x0 + 1.0, ch) * fx;
                    let bottom = at(y1, x0, ch) * (1.0 - fx) + at(y1, x0 + 1.0, ch) * fx;
                    top * (1.0 - fy) + bottom * fy
                };
                let bilinear = v(0) / v(1);
                let level = f64::from(grey[i * out_w + j]) / 255.0;
                let fitted = (v(3) * level + v(4)).clamp(v(5), v(6));
                let expected = bilinear + v(2) * (fitted - bilinear);
                let got = f64::from(out[i * out_w + j]);
                assert!(
                    (got - expected).abs() < 1e-5,
                    "({i}, {j}): {got} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn invalid_where_validity_is_below_half() {
        // Same size: every output pixel is its own source pixel; odd columns are invalid.
        let row = [2.0, 1.0, 0.0, 0.0, 3.0, 1.0, 0.0, 0.0];
        let planes: Vec<f32> = row.iter().chain(&row).copied().collect();
        let mut out = vec![0.0; 8];
        upsample(&planes, 2, 2, 4, None, &mut out, 2, 4);
        assert_eq!((out[0], out[2], out[4]), (2.0, 3.0, 2.0));
        assert!(out[1].is_nan() && out[3].is_nan() && out[7].is_nan());
    }

    /// The fused pass equals the whole-map fit followed by the planes pass, and the bilinear
    /// pass from the map equals the planes pass on (p0, m), on maps with invalid pixels and
    /// output heights that split the bands unevenly.
    #[test]
    fn fused_passes_match_the_planes_pass() {
        let mut state = 0x1234_5679_u32;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            state
        };
        for (h, out_h) in [(6, 6), (9, 31), (40, 123), (70, 70)] {
            let w = 2 * h;
            let out_w = 2 * out_h;
            let disparity: Vec<f32> = (0..h * w)
                .map(|k| {
                    let v = next();
                    if v % 7 == 0 {
                        f32::NAN
                    } else {
                        // Steps, so that the edge weight is on in places.
                        1.0 + ((k % w) / 5 % 2) as f32 + (v >> 12) as f32 / (1u32 << 21) as f32
                    }
                })
                .collect();
            let grey: Vec<u8> = (0..h * w).map(|_| (next() >> 24) as u8).collect();
            let grey_full: Vec<u8> = (0..out_h * out_w).map(|_| (next() >> 24) as u8).collect();
            let maps = WorkingMaps {
                disparity: &disparity,
                grey: &grey,
                h,
                w,
            };
            let fit = GuidedFit::new(1, 1e-4, 0.05, 0.15, h).expect("valid fit");
            let mut planes = vec![0.0; h * w * GUIDED_PLANES];
            fit_planes(maps, &fit, &mut planes);
            assert!(planes.chunks_exact(7).any(|px| px[2] > 0.0));
            let (mut want, mut got) = (vec![0.0; out_h * out_w], vec![0.0; out_h * out_w]);
            upsample(&planes, 7, h, w, Some(&grey_full), &mut want, out_h, out_w);
            guided_upsample(maps, &fit, &grey_full, &mut got, (out_h, out_w));
            for (k, (g, e)) in got.iter().zip(&want).enumerate() {
                let same = (g.is_nan() && e.is_nan()) || (g - e).abs() <= 1e-6 * e.abs().max(1.0);
                assert!(same, "{h} -> {out_h}, pixel {k}: {g} vs {e}");
            }
            let two: Vec<f32> = planes
                .chunks_exact(7)
                .flat_map(|px| [px[0], px[1]])
                .collect();
            upsample(&two, 2, h, w, None, &mut want, out_h, out_w);
            bilinear_upsample(&disparity, (h, w), &mut got, (out_h, out_w));
            // The same arithmetic on the same values: bit for bit.
            for (g, e) in got.iter().zip(&want) {
                assert!(g.to_bits() == e.to_bits() || (g.is_nan() && e.is_nan()));
            }
        }
    }
}
