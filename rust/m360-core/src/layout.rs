//! Tangent layouts: a set of cameras covering the sphere for one ERP size (docs/conventions.md).

use crate::camera::TangentCamera;
use crate::error::{CoreError, Result};
use nalgebra::{Matrix3, Vector3};

/// Tangent width of the paper's layout at ERP width [`REFERENCE_ERP_WIDTH`].
pub const REFERENCE_TANGENT_WIDTH: usize = 400;
/// ERP width at which the paper uses 400-pixel-wide tangents.
pub const REFERENCE_ERP_WIDTH: usize = 2048;
/// Narrowest ERP of the icosahedron layout: below it the tangents are a handful of pixels.
pub const MIN_ERP_WIDTH: usize = 64;
/// Widest ERP m360 accepts (32K): the widest whose indices fit the plan's 32-bit taps (an ERP
/// pixel index below 2³¹, a tangent pixel below 2²⁸). A plan holds about 42 bytes per ERP pixel
/// (~22 GB at 32K), so whether a size fits this machine is judged before allocating, from an
/// estimate of the memory needed (`m360.memory` in the Python package).
pub const MAX_ERP_WIDTH: usize = 1 << 15;
/// Largest icosahedron padding, in gnomonic units (0.3 is the paper's).
pub const MAX_PADDING: f64 = 2.0;
/// Narrowest tangent image of the icosahedron layout.
pub const MIN_TANGENT_WIDTH: usize = 8;

/// Cameras that together cover the sphere, for an ERP image of a given size.
///
/// All cameras have the same image size, so tangent stacks are (N, h, w) arrays.
#[derive(Debug, Clone, PartialEq)]
pub struct Layout {
    /// ERP height H (W = 2H).
    pub erp_height: usize,
    /// ERP width W.
    pub erp_width: usize,
    /// The tangent cameras.
    pub cameras: Vec<TangentCamera>,
    /// Per camera, the polygon it is responsible for in gnomonic coordinates (the un-padded face
    /// triangle for the icosahedron); empty for layouts without one.
    pub face_polygons: Vec<Vec<[f64; 2]>>,
}

impl Layout {
    /// A layout from explicit cameras, checked for consistency.
    ///
    /// # Errors
    /// [`CoreError::InvalidLayout`] saying what is inconsistent.
    pub fn new(
        erp_height: usize,
        erp_width: usize,
        cameras: Vec<TangentCamera>,
        face_polygons: Vec<Vec<[f64; 2]>>,
    ) -> Result<Self> {
        let bad = |msg: String| Err(CoreError::InvalidLayout(msg));
        if erp_width != 2 * erp_height || erp_height < 2 {
            return bad(format!(
                "ERP size {erp_height}x{erp_width} is not H x 2H with H >= 2"
            ));
        }
        let Some(first) = cameras.first() else {
            return bad("a layout needs at least one camera".into());
        };
        for (k, cam) in cameras.iter().enumerate() {
            if (cam.width, cam.height) != (first.width, first.height) {
                return bad(format!(
                    "camera {k} is {}x{} but camera 0 is {}x{}: all tangents must have one size",
                    cam.width, cam.height, first.width, first.height
                ));
            }
            if cam.width < 2 || cam.height < 2 {
                return bad(format!("camera {k} is smaller than 2x2 pixels"));
            }
            let finite = [cam.fx, cam.fy, cam.cx, cam.cy]
                .iter()
                .all(|v| v.is_finite());
            if !finite || cam.fx <= 0.0 || cam.fy <= 0.0 {
                return bad(format!(
                    "camera {k} has non-finite or non-positive intrinsics"
                ));
            }
            let r = &cam.rotation;
            let orthonormal = (r * r.transpose() - Matrix3::identity()).abs().max() < 1e-6;
            if !orthonormal || (r.determinant() - 1.0).abs() > 1e-6 {
                return bad(format!(
                    "camera {k}'s rotation is not a proper rotation matrix"
                ));
            }
        }
        if !face_polygons.is_empty() && face_polygons.len() != cameras.len() {
            return bad("face polygons must be given for every camera or none".into());
        }
        Ok(Self {
            erp_height,
            erp_width,
            cameras,
            face_polygons,
        })
    }

