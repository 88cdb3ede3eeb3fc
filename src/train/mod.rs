//! Offline training: data sets, procedural shapes, augmentation, optimizers, the loop.
//! Nothing on the inference path uses this module.

pub mod augment;
pub mod average;
pub mod batch;
pub mod bench;
pub mod bench_ops;
pub mod checkpoint;
pub mod dataset;
pub mod device_check;
pub mod dit;
mod error;
pub mod evaluate;
pub mod log;
pub mod optim;
pub mod plot;
pub mod procedural;
pub mod run_loop;
pub mod trainer;

pub use error::TrainError;
