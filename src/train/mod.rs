//! Offline training: data sets, procedural shapes, augmentation, optimizers, the loop.
//! Nothing on the inference path uses this module.

pub mod augment;
pub mod batch;
pub mod dataset;
mod error;
pub mod optim;
pub mod procedural;

pub use error::TrainError;
