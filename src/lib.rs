//! meshstream: the FACE method (one face, one token) as a library.
//!
//! Dependencies point one way: [`mesh`] <- [`tokenize`] <- [`model`] <- [`engine`] (and
//! [`train`]), with [`metrics`] beside [`mesh`]. The conventions every module shares
//! (normalization, ZYX order, tokens, metrics) are those of `DESIGN.md`.

pub mod baseline;
pub mod candidates;
pub mod diffusion;
pub mod engine;
pub mod mesh;
pub mod metrics;
pub mod model;
pub mod render;
pub mod server;
pub mod tokenize;
pub mod train;