    /// The paper's layout: one camera per icosahedron face, looking at the face centroid with no
    /// roll (image x = local east, y = local south), its image the bounding box of the face
    /// triangle with every edge pushed out by `padding` gnomonic units.
    ///
    /// Tangents are `tangent_width` pixels wide (default: 400 at ERP width 2048, scaled linearly),
    /// with square pixels; the height follows from the bounding box (346 at width 400). Faces 0–4
    /// touch the north pole, 5–9 and 10–14 are the equatorial band, 15–19 touch the south pole.
    ///
    /// # Errors
    /// [`CoreError::InvalidLayout`] for an unusable size or padding.
    pub fn icosahedron(
        erp_width: usize,
        padding: f64,
        tangent_width: Option<usize>,
    ) -> Result<Self> {
        if !erp_width.is_multiple_of(2) || !(MIN_ERP_WIDTH..=MAX_ERP_WIDTH).contains(&erp_width) {
            return Err(CoreError::InvalidLayout(format!(
                "erp_width={erp_width} is unusable: it must be even, at least {MIN_ERP_WIDTH} and \
                 at most {MAX_ERP_WIDTH} (ERP images are H x 2H)"
            )));
        }
        if !(padding.is_finite() && (0.0..=MAX_PADDING).contains(&padding)) {
            return Err(CoreError::InvalidLayout(format!(
                "padding={padding} must be a finite number in [0, {MAX_PADDING}] (gnomonic units)"
            )));
        }
        let width = tangent_width.unwrap_or_else(|| {
            ((REFERENCE_TANGENT_WIDTH * erp_width) as f64 / REFERENCE_ERP_WIDTH as f64).round()
                as usize
        });
        if !(MIN_TANGENT_WIDTH..=MAX_ERP_WIDTH).contains(&width) {
            return Err(CoreError::InvalidLayout(format!(
                "tangent_width={width} must be an integer in [{MIN_TANGENT_WIDTH}, {MAX_ERP_WIDTH}]"
            )));
        }
        let mut cameras = Vec::with_capacity(20);
        let mut polygons = Vec::with_capacity(20);
        for face in icosahedron_faces() {
            let (camera, triangle) = face_camera(&face, padding, width);
            cameras.push(camera);
            polygons.push(triangle);
        }
        Self::new(erp_width / 2, erp_width, cameras, polygons)
    }

    /// Tangent image size `(height, width)`.
    #[must_use]
    pub fn tangent_shape(&self) -> (usize, usize) {
        let cam = &self.cameras[0];
        (cam.height, cam.width)
    }
}

/// The 20 faces of an icosahedron with a vertex at each pole, as triples of unit vertices.
fn icosahedron_faces() -> Vec<[Vector3<f64>; 3]> {
    let ring_lat = 0.5f64.atan();
    let deg = std::f64::consts::PI / 180.0;
    let north = Vector3::new(0.0, -1.0, 0.0);
    let south = Vector3::new(0.0, 1.0, 0.0);
    let upper = |k: usize| crate::sphere::lonlat_direction((72.0 * k as f64) * deg, ring_lat);
    let lower =
        |k: usize| crate::sphere::lonlat_direction((36.0 + 72.0 * k as f64) * deg, -ring_lat);
    let mut faces = Vec::with_capacity(20);
    faces.extend((0..5).map(|k| [north, upper(k), upper(k + 1)]));
    faces.extend((0..5).map(|k| [upper(k), upper(k + 1), lower(k)]));
    faces.extend((0..5).map(|k| [lower(k), lower(k + 1), upper(k + 1)]));
    faces.extend((0..5).map(|k| [lower(k), lower(k + 1), south]));
    faces
}

/// The camera of one face and the face triangle in its gnomonic coordinates.
fn face_camera(
    face: &[Vector3<f64>; 3],
    padding: f64,
    width: usize,
) -> (TangentCamera, Vec<[f64; 2]>) {
    let centre = (face[0] + face[1] + face[2]).normalize();
    let lon = centre.x.atan2(centre.z);
    let lat = (-centre.y).asin();
    let (sl, cl) = lon.sin_cos();
    let (sp, cp) = lat.sin_cos();
    let east = Vector3::new(cl, 0.0, -sl);
    let south = Vector3::new(sp * sl, cp, sp * cl);
    let rotation = Matrix3::from_rows(&[east.transpose(), south.transpose(), centre.transpose()]);

    let triangle: Vec<[f64; 2]> = face
        .iter()
        .map(|v| {
            let p = rotation * v;
            [p.x / p.z, p.y / p.z]
        })
        .collect();
    let padded = offset_polygon(&triangle, padding);
    let (mut xmin, mut xmax, mut ymin, mut ymax) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for p in &padded {
        xmin = xmin.min(p[0]);
        xmax = xmax.max(p[0]);
        ymin = ymin.min(p[1]);
        ymax = ymax.max(p[1]);
    }
    let focal = width as f64 / (xmax - xmin);
    let height = ((ymax - ymin) * focal).round() as usize;
    // Centre the bounding box on the pixel grid: the tangent point (0, 0) lands off-centre.
    let camera = TangentCamera {
        rotation,
        fx: focal,
        fy: focal,
        cx: (width as f64 - 1.0) / 2.0 - focal * (xmin + xmax) / 2.0,
        cy: (height as f64 - 1.0) / 2.0 - focal * (ymin + ymax) / 2.0,
        width,
        height,
    };
    (camera, triangle)
}

