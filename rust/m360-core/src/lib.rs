//! Pure-Rust core of m360: 360° monocular depth by stitching perspective tangent images.
//!
//! The pipeline, in the order the modules are used:
//!
//! 1. [`sphere`]: the equirectangular (ERP) pixel grid and its viewing directions.
//! 2. [`camera`] and [`layout`]: pinhole tangent cameras, and the icosahedron layout of the paper.
//! 3. [`plan`]: per-(layout, ERP size) sampling maps, built once and reused for every image.
//! 4. [`resample`]: ERP → tangent images and tangent images → ERP, bilinear and parallel.
//! 5. [`align`]: global multi-scale deformable alignment of the tangents (energy + solvers).
//! 6. [`stitch`]: perspective → spherical disparity and the simple blends (mean, nearest face).
//! 7. [`blend`]: per-face weight maps, radial/frustum blends and the Poisson gradient-domain
//!    blend (matrix-free conjugate gradients).
//!
//! Conventions (world frame x right, y down, z forward; pixel centres at integer coordinates) are
//! those of `DESIGN.md` §1. This crate knows nothing of Python: the bindings crate validates user
//! input, so functions here only `debug_assert!` their preconditions, and report the failures that
//! can happen on valid input through [`CoreError`].
#![deny(missing_docs)]

pub mod align;
pub mod blend;
pub mod camera;
pub mod error;
pub mod layout;
pub mod options;
pub mod plan;
pub mod resample;
pub mod sphere;
pub mod stitch;

pub use camera::TangentCamera;
pub use error::CoreError;
pub use layout::Layout;
pub use plan::Plan;
