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
/// Most subdivisions of the icosahedron layout (2: 320 tangents).
pub const MAX_SUBDIVISIONS: usize = 2;
/// The paper's padding, whose pixel size the subdivided layouts keep.
const REFERENCE_PADDING: f64 = 0.3;

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
        Self::icosahedron_subdivided(erp_width, padding, tangent_width, 0)
    }

    /// The icosahedron layout with every face split `subdivisions` times into 4 (edge midpoints
    /// pushed onto the sphere): 20·4ⁿ cameras, each looking at its sub-face's centroid with no
    /// roll, its image the bounding box of the sub-face padded by `padding` gnomonic units.
    /// `subdivisions = 0` is [`Layout::icosahedron`], exactly.
    ///
    /// The sub-faces are not congruent, so every camera gets the largest padded bounding box of
    /// all of them (each centred on its own). With `tangent_width` unset the pixels have the
    /// angular size of the paper's layout at the same ERP width (the focal length of the 20-face
    /// layout at padding 0.3), so the network sees the scene at the same resolution in smaller
    /// tiles. Cameras `4ⁿ·f ..` are the sub-faces of face `f`.
    ///
    /// # Errors
    /// [`CoreError::InvalidLayout`] for an unusable size, padding or subdivision count.
    pub fn icosahedron_subdivided(
        erp_width: usize,
        padding: f64,
        tangent_width: Option<usize>,
        subdivisions: usize,
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
        if subdivisions > MAX_SUBDIVISIONS {
            return Err(CoreError::InvalidLayout(format!(
                "subdivisions={subdivisions} must be at most {MAX_SUBDIVISIONS} \
                 (20·4^n tangents)"
            )));
        }
        let reference_width = ((REFERENCE_TANGENT_WIDTH * erp_width) as f64
            / REFERENCE_ERP_WIDTH as f64)
            .round() as usize;
        let mut faces = icosahedron_faces();
        for _ in 0..subdivisions {
            faces = faces.iter().flat_map(split_face).collect();
        }
        let frames: Vec<FaceFrame> = faces.iter().map(|f| face_frame(f, padding)).collect();
        let extent =
            |frame: &FaceFrame| (frame.bbox[1] - frame.bbox[0], frame.bbox[3] - frame.bbox[2]);
        let (span_x, span_y) = frames
            .iter()
            .map(extent)
            .fold((0.0f64, 0.0f64), |a, e| (a.0.max(e.0), a.1.max(e.1)));
        let (width, focal) = match (subdivisions, tangent_width) {
            (_, Some(w)) => (w, w as f64 / span_x),
            (0, None) => (reference_width, reference_width as f64 / span_x),
            (_, None) => {
                // The paper's pixels: its focal length at the reference padding.
                let paper = face_frame(&icosahedron_faces()[0], REFERENCE_PADDING);
                let focal = reference_width as f64 / (paper.bbox[1] - paper.bbox[0]);
                ((span_x * focal).ceil() as usize, focal)
            }
        };
        if !(MIN_TANGENT_WIDTH..=MAX_ERP_WIDTH).contains(&width) {
            return Err(CoreError::InvalidLayout(format!(
                "tangent_width={width} must be an integer in [{MIN_TANGENT_WIDTH}, {MAX_ERP_WIDTH}]"
            )));
        }
        // The paper's 346 rows at 400 columns are rounded; a subdivided layout's largest box
        // must fit whole.
        let height = if subdivisions == 0 {
            (span_y * focal).round() as usize
        } else {
            (span_y * focal).ceil() as usize
        };
        let mut cameras = Vec::with_capacity(frames.len());
        let mut polygons = Vec::with_capacity(frames.len());
        for frame in frames {
            let [xmin, xmax, ymin, ymax] = frame.bbox;
            // Centre the bounding box on the pixel grid: the tangent point (0, 0) lands
            // off-centre.
            cameras.push(TangentCamera {
                rotation: frame.rotation,
                fx: focal,
                fy: focal,
                cx: (width as f64 - 1.0) / 2.0 - focal * (xmin + xmax) / 2.0,
                cy: (height as f64 - 1.0) / 2.0 - focal * (ymin + ymax) / 2.0,
                width,
                height,
            });
            polygons.push(frame.triangle);
        }
        let layout = Self::new(erp_width / 2, erp_width, cameras, polygons)?;
        if subdivisions > 0 {
            let seen = layout.most_cameras_seeing_a_direction();
            if seen > crate::resample::MAX_FACES_PER_PIXEL {
                return Err(CoreError::InvalidLayout(format!(
                    "padding={padding} with subdivisions={subdivisions} lets {seen} tangents see \
                     one direction; at most {} can be blended: use a smaller padding",
                    crate::resample::MAX_FACES_PER_PIXEL
                )));
            }
        }
        Ok(layout)
    }

    /// The most cameras whose image holds one direction, over a dense spiral of directions and
    /// the directions of every camera's face vertices (where the most images overlap).
    fn most_cameras_seeing_a_direction(&self) -> usize {
        let n = 20_000;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let spiral = (0..n).map(|i| {
            let y = 1.0 - 2.0 * (f64::from(i) + 0.5) / f64::from(n);
            let r = (1.0 - y * y).sqrt();
            let a = golden * f64::from(i);
            Vector3::new(r * a.cos(), y, r * a.sin())
        });
        let vertices = self
            .cameras
            .iter()
            .zip(&self.face_polygons)
            .flat_map(|(cam, poly)| {
                poly.iter()
                    .map(|p| (cam.rotation.transpose() * Vector3::new(p[0], p[1], 1.0)).normalize())
                    .collect::<Vec<_>>()
            });
        spiral
            .chain(vertices)
            .map(|d| {
                self.cameras
                    .iter()
                    .filter(|cam| cam.project(&d).is_some_and(|(x, y)| cam.contains(x, y)))
                    .count()
            })
            .max()
            .unwrap_or(0)
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

/// One face's camera frame: rotation (no roll), the face triangle in its gnomonic coordinates,
/// and the padded triangle's bounding box `[xmin, xmax, ymin, ymax]`.
struct FaceFrame {
    rotation: Matrix3<f64>,
    triangle: Vec<[f64; 2]>,
    bbox: [f64; 4],
}

/// The frame of a camera looking at the face's centroid with no roll.
fn face_frame(face: &[Vector3<f64>; 3], padding: f64) -> FaceFrame {
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
    let mut bbox = [f64::MAX, f64::MIN, f64::MAX, f64::MIN];
    for p in &padded {
        bbox = [
            bbox[0].min(p[0]),
            bbox[1].max(p[0]),
            bbox[2].min(p[1]),
            bbox[3].max(p[1]),
        ];
    }
    FaceFrame {
        rotation,
        triangle,
        bbox,
    }
}

/// A spherical triangle split into 4 at its edges' midpoints (pushed onto the sphere): the three
/// corner triangles (same vertex order) and the middle one.
fn split_face(face: &[Vector3<f64>; 3]) -> [[Vector3<f64>; 3]; 4] {
    let [a, b, c] = *face;
    let ab = (a + b).normalize();
    let bc = (b + c).normalize();
    let ca = (c + a).normalize();
    [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
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

    /// Whether `d` lies in the spherical triangle `face` (counter-clockwise or not).
    fn in_spherical_triangle(face: &[Vector3<f64>; 3], d: &Vector3<f64>) -> bool {
        let signs: Vec<f64> = (0..3)
            .map(|k| face[k].cross(&face[(k + 1) % 3]).dot(d))
            .collect();
        let same_side = signs.iter().all(|&s| s >= -1e-12) || signs.iter().all(|&s| s <= 1e-12);
        // The sign test alone also accepts the antipodal triangle.
        same_side && d.dot(&(face[0] + face[1] + face[2])) > 0.0
    }

    #[test]
    fn subdivided_sizes_pixels_and_centroids() {
        let paper = Layout::icosahedron(2048, 0.3, None).expect("layout");
        let same = Layout::icosahedron_subdivided(2048, 0.3, None, 0).expect("layout");
        assert_eq!(paper, same);
        for n in 1..=2 {
            let padding = 0.3 / f64::from(1 << n);
            let layout = Layout::icosahedron_subdivided(2048, padding, None, n).expect("layout");
            assert_eq!(layout.cameras.len(), 20 * 4usize.pow(n as u32));
            let mut faces = icosahedron_faces();
            for _ in 0..n {
                faces = faces.iter().flat_map(split_face).collect();
            }
            for (k, (cam, face)) in layout.cameras.iter().zip(&faces).enumerate() {
                // Same angular pixel size as the paper's layout at the same ERP width.
                assert!((cam.fx - paper.cameras[0].fx).abs() < 1e-9, "camera {k}");
                // The sub-face vertices are on the sphere and the axis is their centroid.
                let centroid = (face[0] + face[1] + face[2]).normalize();
                assert!((cam.axis() - centroid).norm() < 1e-12);
                for v in face {
                    assert!((v.norm() - 1.0).abs() < 1e-12);
                    let (x, y) = cam.project(v).expect("vertex in front");
                    assert!(cam.contains(x, y), "camera {k} misses its vertex");
                }
                // No roll: the image x axis is horizontal in the world.
                assert!(cam.rotation[(0, 1)].abs() < 1e-12);
            }
        }
    }

    #[test]
    fn subdivided_faces_tile_the_sphere_and_their_cameras_see_them() {
        // Oracle: a golden-spiral set of directions; each lies in at least one spherical
        // sub-triangle (independent of the cameras), whose camera projects it inside its image.
        let layout = Layout::icosahedron_subdivided(512, 0.0, None, 1).expect("layout");
        let mut faces = icosahedron_faces();
        faces = faces.iter().flat_map(split_face).collect();
        let n = 4000;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for i in 0..n {
            let y = 1.0 - 2.0 * (f64::from(i) + 0.5) / f64::from(n);
            let r = (1.0 - y * y).sqrt();
            let d = Vector3::new(
                r * (golden * f64::from(i)).cos(),
                y,
                r * (golden * f64::from(i)).sin(),
            );
            let owners: Vec<usize> = (0..faces.len())
                .filter(|&k| in_spherical_triangle(&faces[k], &d))
                .collect();
            assert!(!owners.is_empty(), "direction {i} is in no sub-face");
            for k in owners {
                let cam = &layout.cameras[k];
                let (x, y) = cam.project(&d).expect("in front");
                assert!(cam.contains(x, y), "camera {k} misses direction {i}");
            }
        }
        // The areas add up to the sphere: 80 spherical triangles (l'Huilier-free: Girard via
        // solid angles of Van Oosterom and Strackee).
        let total: f64 = faces
            .iter()
            .map(|[a, b, c]| {
                let num = a.dot(&b.cross(c));
                let den = 1.0 + a.dot(b) + b.dot(c) + c.dot(a);
                2.0 * num.abs().atan2(den)
            })
            .sum();
        assert!((total - 4.0 * std::f64::consts::PI).abs() < 1e-9);
    }

    #[test]
    fn subdivided_rejects_too_many_subdivisions() {
        assert!(Layout::icosahedron_subdivided(2048, 0.3, None, 3).is_err());
        // 21 tangents would see the sub-face vertices: more than the ERP taps can hold.
        assert!(Layout::icosahedron_subdivided(512, 0.5, None, 1).is_err());
        assert!(Layout::icosahedron_subdivided(512, 0.3, None, 1).is_ok());
        assert!(Layout::icosahedron_subdivided(64, 0.3, Some(4), 1).is_err());
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
