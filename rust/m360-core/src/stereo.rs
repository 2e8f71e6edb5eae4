//! Omnidirectional stereo (ODS): a left and a right eye ERP panorama from one panorama and its
//! radial depth, by forward warping.
//!
//! ODS model: the eye ray of ERP pixel (λ, φ) leaves from the point of the horizontal viewing
//! circle of radius r = IPD/2 where the ray, seen from above, is tangent to the circle:
//! origin s·r·e(λ) with e(λ) = (cos λ, 0, −sin λ) (local east), s = −1 for the left eye and +1
//! for the right, direction d(λ, φ) (docs/conventions.md). r fades to 0 towards the poles
//! ([`OdsOptions::radius_at`]), the usual remedy for ODS's pole distortion.
//!
//! A scene point P = D·d(λ, φ) of the centre panorama is seen by the eye at longitude
//! λ' = λ − asin(s·r/ρ) with ρ = D cos φ (the horizontal distance) and at latitude
//! φ' = atan2(D sin φ, √(ρ² − r²)) (`eye_latitude` evaluates it without an arctangent in
//! the usual case); since r depends on φ', that pair is found by a fixed-point
//! iteration (exact when r does not change, i.e. outside the fade). A point within the viewing
//! circle (ρ ≤ r) is seen by no eye ray.
//!
//! The warp treats the panorama as a mesh on its pixel grid (columns W − 1 and 0 are neighbours,
//! so it is continuous across the 0/360° seam): every grid triangle whose depths differ by at
//! most `max_depth_ratio` (a surface, not an occlusion edge) is rasterised into the eye's
//! panorama with a z-buffer (nearest wins; ties keep the first triangle in grid order), its
//! colour interpolated from its three pixels. A pixel without a valid depth (NaN, ≤ 0) is taken
//! as infinitely far: it keeps its place (no parallax) and lies behind everything. Eye pixels no
//! triangle covers may still get a single pixel that lies between two occlusion edges (a thin
//! structure), splatted there as a point. The pixels left are disocclusions (or pixels the
//! eye sees within the viewing circle): each
//! horizontal run of them is filled from the side whose depth is larger (the background), so a
//! foreground colour never spreads into a hole; a row without any covered pixel keeps the
//! centre view's row.
//!
//! Work is parallel over bands of eye rows; each band rasterises the triangles that reach it in
//! grid order, so the result is the same for any thread count.

use crate::error::{CoreError, Result};
use crate::sphere::{column_longitude, row_latitude};
use rayon::prelude::*;
use std::f64::consts::{FRAC_PI_2, PI, TAU};

/// Largest interpupillary distance accepted, in the depth's units (10 m: far beyond any eye, but
/// hyper-stereo of distant scenes uses more than a head's width).
pub const MAX_IPD: f64 = 10.0;
/// Default latitude (degrees) where the IPD starts fading to 0 at the poles.
pub const DEFAULT_POLE_FADE_DEG: f64 = 60.0;
/// Default depth ratio above which a grid triangle is an occlusion edge, not a surface.
pub const DEFAULT_MAX_DEPTH_RATIO: f64 = 1.1;
/// Eye rows per parallel band (a band also reads the grid rows one or two beyond its own).
const BAND_ROWS: usize = 32;
/// Tolerance (pixels) of the rasteriser's edge tests: pixel centres on a shared edge or vertex
/// belong to every triangle there (the z-buffer keeps one).
const EDGE_EPS: f64 = 1e-6;
/// Most fixed-point iterations of the eye latitude inside the pole fade (each one shrinks the
/// error by the fade's slope times r/ρ, far below 1; two or three usually settle it).
const FADE_ITERATIONS: usize = 6;

/// Which eye of an ODS pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Eye {
    /// Ray origins on the left of each viewing direction.
    Left,
    /// Ray origins on the right of each viewing direction.
    Right,
}

impl Eye {
    /// −1 for the left eye, +1 for the right one: the side of the origin along e(λ).
    #[must_use]
    pub fn sign(self) -> f64 {
        match self {
            Self::Left => -1.0,
            Self::Right => 1.0,
        }
    }
}

