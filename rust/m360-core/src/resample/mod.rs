//! Bilinear resampling between the ERP image and the tangent images, both ways.
//!
//! Both directions use precomputed taps (see [`crate::plan::Plan`]): the position of every output
//! pixel in the source image, stored as the index of its top-left source pixel and two fixed-point
//! fractions (8 bytes a pixel). Nothing is rounded to whole pixels (reference pitfall B8,
//! docs/reference-pitfalls.md).
//!
//! The pipeline: [`TangentTaps`] are built once per plan and [`erp_to_tangents`] samples the ERP
//! image into the tangent images through them; the network runs on those; [`ErpTaps`] are built
//! once per plan and [`tangents_to_erp`] (or a blend, which reads [`ErpTaps`] run by run) maps
//! the tangents back onto the ERP grid.
//!
//! - `taps.rs`: the tap encoding ([`Tap`], its index flags and fixed-point fractions), the
//!   per-pixel bilinear combinations ([`Texel`], and that of f32 tangent stacks) and prefetch.
//! - `to_tangents.rs`: ERP → tangents ([`TangentTaps`], [`ErpSource`], [`erp_to_tangents`]).
//! - `to_erp.rs`: tangents → ERP ([`ErpTaps`], [`Run`], [`Ranks`], [`tangents_to_erp`]).
//! - `simd.rs`: the x86 SIMD kernels of both directions (u8 ERP sampling, f32 run sampling).

mod taps;
mod to_erp;
mod to_tangents;

#[cfg(target_arch = "x86_64")]
mod simd;

pub use taps::{Sampling, Tap, Texel};
pub(crate) use taps::{OFFSET_MASK, RANK_SHIFT, WRAPPED};
pub(crate) use to_erp::MAX_FACES_PER_PIXEL;
pub use to_erp::{tangents_to_erp, ErpTaps, Ranks, Run};
pub use to_tangents::{erp_to_tangents, ErpSource, TangentTaps};
