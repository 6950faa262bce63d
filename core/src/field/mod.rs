//! The radiance field: the trainable encodings and networks that map a (contracted) position and a view
//! direction to density and colour. Every GPU kernel here has a CPU reference next to it, written to the
//! same arithmetic order so the two can be compared to f32 rounding.
//!
//! - [`hashgrid`]: the multi-resolution hash-grid encoding (nerfacto's base and proposal fields).
//! - [`encoding`]: scene contraction, SH view encoding, trunc_exp.
//! - [`model`]: nerfacto's radiance and proposal fields assembled from the parts, parameter layout.
//! - [`mlp`]: small fully-connected networks, forward and backward (nerfacto's density and colour heads).

pub mod encoding;
pub mod hashgrid;
pub mod mlp;
pub mod model;
