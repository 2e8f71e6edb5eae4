//! Pinhole tangent cameras: world direction ↔ tangent pixel (docs/conventions.md, "Tangent cameras").

use nalgebra::{Matrix3, Vector3};

/// A pinhole camera on the unit sphere.
///
/// A world direction `d` has camera coordinates `X = rotation · d`; it is visible when `X.z > 0`,
/// at pixel position `x = fx·X.x/X.z + cx`, `y = fy·X.y/X.z + cy`. Pixel (row r, column c) has its
/// centre at (x = c, y = r) and covers [c − ½, c + ½] × [r − ½, r + ½].
#[derive(Debug, Clone, PartialEq)]
pub struct TangentCamera {
    /// World → camera rotation (rows: camera x, y, z axes in world coordinates).
    pub rotation: Matrix3<f64>,
    /// Horizontal focal length in pixels.
    pub fx: f64,
    /// Vertical focal length in pixels.
    pub fy: f64,
    /// Column of the principal point (where the optical axis meets the image).
    pub cx: f64,
    /// Row of the principal point.
    pub cy: f64,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
}

impl TangentCamera {
    /// World direction of the optical axis.
    #[inline]
    #[must_use]
    pub fn axis(&self) -> Vector3<f64> {
        self.rotation.row(2).transpose()
    }

    /// Continuous pixel position `(x, y)` of a world direction, or `None` behind the camera.
    #[inline]
    #[must_use]
    pub fn project(&self, d: &Vector3<f64>) -> Option<(f64, f64)> {
        let p = self.rotation * d;
        (p.z > 0.0).then(|| {
            let inv_z = 1.0 / p.z;
            (
                self.fx * p.x * inv_z + self.cx,
                self.fy * p.y * inv_z + self.cy,
            )
        })
    }

    /// Whether a continuous pixel position lies on the image (pixel areas included).
    #[inline]
    #[must_use]
    pub fn contains(&self, x: f64, y: f64) -> bool {
        x >= -0.5 && x <= self.width as f64 - 0.5 && y >= -0.5 && y <= self.height as f64 - 0.5
    }

    /// Gnomonic (tangent-plane) coordinates of a pixel position.
    #[inline]
    #[must_use]
    pub fn gnomonic(&self, x: f64, y: f64) -> (f64, f64) {
        ((x - self.cx) / self.fx, (y - self.cy) / self.fy)
    }

    /// `1/|q|` for the pixel ray `q = (gx, gy, 1)`: the factor from perspective disparity (1/z)
    /// to spherical disparity (1/distance) at that pixel.
    #[inline]
    #[must_use]
    pub fn spherical_factor(&self, x: f64, y: f64) -> f64 {
        let (gx, gy) = self.gnomonic(x, y);
        1.0 / (1.0 + gx * gx + gy * gy).sqrt()
    }

    /// Unit world direction of a pixel position.
    #[inline]
    #[must_use]
    pub fn pixel_direction(&self, x: f64, y: f64) -> Vector3<f64> {
        let (gx, gy) = self.gnomonic(x, y);
        (self.rotation.transpose() * Vector3::new(gx, gy, 1.0)).normalize()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> TangentCamera {
        let rotation = nalgebra::Rotation3::from_euler_angles(0.3, -0.7, 0.2).into_inner();
        TangentCamera {
            rotation,
            fx: 100.0,
            fy: 90.0,
            cx: 49.5,
            cy: 30.0,
            width: 100,
            height: 80,
        }
    }

    #[test]
    fn project_inverts_pixel_direction() {
        let cam = camera();
        for &(x, y) in &[(0.0, 0.0), (49.5, 30.0), (99.0, 79.0), (-3.0, 120.0)] {
            let d = cam.pixel_direction(x, y);
            let (px, py) = cam.project(&d).expect("in front");
            assert!((px - x).abs() < 1e-9 && (py - y).abs() < 1e-9);
        }
        assert!(cam.project(&-cam.axis()).is_none());
    }

    #[test]
    fn spherical_factor_is_cosine_to_axis() {
        let cam = camera();
        let d = cam.pixel_direction(7.0, 66.0);
        assert!((cam.spherical_factor(7.0, 66.0) - d.dot(&cam.axis())).abs() < 1e-12);
    }
}
