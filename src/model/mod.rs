//! The FACE model in candle: shape encoder, autoregressive face decoder with per-sequence
//! caches, CausalMLP head, generation with constraints, the per-coordinate baseline, and
//! checkpoints.
//!
//! The model is stateless: a [`SequenceState`] (decoder caches and faces so far) belongs to the
//! caller, and [`FaceModel::step`] advances any set of sequences, of any lengths, in one batch.

mod attention;
mod baseline;
mod batch;
mod cache;
pub mod checkpoint;
mod config;
mod constraints;
mod decoder;
mod device;
mod embedding;
mod encoder;
#[cfg(test)]
mod end_to_end;
mod error;
mod face;
mod fourier;
mod generate;
mod head;
mod input;
mod ragged;
mod sampling;
#[cfg(test)]
mod testing;

pub use baseline::{BaselineState, CoordinateBaseline};
pub use batch::{TrainBatch, TrainExample};
pub use cache::{DecoderCache, KV_CHUNK};
pub use config::{Bottleneck, COORDS_PER_FACE, FaceConfig, StackConfig};
pub use constraints::{allowed_values, completion_exists, is_valid_next};
pub use device::parse_device;
pub use encoder::EncoderOutput;
pub use error::ModelError;
pub use face::{FaceModel, SequenceState, TrainLoss};
pub use generate::{
    FaceStream, FinishReason, GenerateOptions, Generation, StepEvent, generate, step_generations,
};
pub use input::PointCloudInput;
pub use sampling::{Sampler, SamplingParams};

/// A face: (z0 y0 x0 z1 y1 x1 z2 y2 x2), each coordinate in 0..Q.
pub type FaceToken = [u16; 9];

pub type Result<T, E = ModelError> = std::result::Result<T, E>;
