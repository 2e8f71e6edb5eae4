//! From per-tangent perspective disparity to one ERP spherical disparity map: the simple blends.

use crate::blend::{blend_rows, Statistic};
use crate::layout::Layout;
use crate::resample::ErpTaps;
use rayon::prelude::*;

/// How the tangents that see an ERP pixel are combined.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Blend {
    /// Unweighted mean of every valid sample.
    Mean,
    /// The valid sample of the face whose axis is nearest the pixel (for the icosahedron: the face
    /// whose un-padded triangle contains the pixel, falling back to the next nearest when that
    /// face has no valid sample there).
    Nearest,
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

/// Blend per-tangent maps (N·h·w, NaN = invalid) onto the ERP grid of `layout`: `disparity`
/// (H·W) gets the blend, NaN where no tangent has a valid sample; `spread` (H·W, if given) the population
/// standard deviation of the valid samples (0 with one, NaN with none).
///
/// # Panics
/// If the outputs are not H·W long.
pub fn blend(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    mode: Blend,
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) {
    let which = match mode {
        Blend::Mean => Statistic::Mean,
        Blend::Nearest => Statistic::Nearest,
    };
    blend_rows(taps, layout, tangents, None, which, disparity, spread);
}

/// [`blend`] into new vectors: (disparity, spread).
pub fn blend_to_vec(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    mode: Blend,
) -> (Vec<f32>, Vec<f32>) {
    let n = layout.erp_height * layout.erp_width;
    let (mut disparity, mut spread) = (vec![0.0; n], vec![0.0; n]);
    blend(
        taps,
        layout,
        tangents,
        mode,
        &mut disparity,
        Some(&mut spread),
    );
    (disparity, spread)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::Plan;
    use crate::resample::{erp_to_tangents, tangents_to_erp};
    use crate::sphere::ErpGrid;

    /// A smooth function of direction, so bilinear resampling of it is nearly exact.
    fn field(d: &nalgebra::Vector3<f64>) -> f64 {
        2.0 + 0.5 * d.x + 0.3 * d.y * d.z + 0.2 * d.z
    }

    fn plan(erp_width: usize) -> Plan {
        Plan::new(Layout::icosahedron(erp_width, 0.3, None).expect("layout"))
    }

    fn tangent_field(plan: &Plan) -> Vec<f32> {
        let layout = plan.layout();
        let (h, w) = layout.tangent_shape();
        let mut t = Vec::with_capacity(layout.cameras.len() * h * w);
        for cam in &layout.cameras {
            for r in 0..h {
                for c in 0..w {
                    t.push(field(&cam.pixel_direction(c as f64, r as f64)) as f32);
                }
            }
        }
        t
    }

    #[test]
    fn erp_to_tangents_matches_direct_evaluation() {
        let plan = plan(512);
        let layout = plan.layout();
        let grid = ErpGrid::new(layout.erp_height, layout.erp_width);
        let erp: Vec<f32> = (0..layout.erp_height)
            .flat_map(|i| (0..layout.erp_width).map(move |j| (i, j)))
            .map(|(i, j)| field(&grid.direction(i, j)) as f32)
            .collect();
        let mut got = vec![0.0f32; 20 * layout.tangent_shape().0 * layout.tangent_shape().1];
        erp_to_tangents(plan.tangent_taps(), layout, &erp, 1, &mut got);
        let want = tangent_field(&plan);
        let worst = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 2e-3, "worst error {worst}");
    }

    #[test]
    fn every_direction_is_seen_by_two_to_five_faces() {
        let plan = plan(256);
        let counts = plan.erp_taps().counts();
        assert!(
            counts.iter().all(|&c| (2..=5).contains(&c)),
            "{:?}",
            counts.iter().max()
        );
    }

    #[test]
    fn mean_and_nearest_reproduce_a_smooth_field() {
        let plan = plan(512);
        let layout = plan.layout();
        let grid = ErpGrid::new(layout.erp_height, layout.erp_width);
        let tangents = tangent_field(&plan);
        for mode in [Blend::Mean, Blend::Nearest] {
            let (disparity, _) = blend_to_vec(plan.erp_taps(), layout, &tangents, mode);
            for (p, &v) in disparity.iter().enumerate() {
                let want = field(&grid.direction(p / layout.erp_width, p % layout.erp_width));
                assert!(
                    (v as f64 - want).abs() < 2e-3,
                    "{mode:?} pixel {p}: {v} vs {want}"
                );
            }
        }
    }

    #[test]
    fn a_nan_neighbour_invalidates_a_sample_and_per_face_maps_agree() {
        let plan = plan(256);
        let layout = plan.layout();
        let mut tangents = tangent_field(&plan);
        let (h, w) = layout.tangent_shape();
        tangents[..h * w].fill(f32::NAN); // face 0 has no estimate at all
        let plane = layout.erp_height * layout.erp_width;
        let mut per_face = vec![0.0f32; 20 * plane];
        tangents_to_erp(plan.erp_taps(), layout, &tangents, &mut per_face);
        assert!(per_face[..plane].iter().all(|v| v.is_nan()));
        assert!(per_face[plane..].iter().any(|v| v.is_finite()));
        let (disparity, _) = blend_to_vec(plan.erp_taps(), layout, &tangents, Blend::Nearest);
        assert!(
            disparity.iter().all(|v| v.is_finite()),
            "other faces cover face 0"
        );
    }

    #[test]
    fn spherical_factor_and_mask() {
        let plan = plan(256);
        let layout = plan.layout();
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
    fn parallel_equals_sequential() {
        let plan_a = plan(256);
        let tangents = tangent_field(&plan_a);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .expect("pool");
        let seq = pool.install(|| {
            let p = self::plan(256);
            blend_to_vec(p.erp_taps(), p.layout(), &tangents, Blend::Mean).0
        });
        let par = blend_to_vec(plan_a.erp_taps(), plan_a.layout(), &tangents, Blend::Mean).0;
        assert!(seq
            .iter()
            .zip(&par)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
    }
}
