//! Per-face blending weights on each tangent's own pixel grid (paper §3.4), computed from that
//! face's own intrinsics and sampled at an ERP pixel with the same bilinear tap as the disparity.

use crate::camera::TangentCamera;
use crate::layout::Layout;
use crate::options::choice;
use crate::resample::{ErpTaps, Sampling};
use rayon::prelude::*;

/// Radial weights are 1 up to this angle from the optical axis (degrees).
pub const RADIAL_FULL_DEG: f64 = 15.0;
/// Frustum weights reach 1 this fraction of the way along each diagonal from a corner (so the
/// ramp is `FRUSTUM_RAMP`·width wide horizontally and `FRUSTUM_RAMP`·height vertically).
pub const FRUSTUM_RAMP: f64 = 0.3;

/// Which per-face weight map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Weighting {
    /// 1 where this face's axis is the nearest axis to the pixel's ray (for the icosahedron: the
    /// un-padded face triangle), 0 elsewhere.
    Nearest,
    /// 1 everywhere.
    Mean,
    /// 1 within [`RADIAL_FULL_DEG`] of the optical axis, falling linearly to 0 at the image's
    /// inscribed half field of view (the widest cone about the axis that fits in the image).
    Radial,
    /// min(1, d_x / (r·width), d_y / (r·height)) with d the distance to the nearest image border
    /// (pixel edges) and r = [`FRUSTUM_RAMP`]: 1 in the centre, 0 at the border.
    Frustum,
}

choice!(
    Weighting,
    "weights",
    [
        (Weighting::Nearest, "nn"),
        (Weighting::Mean, "mean"),
        (Weighting::Radial, "radial"),
        (Weighting::Frustum, "frustum"),
    ]
);

/// Frustum weight of continuous pixel position (x, y) of `cam` (0 outside the image).
#[must_use]
pub fn frustum_weight(cam: &TangentCamera, x: f64, y: f64) -> f64 {
    let (w, h) = (cam.width as f64, cam.height as f64);
    let dx = (x + 0.5).min(w - 0.5 - x);
    let dy = (y + 0.5).min(h - 0.5 - y);
    (dx / (FRUSTUM_RAMP * w))
        .min(dy / (FRUSTUM_RAMP * h))
        .clamp(0.0, 1.0)
}

/// Half-angle (radians) of the widest cone about the optical axis of `cam` inside its image.
#[must_use]
pub fn inscribed_half_fov(cam: &TangentCamera) -> f64 {
    let (w, h) = (cam.width as f64, cam.height as f64);
    // The principal point is off-centre for the icosahedron: the nearest border decides.
    let tan = ((cam.cx + 0.5) / cam.fx)
        .min((w - 0.5 - cam.cx) / cam.fx)
        .min((cam.cy + 0.5) / cam.fy)
        .min((h - 0.5 - cam.cy) / cam.fy);
    tan.max(0.0).atan()
}

/// Radial weight of continuous pixel position (x, y) of `cam`.
#[must_use]
pub fn radial_weight(cam: &TangentCamera, x: f64, y: f64) -> f64 {
    let full = RADIAL_FULL_DEG.to_radians();
    let edge = inscribed_half_fov(cam);
    let angle = cam.spherical_factor(x, y).clamp(-1.0, 1.0).acos();
    if angle <= full {
        1.0
    } else if edge <= full {
        0.0
    } else {
        ((edge - angle) / (edge - full)).clamp(0.0, 1.0)
    }
}

/// Weight maps of every face of `layout` (N·h·w, f32, row-major per face).
pub fn weight_maps(layout: &Layout, kind: Weighting) -> Vec<f32> {
    let (h, w) = layout.tangent_shape();
    let axes: Vec<_> = layout.cameras.iter().map(TangentCamera::axis).collect();
    let mut out = vec![0.0f32; layout.cameras.len() * h * w];
    out.par_chunks_mut(w)
        .enumerate()
        .for_each(|(face_row, row)| {
            let k = face_row / h;
            let cam = &layout.cameras[k];
            let r = (face_row % h) as f64;
            for (c, v) in row.iter_mut().enumerate() {
                let x = c as f64;
                *v = match kind {
                    Weighting::Mean => 1.0,
                    Weighting::Frustum => frustum_weight(cam, x, r) as f32,
                    Weighting::Radial => radial_weight(cam, x, r) as f32,
                    Weighting::Nearest => {
                        let d = cam.pixel_direction(x, r);
                        let own = axes[k].dot(&d);
                        // Ties go to the lower index, as the taps' nearness ranks do.
                        #[expect(clippy::float_cmp, reason = "an exact tie is what needs a rule")]
                        let nearest = axes
                            .iter()
                            .enumerate()
                            .all(|(m, a)| m == k || a.dot(&d) < own || (a.dot(&d) == own && k < m));
                        f32::from(u8::from(nearest))
                    }
                };
            }
        });
    out
}

/// Blending weights of one kind, kept as the per-face maps (N·h·w) and sampled at the ERP taps
/// one row at a time as a blend reads them.
///
/// Stored per tap instead, they took 4 bytes for every (ERP pixel, face) pair: 0.7 GB at 8K
/// with padding 0.7, where the maps take 4 bytes per tangent pixel (0.18 GB). Sampling uses the
/// taps' own bilinear kernel ([`ErpTaps::sample`]), so the weights are the same numbers either
/// way.
#[derive(Debug, Clone)]
pub struct WeightMaps {
    maps: Vec<f32>,
}

impl WeightMaps {
    /// The maps of `kind` for every face of `layout`.
    #[must_use]
    pub fn new(layout: &Layout, kind: Weighting) -> Self {
        Self {
            maps: weight_maps(layout, kind),
        }
    }

    /// The per-face maps (N·h·w, row-major per face).
    #[must_use]
    pub fn maps(&self) -> &[f32] {
        &self.maps
    }

    /// The weights at the taps of ERP row `i`, in tap order, into `out`.
    ///
    /// # Panics
    /// If `taps` were built for another layout size.
    pub fn row_into(&self, taps: &ErpTaps, i: usize, out: &mut Vec<f32>) {
        taps.sample(&self.maps, Sampling::Bilinear, i, out);
    }

    /// Bytes held.
    #[must_use]
    pub fn memory_bytes(&self) -> usize {
        self.maps.len() * 4
    }
}
