//! Pure-Rust core of m360: 360° monocular depth by stitching perspective tangent images.
//!
//! The pipeline, in the order the modules are used:
//!
//! 1. [`sphere`]: the equirectangular (ERP) pixel grid and its viewing directions.
//! 2. [`camera`] and [`layout`]: pinhole tangent cameras, and the icosahedron layout of the paper.
//! 3. [`plan`]: per-(layout, ERP size) sampling maps, built once and reused for every image;
//!    [`plan_cache`] keeps them on disk for later processes.
//! 4. [`resample`]: ERP → tangent images and tangent images → ERP, bilinear and parallel.
//! 5. [`stitch`]: the network's perspective disparity → spherical disparity.
//! 6. [`align`]: global multi-scale deformable alignment of the tangents (energy + solvers).
//! 7. [`blend`]: per-face weights, the row blends (mean, nearest, radial, frustum) and the
//!    Poisson gradient-domain blend; [`Plan::blend`] dispatches on a [`blend::Method`].
//! 8. [`edges`]: optionally, blurred depth edges made sharp along the photo's.
//! 9. [`stereo`]: after the depth, an omnidirectional stereo (ODS) pair by forward warping.
//!
//! [`options`] holds what the options share (names, limits); each option type lives with its
//! stage and says its own names and defaults, so the bindings and Python only read them.
//! Conventions (world frame x right, y down, z forward; pixel centres at integer coordinates)
//! are those of docs/conventions.md. This crate knows nothing of Python: it checks option values
//! itself (typed [`CoreError`]s), while array shapes are checked by the bindings, so functions
//! here only `debug_assert!` or document (`# Panics`) their size preconditions.
#![deny(missing_docs)]

pub mod align;
pub mod blend;
pub mod camera;
pub mod edges;
pub mod error;
pub mod layout;
pub mod options;
pub mod plan;
mod plan_array;
pub mod plan_cache;
pub mod resample;
pub mod sphere;
pub mod stereo;
pub mod stitch;
pub mod upsample;

pub use camera::TangentCamera;
pub use error::CoreError;
pub use layout::Layout;
pub use plan::Plan;