/// A convex polygon with every edge moved outwards by `distance`.
fn offset_polygon(poly: &[[f64; 2]], distance: f64) -> Vec<[f64; 2]> {
    let n = poly.len();
    let centroid = poly.iter().fold([0.0, 0.0], |a, p| {
        [a[0] + p[0] / n as f64, a[1] + p[1] / n as f64]
    });
    // Edge k joins vertex k and k+1: outward unit normal and offset line n·p = c.
    let lines: Vec<([f64; 2], f64)> = (0..n)
        .map(|k| {
            let (a, b) = (poly[k], poly[(k + 1) % n]);
            let mut normal = [b[1] - a[1], a[0] - b[0]];
            let len = normal[0].hypot(normal[1]);
            normal = [normal[0] / len, normal[1] / len];
            if normal[0] * (centroid[0] - a[0]) + normal[1] * (centroid[1] - a[1]) > 0.0 {
                normal = [-normal[0], -normal[1]];
            }
            (normal, normal[0] * a[0] + normal[1] * a[1] + distance)
        })
        .collect();
    // Vertex k of the result is where the lines of edges k−1 and k meet.
    (0..n)
        .map(|k| {
            let (n1, c1) = lines[(k + n - 1) % n];
            let (n2, c2) = lines[k];
            let det = n1[0] * n2[1] - n1[1] * n2[0];
            [
                (c1 * n2[1] - c2 * n1[1]) / det,
                (n1[0] * c2 - n2[0] * c1) / det,
            ]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_sizes() {
        for (erp, w, h) in [(2048, 400, 346), (4096, 800, 693), (8192, 1600, 1386)] {
            let layout = Layout::icosahedron(erp, 0.3, None).expect("layout");
            assert_eq!(layout.cameras.len(), 20);
            assert_eq!(layout.tangent_shape(), (h, w), "erp {erp}");
        }
    }

    #[test]
    fn reference_extent_and_principal_point() {
        // Measured in the reference: x ∈ [−1.181, 1.181], y ∈ [−1.364, 0.682] for faces whose
        // apex points north; tangent point at row ≈ 230 of 346 (≈ 115 for the others).
        let layout = Layout::icosahedron(2048, 0.3, None).expect("layout");
        for (k, cam) in layout.cameras.iter().enumerate() {
            let (x0, y0) = cam.gnomonic(-0.5, -0.5);
            let (x1, y1) = cam.gnomonic(cam.width as f64 - 0.5, cam.height as f64 - 0.5);
            assert!(
                (x0 + 1.181).abs() < 2e-3 && (x1 - 1.181).abs() < 2e-3,
                "face {k}"
            );
            let apex_up = matches!(k, 0..=4 | 10..=14);
            let (ylo, yhi, row) = if apex_up {
                (-1.364, 0.682, 230.0)
            } else {
                (-0.682, 1.364, 115.0)
            };
            assert!(
                (y0 - ylo).abs() < 5e-3 && (y1 - yhi).abs() < 5e-3,
                "face {k}: {y0} {y1}"
            );
            assert!((cam.cy - row).abs() < 1.0, "face {k}: cy {}", cam.cy);
        }
    }

    #[test]
    fn axes_hit_face_centroids_and_triangles_fit() {
        let layout = Layout::icosahedron(1024, 0.3, None).expect("layout");
        for (cam, face) in layout.cameras.iter().zip(icosahedron_faces()) {
            let centroid = (face[0] + face[1] + face[2]).normalize();
            assert!((cam.axis() - centroid).norm() < 1e-12);
            for v in face {
                let (x, y) = cam.project(&v).expect("vertex in front");
                assert!(cam.contains(x, y));
            }
        }
    }

    #[test]
    fn offset_moves_each_edge_by_distance() {
        let tri = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]];
        let p = offset_polygon(&tri, 0.5);
        assert!((p[0][0] + 0.5).abs() < 1e-12 && (p[0][1] + 0.5).abs() < 1e-12);
    }

    #[test]
    fn rejects_bad_layouts() {
        assert!(Layout::icosahedron(7, 0.3, None).is_err());
        assert!(Layout::icosahedron(2048, f64::NAN, None).is_err());
        let mut cams = Layout::icosahedron(256, 0.3, None).expect("layout").cameras;
        cams[3].rotation[(0, 0)] = 2.0;
        assert!(Layout::new(128, 256, cams, vec![]).is_err());
    }
}