/// The options of the ODS warp, checked by [`OdsOptions::validate`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdsOptions {
    /// Interpupillary distance, in the depth's units (≥ 0, at most [`MAX_IPD`]).
    pub ipd: f64,
    /// Latitude (degrees, 0–90) where the IPD starts fading; it reaches 0 at the poles along a
    /// half cosine. 90: no fade.
    pub pole_fade_deg: f64,
    /// A grid triangle whose largest depth exceeds its smallest by more than this ratio is an
    /// occlusion edge and is not drawn (> 1).
    pub max_depth_ratio: f64,
}

impl Default for OdsOptions {
    fn default() -> Self {
        Self {
            ipd: 0.064,
            pole_fade_deg: DEFAULT_POLE_FADE_DEG,
            max_depth_ratio: DEFAULT_MAX_DEPTH_RATIO,
        }
    }
}

impl OdsOptions {
    /// Check every option's value.
    ///
    /// # Errors
    /// [`CoreError::InvalidOption`] naming the first option out of its range.
    pub fn validate(&self) -> Result<()> {
        if !(self.ipd.is_finite() && (0.0..=MAX_IPD).contains(&self.ipd)) {
            return Err(CoreError::option(
                "ipd",
                format!("must be in [0, {MAX_IPD}] (metres), got {}", self.ipd),
            ));
        }
        if !(self.pole_fade_deg.is_finite() && (0.0..=90.0).contains(&self.pole_fade_deg)) {
            return Err(CoreError::option(
                "pole_fade",
                format!(
                    "must be a latitude in [0, 90] degrees, got {}",
                    self.pole_fade_deg
                ),
            ));
        }
        if !(self.max_depth_ratio.is_finite() && self.max_depth_ratio > 1.0) {
            return Err(CoreError::option(
                "max_depth_ratio",
                format!("must be a finite ratio > 1, got {}", self.max_depth_ratio),
            ));
        }
        Ok(())
    }

    /// Radius of the viewing circle for eye rays at latitude `lat` (radians): IPD/2 up to
    /// `pole_fade_deg`, then fading along a half cosine to 0 at ±90°.
    #[must_use]
    pub fn radius_at(&self, lat: f64) -> f64 {
        let half = 0.5 * self.ipd;
        let start = self.pole_fade_deg.to_radians();
        let a = lat.abs();
        if a <= start {
            return half;
        }
        if start >= FRAC_PI_2 {
            return half;
        }
        let t = ((a - start) / (FRAC_PI_2 - start)).min(1.0);
        half * 0.5 * (1.0 + (PI * t).cos())
    }
}

/// Latitude of one grid row and its sine and cosine (computed once per row).
#[derive(Clone, Copy)]
struct RowAngle {
    lat: f64,
    sin: f64,
    cos: f64,
    /// The viewing circle's radius at this latitude.
    radius: f64,
}

/// Eye latitude of a point at latitude `row.lat` seen from `radius` off the centre, ρ its
/// horizontal distance: tan φ' = tan φ / √(1 − q²), q = r/ρ. Written as φ + atan(x) with
/// x = k·t / (1 + (1 + k)·t²), t = tan φ, k = 1/√(1 − q²) − 1 (atan(a) − atan(b) =
/// atan((a − b)/(1 + ab))): x is tiny for eyes a few centimetres apart, and a short series then
/// replaces the arctangent, the costliest step of the warp.
fn eye_latitude(row: RowAngle, q: f64) -> f64 {
    if q == 0.0 {
        return row.lat;
    }
    let k = 1.0 / (1.0 - q * q).sqrt() - 1.0;
    let t = row.sin / row.cos; // rows never reach the poles: cos > 0
    let x = k * t / (1.0 + (1.0 + k) * t * t);
    let delta = if x.abs() < 1e-2 {
        let x2 = x * x;
        x * (1.0 - x2 * (1.0 / 3.0 - x2 / 5.0)) // error below x⁷/7 < 2e-15
    } else {
        x.atan()
    };
    row.lat + delta
}

