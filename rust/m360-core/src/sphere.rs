//! The equirectangular grid: pixel centres ↔ unit viewing directions (docs/conventions.md).
//!
//! Pixel (row i, column j) of an H×W ERP image has longitude λ = 2π(j+0.5)/W − π and latitude
//! φ = π/2 − π(i+0.5)/H; its direction is (cos φ sin λ, −sin φ, cos φ cos λ).

use nalgebra::Vector3;
use std::f64::consts::{FRAC_PI_2, PI};

/// Longitude of the centre of column `j` of a `width`-wide ERP image, in radians.
#[inline]
#[must_use]
pub fn column_longitude(j: f64, width: usize) -> f64 {
    2.0 * PI * (j + 0.5) / width as f64 - PI
}

/// Latitude of the centre of row `i` of a `height`-tall ERP image, in radians.
#[inline]
#[must_use]
pub fn row_latitude(i: f64, height: usize) -> f64 {
    FRAC_PI_2 - PI * (i + 0.5) / height as f64
}

/// Unit direction of longitude `lon` and latitude `lat`.
#[inline]
#[must_use]
pub fn lonlat_direction(lon: f64, lat: f64) -> Vector3<f64> {
    let (sl, cl) = lon.sin_cos();
    let (sp, cp) = lat.sin_cos();
    Vector3::new(cp * sl, -sp, cp * cl)
}

/// Continuous ERP pixel coordinates `(column, row)` of a (not necessarily unit) direction.
///
/// The column lies in [−0.5, W − 0.5) and the row in [−0.5, H − 0.5].
#[inline]
#[must_use]
pub fn direction_to_pixel(d: &Vector3<f64>, height: usize, width: usize) -> (f64, f64) {
    let lon = d.x.atan2(d.z);
    let lat = (-d.y).atan2((d.x * d.x + d.z * d.z).sqrt());
    let col = (lon + PI) * width as f64 / (2.0 * PI) - 0.5;
    let row = (FRAC_PI_2 - lat) * height as f64 / PI - 0.5;
    (col, row)
}

/// Per-row and per-column sines and cosines of an ERP grid, so directions cost no trigonometry.
#[derive(Debug, Clone)]
pub struct ErpGrid {
    /// Image height H.
    pub height: usize,
    /// Image width W.
    pub width: usize,
    sin_lat: Vec<f64>,
    cos_lat: Vec<f64>,
    sin_lon: Vec<f64>,
    cos_lon: Vec<f64>,
}

impl ErpGrid {
    /// Tables for an `height`×`width` ERP image.
    #[must_use]
    pub fn new(height: usize, width: usize) -> Self {
        let (sin_lat, cos_lat) = (0..height)
            .map(|i| row_latitude(i as f64, height).sin_cos())
            .unzip();
        let (sin_lon, cos_lon) = (0..width)
            .map(|j| column_longitude(j as f64, width).sin_cos())
            .unzip();
        Self {
            height,
            width,
            sin_lat,
            cos_lat,
            sin_lon,
            cos_lon,
        }
    }

    /// (sin, cos) of the latitude of row `i`.
    #[inline]
    #[must_use]
    pub fn row_sin_cos(&self, i: usize) -> (f64, f64) {
        (self.sin_lat[i], self.cos_lat[i])
    }

    /// (sin, cos) of the longitude of column `j`.
    #[inline]
    #[must_use]
    pub fn column_sin_cos(&self, j: usize) -> (f64, f64) {
        (self.sin_lon[j], self.cos_lon[j])
    }

    /// Unit direction of the centre of pixel (row `i`, column `j`).
    #[inline]
    #[must_use]
    pub fn direction(&self, i: usize, j: usize) -> Vector3<f64> {
        let cp = self.cos_lat[i];
        Vector3::new(cp * self.sin_lon[j], -self.sin_lat[i], cp * self.cos_lon[j])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centre_pixel_looks_forward_and_top_row_looks_up() {
        let g = ErpGrid::new(64, 128);
        // Between columns 63 and 64 lies longitude 0: their mean direction is +z.
        let d = (g.direction(31, 63) + g.direction(31, 64)).normalize();
        assert!((d.z - 1.0).abs() < 1e-3, "{d:?}");
        assert!(g.direction(0, 10).y < -0.99);
        assert!(g.direction(63, 10).y > 0.99);
    }

    #[test]
    fn pixel_direction_round_trip() {
        let (h, w) = (50, 100);
        let g = ErpGrid::new(h, w);
        for i in 0..h {
            for j in 0..w {
                let (c, r) = direction_to_pixel(&(g.direction(i, j) * 3.0), h, w);
                assert!((c - j as f64).abs() < 1e-9 && (r - i as f64).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn lonlat_matches_grid() {
        let g = ErpGrid::new(8, 16);
        let d = lonlat_direction(column_longitude(5.0, 16), row_latitude(2.0, 8));
        assert!((d - g.direction(2, 5)).norm() < 1e-12);
    }
}
