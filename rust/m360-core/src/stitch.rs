//! Perspective → spherical disparity: what the stitch does to the network's output before it
//! aligns and blends it (docs/conventions.md, "Disparity").

use crate::layout::Layout;
use rayon::prelude::*;

/// The length |q| of every tangent pixel's ray q = ((x − cx)/fx, (y − cy)/fy, 1) (N·h·w, f32):
/// spherical disparity = perspective disparity / |q|.
pub fn ray_lengths(layout: &Layout) -> Vec<f32> {
    let (h, w) = layout.tangent_shape();
    let mut out = vec![0.0f32; layout.cameras.len() * h * w];
    out.par_chunks_mut(w)
        .enumerate()
        .for_each(|(face_row, dst)| {
            let cam = &layout.cameras[face_row / h];
            let gy = ((face_row % h) as f64 - cam.cy) / cam.fy;
            for (c, d) in dst.iter_mut().enumerate() {
                let gx = (c as f64 - cam.cx) / cam.fx;
                *d = (1.0 + gx * gx + gy * gy).sqrt() as f32;
            }
        });
    out
}

/// Spherical disparity (1/distance) of every tangent pixel from perspective disparity (1/z):
/// each pixel divided by the length of its own ray `(gx, gy, 1)`, computed from its own camera,
/// so no face can use another's factor (reference bug B1). Pixels whose `mask` is false become NaN.
/// `out` (N·h·w) is overwritten.
///
/// # Panics
/// If the slices are not N·h·w long.
pub fn spherical_disparity(
    layout: &Layout,
    perspective: &[f32],
    mask: Option<&[bool]>,
    out: &mut [f32],
) {
    let (h, w) = layout.tangent_shape();
    let n = layout.cameras.len() * h * w;
    assert!(perspective.len() == n && out.len() == n && mask.is_none_or(|m| m.len() == n));
    out.par_chunks_mut(w)
        .zip(perspective.par_chunks(w))
        .enumerate()
        .for_each(|(face_row, (dst, src))| {
            let cam = &layout.cameras[face_row / h];
            // The factor 1/|(gx, gy, 1)| of `TangentCamera::spherical_factor`, with gy fixed
            // along the row: a branch-free loop the compiler vectorises.
            let gy = (((face_row % h) as f64 - cam.cy) / cam.fy).powi(2);
            let (inv_fx, cx) = (1.0 / cam.fx, cam.cx);
            for (c, (d, &s)) in dst.iter_mut().zip(src).enumerate() {
                let gx = (c as f64 - cx) * inv_fx;
                *d = s * (1.0 / (1.0 + gx * gx + gy).sqrt()) as f32;
            }
            if let Some(m) = mask {
                for (d, &keep) in dst.iter_mut().zip(&m[face_row * w..(face_row + 1) * w]) {
                    if !keep {
                        *d = f32::NAN;
                    }
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout(erp_width: usize) -> Layout {
        Layout::icosahedron(erp_width, 0.3, None).expect("layout")
    }

    #[test]
    fn spherical_factor_and_mask() {
        let layout = &layout(256);
        let n = layout.cameras.len() * layout.tangent_shape().0 * layout.tangent_shape().1;
        let ones = vec![1.0f32; n];
        let mut mask = vec![true; n];
        mask[5] = false;
        let mut s = vec![0.0f32; n];
        spherical_disparity(layout, &ones, Some(&mask), &mut s);
        assert!(s[5].is_nan());
        let cam = &layout.cameras[0];
        let (cx, cy) = (cam.cx.round(), cam.cy.round());
        let centre = s[cy as usize * cam.width + cx as usize];
        assert!((centre as f64 - cam.spherical_factor(cx, cy)).abs() < 1e-6 && centre > 0.99);
        assert!(s[0] < 0.7, "the corner ray is long: {}", s[0]);
    }

    #[test]
    fn ray_lengths_match_the_camera_and_divide_perspective_into_spherical() {
        let layout = layout(256);
        let lengths = ray_lengths(&layout);
        let n = lengths.len();
        let mut spherical = vec![0.0f32; n];
        spherical_disparity(&layout, &vec![1.0f32; n], None, &mut spherical);
        let (h, w) = layout.tangent_shape();
        for (k, cam) in layout.cameras.iter().enumerate() {
            for (r, c) in [(0, 0), (h - 1, w - 1), (h / 2, w / 3)] {
                let p = (k * h + r) * w + c;
                let want = 1.0 / cam.spherical_factor(c as f64, r as f64);
                assert!((f64::from(lengths[p]) - want).abs() < 1e-5 * want, "{p}");
                assert!((spherical[p] * lengths[p] - 1.0).abs() < 1e-6, "{p}");
            }
        }
    }
}