#[allow(clippy::too_many_arguments)]
/// Where one centre pixel lands in an eye's panorama: continuous (column, row), NaN column when
/// no eye ray sees it.
fn eye_position(
    depth: f32,
    row: RowAngle,
    lon: f64,
    opts: &OdsOptions,
    sign: f64,
    height: usize,
    width: usize,
    identity: (f64, f64),
) -> (f32, f32) {
    if !(depth.is_finite() && depth > 0.0) {
        return (identity.0 as f32, identity.1 as f32); // at infinity: no parallax
    }
    let rho = f64::from(depth) * row.cos;
    let mut eye_lat = row.lat;
    let mut radius = row.radius;
    let mut eye_lon = lon;
    for _ in 0..FADE_ITERATIONS {
        if radius >= rho {
            return (f32::NAN, f32::NAN);
        }
        let q = radius / rho;
        eye_lon = if q == 0.0 {
            lon
        } else {
            lon - (sign * q).asin()
        };
        eye_lat = eye_latitude(row, q);
        let next = opts.radius_at(eye_lat);
        // Settled once the radius moves by less than a nanometre per metre of IPD (outside the
        // fade it does not move at all): the eye direction then changes by < 1e-9 rad.
        if (next - radius).abs() <= 1e-9 * opts.ipd {
            break;
        }
        radius = next;
    }
    let col = (eye_lon + PI) * width as f64 / TAU - 0.5;
    let row = (FRAC_PI_2 - eye_lat) * height as f64 / PI - 0.5;
    (col as f32, row as f32)
}

/// ⌊v⌋ for pixel coordinates (|v| far below 2^53), without the libm call `f64::floor` makes on
/// targets without SSE4.1: the rasteriser takes several per triangle.
#[inline]
fn floor(v: f64) -> f64 {
    let t = v as i64 as f64;
    if t > v {
        t - 1.0
    } else {
        t
    }
}

/// ⌈v⌉, as [`floor`].
#[inline]
fn ceil(v: f64) -> f64 {
    let t = v as i64 as f64;
    if t < v {
        t + 1.0
    } else {
        t
    }
}

/// One vertex of the warp mesh: eye position, depth (∞ for none) and the centre pixel whose
/// colour it carries.
#[derive(Clone, Copy)]
struct Vertex {
    x: f64,
    y: f64,
    z: f32,
    pixel: usize,
}

/// The centre map and its eye positions, read by the rasteriser.
struct Warp<'a> {
    rgb: &'a [u8],
    depth: &'a [f32],
    positions: &'a [(f32, f32)],
    height: usize,
    width: usize,
    max_depth_ratio: f32,
}

impl Warp<'_> {
    /// Vertex of grid row `i` (−1 and H are copies of the pole rows one row further out, so the
    /// first and last eye rows are covered) and column `j` (wrapping); None when unseen.
    fn vertex(&self, i: isize, j: usize) -> Option<Vertex> {
        let (row, dy) = if i < 0 {
            (0, -1.0)
        } else if i as usize >= self.height {
            (self.height - 1, 1.0)
        } else {
            (i as usize, 0.0)
        };
        let pixel = row * self.width + j % self.width;
        let (x, y) = self.positions[pixel];
        if x.is_nan() {
            return None;
        }
        let d = self.depth[pixel];
        let z = if d.is_finite() && d > 0.0 {
            d
        } else {
            f32::INFINITY
        };
        Some(Vertex {
            x: f64::from(x),
            y: f64::from(y) + dy,
            z,
            pixel,
        })
    }

    /// Whether three depths lie on one surface (all at infinity, or within the ratio).
    fn continuous(&self, z: [f32; 3]) -> bool {
        let lo = z[0].min(z[1]).min(z[2]);
        let hi = z[0].max(z[1]).max(z[2]);
        if hi.is_infinite() {
            return lo.is_infinite();
        }
        hi <= self.max_depth_ratio * lo
    }
}

/// One band of eye rows being drawn: colours, z-buffer and coverage.
struct Band<'a> {
    first_row: usize,
    rows: usize,
    width: usize,
    channels: usize,
    rgb: &'a mut [u8],
    z: Vec<f32>,
    covered: Vec<bool>,
    /// Whether a triangle (not only a point) covers the pixel.
    by_triangle: Vec<bool>,
}

