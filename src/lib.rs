//! meshstream: the FACE method (one face, one token) as a library.
//!
//! Dependencies point one way: [`mesh`] <- [`tokenize`] <- [`model`], with [`metrics`] beside
//! [`mesh`]. The conventions every module shares (normalization, ZYX order, tokens, metrics)
//! are those of `DESIGN.md`.

pub mod baseline;
pub mod mesh;
pub mod metrics;
pub mod model;
pub mod tokenize;
pub mod train;