impl Band<'_> {
    /// Rasterise one triangle into the band (z-test, colour interpolated from its pixels).
    fn draw(&mut self, warp: &Warp<'_>, v: [Vertex; 3]) {
        // The cheap test first: most triangles a band reads miss its rows.
        let ys = [v[0].y, v[1].y, v[2].y];
        let (y_lo, y_hi) = (ys[0].min(ys[1]).min(ys[2]), ys[0].max(ys[1]).max(ys[2]));
        let first = self.first_row as f64;
        let last = (self.first_row + self.rows - 1) as f64;
        let row_lo = ceil(y_lo - EDGE_EPS).max(first);
        let row_hi = floor(y_hi + EDGE_EPS).min(last);
        if row_lo > row_hi {
            return;
        }
        let w = self.width as f64;
        // Unwrap the longitudes around the first vertex so the triangle is not cut at the seam.
        let unwrap = |x: f64| {
            let dx = x - v[0].x;
            if dx.abs() <= 0.5 * w {
                x // the usual case: no division
            } else {
                x - w * (dx / w).round()
            }
        };
        let xs = [v[0].x, unwrap(v[1].x), unwrap(v[2].x)];
        let area = (xs[1] - xs[0]) * (ys[2] - ys[0]) - (xs[2] - xs[0]) * (ys[1] - ys[0]);
        if area.abs() < 1e-12 {
            return;
        }
        let (x_lo, x_hi) = (xs[0].min(xs[1]).min(xs[2]), xs[0].max(xs[1]).max(xs[2]));
        if x_hi - x_lo > 0.5 * w {
            return; // wraps round a pole: not a surface patch of the eye's view
        }
        let col_lo = ceil(x_lo - EDGE_EPS) as i64;
        let col_hi = floor(x_hi + EDGE_EPS) as i64;
        let inv = 1.0 / area;
        let all_far = v.iter().all(|p| p.z.is_infinite());
        let c = self.channels;
        let mut py = row_lo;
        while py <= row_hi {
            let band_row = py as usize - self.first_row;
            for px in col_lo..=col_hi {
                let x = px as f64;
                // Barycentric weights of the pixel centre (x, py).
                let b0 = ((xs[1] - x) * (ys[2] - py) - (xs[2] - x) * (ys[1] - py)) * inv;
                let b1 = ((xs[2] - x) * (ys[0] - py) - (xs[0] - x) * (ys[2] - py)) * inv;
                let b2 = 1.0 - b0 - b1;
                if b0 < -EDGE_EPS || b1 < -EDGE_EPS || b2 < -EDGE_EPS {
                    continue;
                }
                let z = if all_far {
                    f32::INFINITY
                } else {
                    (b0 * f64::from(v[0].z) + b1 * f64::from(v[1].z) + b2 * f64::from(v[2].z))
                        as f32
                };
                let col = px.rem_euclid(self.width as i64) as usize;
                let at = band_row * self.width + col;
                if self.covered[at] && z >= self.z[at] {
                    continue;
                }
                self.covered[at] = true;
                self.by_triangle[at] = true;
                self.z[at] = z;
                for k in 0..c {
                    let value = b0 * f64::from(warp.rgb[v[0].pixel * c + k])
                        + b1 * f64::from(warp.rgb[v[1].pixel * c + k])
                        + b2 * f64::from(warp.rgb[v[2].pixel * c + k]);
                    self.rgb[at * c + k] = (value + 0.5).clamp(0.0, 255.0) as u8;
                    // rounded
                }
            }
            py += 1.0;
        }
    }

    /// Splat one vertex onto its nearest eye pixel if no triangle covers that pixel (z-test
    /// among the points).
    fn point(&mut self, warp: &Warp<'_>, v: Vertex) {
        let row = floor(v.y + 0.5);
        if row < self.first_row as f64 || row > (self.first_row + self.rows - 1) as f64 {
            return;
        }
        let col = (floor(v.x + 0.5) as i64).rem_euclid(self.width as i64) as usize;
        let at = (row as usize - self.first_row) * self.width + col;
        if self.covered[at] && (self.by_triangle[at] || v.z >= self.z[at]) {
            return;
        }
        self.covered[at] = true;
        self.z[at] = v.z;
        let c = self.channels;
        self.rgb[at * c..(at + 1) * c].copy_from_slice(&warp.rgb[v.pixel * c..(v.pixel + 1) * c]);
    }

    /// Fill the uncovered pixels of every band row from their background side; returns the
    /// number filled and marks them in `holes`.
    fn fill(&mut self, centre: &[u8], holes: &mut [bool]) -> usize {
        let (w, c) = (self.width, self.channels);
        let mut filled = 0;
        for r in 0..self.rows {
            let row = r * w;
            let covered = &self.covered[row..row + w];
            let Some(start) = covered.iter().position(|&k| k) else {
                // No eye ray of this row was drawn: keep the centre view's row.
                let src = (self.first_row + r) * w * c;
                self.rgb[row * c..(row + w) * c].copy_from_slice(&centre[src..src + w * c]);
                holes[row..row + w].fill(true);
                filled += w;
                continue;
            };
            // Walk once round the row from a covered pixel; each uncovered run lies between its
            // left neighbour and its right neighbour (cyclically).
            let mut k = 1;
            while k < w {
                let at = (start + k) % w;
                if self.covered[row + at] {
                    k += 1;
                    continue;
                }
                let left = (start + k - 1) % w;
                let mut n = 0;
                while !self.covered[row + (at + n) % w] {
                    n += 1;
                }
                let right = (at + n) % w;
                let from = if self.z[row + right] > self.z[row + left] {
                    right
                } else {
                    left
                };
                for m in 0..n {
                    let dst = row + (at + m) % w;
                    self.rgb
                        .copy_within((row + from) * c..(row + from + 1) * c, dst * c);
                    self.z[dst] = self.z[row + from];
                    holes[dst] = true;
                }
                filled += n;
                k += n;
            }
        }
        filled
    }
}

/// Eye position of every centre pixel (see [`eye_position`]), parallel over rows.
fn eye_positions(
    depth: &[f32],
    height: usize,
    width: usize,
    opts: &OdsOptions,
    eye: Eye,
) -> Vec<(f32, f32)> {
    let sign = eye.sign();
    let mut positions = vec![(0.0_f32, 0.0_f32); height * width];
    positions
        .par_chunks_mut(width)
        .zip(depth.par_chunks(width))
        .enumerate()
        .for_each(|(i, (row, d))| {
            let lat = row_latitude(i as f64, height);
            let (sin, cos) = lat.sin_cos();
            let angle = RowAngle {
                lat,
                sin,
                cos,
                radius: opts.radius_at(lat),
            };
            for (j, (p, &z)) in row.iter_mut().zip(d).enumerate() {
                let lon = column_longitude(j as f64, width);
                *p = eye_position(
                    z,
                    angle,
                    lon,
                    opts,
                    sign,
                    height,
                    width,
                    (j as f64, i as f64),
                );
            }
        });
    positions
}

/// Eye rows (lowest, highest) each pair of grid rows (i, i + 1), i = −1 … H − 1, reaches.
fn pair_rows(positions: &[(f32, f32)], height: usize, width: usize) -> Vec<(f64, f64)> {
    (-1..height as isize)
        .into_par_iter()
        .map(|i| {
            let mut lo = f64::INFINITY;
            let mut hi = f64::NEG_INFINITY;
            for r in [i, i + 1] {
                let (row, dy) = if r < 0 {
                    (0, -1.0)
                } else if r as usize >= height {
                    (height - 1, 1.0)
                } else {
                    (r as usize, 0.0)
                };
                for &(x, y) in &positions[row * width..(row + 1) * width] {
                    if !x.is_nan() {
                        lo = lo.min(f64::from(y) + dy);
                        hi = hi.max(f64::from(y) + dy);
                    }
                }
            }
            (lo, hi)
        })
        .collect()
}

/// Warp one eye: `rgb` (H × W × C, uint8) and its radial `depth` (H × W; NaN or ≤ 0 = at
/// infinity) into the eye's panorama `out` (H × W × C), marking in `holes` (H × W) the pixels
/// filled rather than seen; returns how many were filled.
///
/// # Errors
/// [`CoreError::InvalidOption`] for options out of range.
///
/// # Panics
/// If the slice sizes do not match H, W and C (the bindings check them first).
#[allow(clippy::too_many_arguments)]
pub fn ods_eye(
    rgb: &[u8],
    channels: usize,
    depth: &[f32],
    height: usize,
    width: usize,
    opts: &OdsOptions,
    eye: Eye,
    out: &mut [u8],
    holes: &mut [bool],
) -> Result<usize> {
    opts.validate()?;
    let pixels = height * width;
    assert!(
        rgb.len() == pixels * channels
            && depth.len() == pixels
            && out.len() == pixels * channels
            && holes.len() == pixels,
        "ods_eye: slice sizes do not match {height}x{width}x{channels}"
    );
    if pixels == 0 {
        return Ok(0);
    }
    let positions = eye_positions(depth, height, width, opts, eye);
    let pair_rows = pair_rows(&positions, height, width);
    let warp = Warp {
        rgb,
        depth,
        positions: &positions,
        height,
        width,
        max_depth_ratio: opts.max_depth_ratio as f32,
    };
    let filled = out
        .par_chunks_mut(BAND_ROWS * width * channels)
        .zip(holes.par_chunks_mut(BAND_ROWS * width))
        .enumerate()
        .map(|(b, (out_band, holes_band))| {
            let rows = holes_band.len() / width;
            let mut band = Band {
                first_row: b * BAND_ROWS,
                rows,
                width,
                channels,
                rgb: out_band,
                z: vec![f32::INFINITY; rows * width],
                covered: vec![false; rows * width],
                by_triangle: vec![false; rows * width],
            };
            holes_band.fill(false);
            let (top, bottom) = (band.first_row as f64, (band.first_row + rows - 1) as f64);
            for (p, &(lo, hi)) in pair_rows.iter().enumerate() {
                if hi < top - 1.0 || lo > bottom + 1.0 {
                    continue;
                }
                let i = p as isize - 1;
                // The right column of one quad is the left column of the next.
                let (mut top_left, mut bottom_left) = (warp.vertex(i, 0), warp.vertex(i + 1, 0));
                for j in 0..width {
                    let (top_right, bottom_right) =
                        (warp.vertex(i, j + 1), warp.vertex(i + 1, j + 1));
                    let quad = [top_left, top_right, bottom_left, bottom_right];
                    (top_left, bottom_left) = (top_right, bottom_right);
                    for tri in [[0, 1, 2], [1, 3, 2]] {
                        if let (Some(a), Some(b), Some(c)) =
                            (quad[tri[0]], quad[tri[1]], quad[tri[2]])
                        {
                            if warp.continuous([a.z, b.z, c.z]) {
                                band.draw(&warp, [a, b, c]);
                            }
                        }
                    }
                }
            }
            // Pixels no triangle covers may still be seen: single pixels between occlusion
            // edges (thin structures) land there as points, the nearest kept.
            let all_covered = band.covered.iter().all(|&k| k);
            for (p, &(lo, hi)) in pair_rows.iter().enumerate() {
                if all_covered || p == 0 || hi < top - 1.0 || lo > bottom + 1.0 {
                    continue;
                }
                for j in 0..width {
                    if let Some(v) = warp.vertex(p as isize - 1, j) {
                        band.point(&warp, v);
                    }
                }
            }
            band.fill(rgb, holes_band)
        })
        .sum();
    Ok(filled)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sphere::{direction_to_pixel, lonlat_direction};
    use nalgebra::Vector3;

    /// A smooth periodic test pattern of continuous pixel coordinates (column, row).
    fn pattern(col: f64, row: f64, width: usize, height: usize, k: usize) -> f64 {
        let lon = TAU * (col + 0.5) / width as f64;
        let lat = PI * (row + 0.5) / height as f64;
        let v = 127.5
            + 60.0 * (3.0 * lon + 0.4 * k as f64).sin()
            + 50.0 * (2.0 * lat).cos() * (lon + k as f64).cos();
        v.clamp(0.0, 255.0)
    }

    fn image(height: usize, width: usize) -> Vec<u8> {
        let mut rgb = vec![0; height * width * 3];
        for i in 0..height {
            for j in 0..width {
                for k in 0..3 {
                    rgb[(i * width + j) * 3 + k] =
                        pattern(j as f64, i as f64, width, height, k).round() as u8;
                }
            }
        }
        rgb
    }

    fn warp(
        rgb: &[u8],
        depth: &[f32],
        h: usize,
        w: usize,
        opts: &OdsOptions,
        eye: Eye,
    ) -> (Vec<u8>, Vec<bool>, usize) {
        let mut out = vec![0; rgb.len()];
        let mut holes = vec![false; depth.len()];
        let n = ods_eye(rgb, 3, depth, h, w, opts, eye, &mut out, &mut holes).expect("valid");
        (out, holes, n)
    }

    #[test]
    fn zero_ipd_gives_the_input_back() {
        let (h, w) = (32, 64);
        let rgb = image(h, w);
        let depth: Vec<f32> = (0..h * w).map(|p| 1.0 + (p % 7) as f32 * 0.3).collect();
        let opts = OdsOptions {
            ipd: 0.0,
            ..OdsOptions::default()
        };
        for eye in [Eye::Left, Eye::Right] {
            let (out, holes, n) = warp(&rgb, &depth, h, w, &opts, eye);
            assert_eq!(n, 0);
            assert!(holes.iter().all(|&x| !x));
            assert_eq!(out, rgb);
        }
    }

    /// On a sphere of radius D around the centre, each eye pixel's ray (from its origin on the
    /// viewing circle) hits the point whose centre pixel is known in closed form: the warped
    /// colours must be the pattern there.
    #[test]
    fn constant_depth_matches_ray_traced_eyes() {
        let (h, w) = (64, 128);
        let rgb = image(h, w);
        let d = 0.5_f32;
        let depth = vec![d; h * w];
        let opts = OdsOptions {
            ipd: 0.2,
            pole_fade_deg: 45.0,
            ..OdsOptions::default()
        };
        for eye in [Eye::Left, Eye::Right] {
            let (out, holes, _) = warp(&rgb, &depth, h, w, &opts, eye);
            let mut worst: f64 = 0.0;
            let mut checked = 0;
            for i in 2..h - 2 {
                let lat = row_latitude(i as f64, h);
                let r = opts.radius_at(lat);
                for j in 0..w {
                    if holes[i * w + j] {
                        continue;
                    }
                    let lon = column_longitude(j as f64, w);
                    let east = Vector3::new(lon.cos(), 0.0, -lon.sin());
                    let origin = east * (eye.sign() * r);
                    let dir = lonlat_direction(lon, lat);
                    let t = (f64::from(d).powi(2) - r * r).sqrt(); // origin ⊥ dir
                    let hit = origin + dir * t;
                    let (col, row) = direction_to_pixel(&hit, h, w);
                    for k in 0..3 {
                        let want = pattern(col, row, w, h, k);
                        let got = f64::from(out[(i * w + j) * 3 + k]);
                        worst = worst.max((want - got).abs());
                    }
                    checked += 1;
                }
            }
            assert!(checked > h * w * 3 / 4, "only {checked} pixels seen");
            // Linear interpolation of a smooth pattern on a 2.8° grid, and uint8 rounding.
            assert!(worst < 4.0, "{eye:?}: largest colour error {worst}");
        }
    }

    /// A near vertical band in front of a far wall: the eye sees round it, the disoccluded
    /// pixels are filled with the wall's colour, never the band's.
    #[test]
    fn disocclusions_are_filled_from_the_background() {
        let (h, w) = (32, 128);
        let mut rgb = vec![0_u8; h * w * 3];
        let mut depth = vec![4.0_f32; h * w];
        for i in 0..h {
            for j in 0..w {
                let near = (60..68).contains(&j);
                let p = i * w + j;
                rgb[p * 3..p * 3 + 3].copy_from_slice(if near {
                    &[250, 0, 0]
                } else {
                    &[0, 0, 200]
                });
                if near {
                    depth[p] = 0.4;
                }
            }
        }
        let opts = OdsOptions {
            ipd: 0.2,
            ..OdsOptions::default()
        };
        for eye in [Eye::Left, Eye::Right] {
            let (out, holes, n) = warp(&rgb, &depth, h, w, &opts, eye);
            assert!(n > 0, "{eye:?}: no disocclusion");
            let i = h / 2;
            let row_holes: Vec<usize> = (0..w).filter(|&j| holes[i * w + j]).collect();
            assert!(!row_holes.is_empty());
            for &j in &row_holes {
                assert_eq!(&out[(i * w + j) * 3..(i * w + j) * 3 + 3], &[0, 0, 200]);
            }
            // The left eye sees the near band shifted right (λ' = λ + asin(r/ρ)), so the hole
            // opens on its left side; the right eye the other way round.
            let band: Vec<usize> = (0..w).filter(|&j| out[(i * w + j) * 3] == 250).collect();
            let band_mid = band.iter().sum::<usize>() as f64 / band.len() as f64;
            let hole_mid = row_holes.iter().sum::<usize>() as f64 / row_holes.len() as f64;
            match eye {
                Eye::Left => assert!(band_mid > 64.0 && hole_mid < band_mid),
                Eye::Right => assert!(band_mid < 64.0 && hole_mid > band_mid),
            }
        }
    }

    #[test]
    fn rolling_the_input_rolls_the_eyes_and_threads_do_not_matter() {
        let (h, w) = (32, 64);
        let rgb = image(h, w);
        let depth: Vec<f32> = (0..h * w)
            .map(|p| {
                let j = p % w;
                if p % 97 == 0 {
                    f32::NAN
                } else if (20..30).contains(&j) {
                    0.6
                } else {
                    2.0 + (j as f32 * 0.1).sin()
                }
            })
            .collect();
        let opts = OdsOptions {
            ipd: 0.15,
            ..OdsOptions::default()
        };
        let shift = 17;
        let roll = |v: &[u8], c: usize| -> Vec<u8> {
            let mut r = vec![0; v.len()];
            for i in 0..h {
                for j in 0..w {
                    let (a, b) = ((i * w + j) * c, (i * w + (j + shift) % w) * c);
                    r[b..b + c].copy_from_slice(&v[a..a + c]);
                }
            }
            r
        };
        let depth_bytes: Vec<[u8; 4]> = depth.iter().map(|z| z.to_le_bytes()).collect();
        let rolled_depth: Vec<f32> = roll(&depth_bytes.concat(), 4)
            .chunks(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        let (out, _, _) = warp(&rgb, &depth, h, w, &opts, Eye::Left);
        let (rolled, _, _) = warp(&roll(&rgb, 3), &rolled_depth, h, w, &opts, Eye::Left);
        let expected = roll(&out, 3);
        let differ = rolled
            .iter()
            .zip(&expected)
            .filter(|(a, b)| a.abs_diff(**b) > 1)
            .count();
        assert!(
            differ * 200 < rolled.len(),
            "{differ} values differ after a roll"
        );
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool");
            let again = pool.install(|| warp(&rgb, &depth, h, w, &opts, Eye::Left));
            assert_eq!(again.0, out);
        }
    }

    #[test]
    fn eye_latitude_is_the_arctangent() {
        for i in 0..200 {
            let lat = -1.55 + 3.1 * f64::from(i) / 199.0;
            let (sin, cos) = lat.sin_cos();
            for q in [0.0, 1e-6, 1e-3, 0.03, 0.3, 0.9, 0.999] {
                let d = 1.0;
                let rho = d * cos;
                let r = q * rho;
                let exact = (d * sin).atan2((rho * rho - r * r).sqrt());
                let row = RowAngle {
                    lat,
                    sin,
                    cos,
                    radius: 0.0,
                };
                let got = eye_latitude(row, q);
                assert!(
                    (got - exact).abs() < 1e-12,
                    "lat {lat} q {q}: {got} vs {exact}"
                );
            }
        }
    }

    #[test]
    fn options_are_checked() {
        let bad = [
            OdsOptions {
                ipd: -0.1,
                ..OdsOptions::default()
            },
            OdsOptions {
                ipd: f64::NAN,
                ..OdsOptions::default()
            },
            OdsOptions {
                pole_fade_deg: 91.0,
                ..OdsOptions::default()
            },
            OdsOptions {
                max_depth_ratio: 1.0,
                ..OdsOptions::default()
            },
        ];
        for opts in bad {
            assert!(matches!(
                opts.validate(),
                Err(CoreError::InvalidOption { .. })
            ));
        }
        let opts = OdsOptions::default();
        assert!((opts.radius_at(0.0) - 0.032).abs() < 1e-15);
        assert!(opts.radius_at(FRAC_PI_2).abs() < 1e-15);
        assert!(opts.radius_at(75_f64.to_radians()) < 0.032);
    }
}
