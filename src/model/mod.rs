//! The FACE model in candle: shape encoder, autoregressive face decoder with per-sequence
//! caches, CausalMLP head, generation with constraints, the per-coordinate baseline, and
//! checkpoints.
//!
//! The model is stateless: a [`SequenceState`] (decoder caches and faces so far) belongs to the
//! caller, and [`FaceModel::step`] advances any set of sequences, of any lengths, in one batch.
//!
//! # How the engine drives it
//!
//! ```text
//! latents = model.encode(points, normals, fps_indices)      // (B, K, latent_dim), batched
//! gen     = Generation::new(&model, &latents.get(i), opts)   // keeps the latents, a fresh cache
//! loop { events = step_generations(&model, &mut running) }   // one decoder step for all rows,
//!                                                            // then 9 head passes with per-row
//!                                                            // sampling or face beams, and
//!                                                            // constraint masks
//! ```
//! A generation may join `running` at any iteration (a face boundary) and is dropped when its
//! event says it finished; `Generation::cancel` ends it early. Lower level, the same loop is
//! [`FaceModel::step`] (hidden states) + [`FaceModel::head_logits`] /
//! [`FaceModel::extend_context`] (the CausalMLP, coordinate by coordinate) +
//! [`SequenceState::push_face`].
//!
//! # Decisions
//!
//! - Positions: RoPE in the decoder's self-attention (no learned table to outgrow); the encoder
//!   has no positions (a point set has no order). Learned positions were not tried.
//! - The CausalMLP's sub-heads reuse the decoder's 9 per-slot coordinate embedding tables for
//!   the coordinates already chosen; sub-head j is an MLP on [h ; e_0 .. e_{j-1}]. Decoding
//!   folds their first layers with the tables (`head::FoldedHead`).
//! - Pre-norm LayerNorm blocks, SiLU MLPs, no biases in attention projections.
//! - Weight names (the checkpoint format): `encoder.{point_embed, query_block.*, layers.N.*,
//!   norm, bottleneck}`, `decoder.{coord_embed, face_pooling.fc1/fc2, start, latent_up,
//!   layers.N.{self_norm, self_attn.qkv/out, cross_norm, cross_attn.q/kv/out, mlp_norm,
//!   mlp.fc1/fc2}, norm}`, `head.sub.J.fc1/fc2`; linear weights are (out, in) as in candle.
//! - candle's fused kernels (layer norm, softmax, RoPE) have no backward pass: blocks use them
//!   only when nothing tracks gradients, so build inference models from detached weights
//!   ([`checkpoint::load`], [`checkpoint::inference_model`]); a `VarMap`-backed model trains.

pub(crate) mod attention;
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
mod face_search;
pub mod few_rows;
mod fourier;
pub(crate) mod fused;
mod generate;
mod head;
mod input;
pub mod quantize;
mod ragged;
mod sampling;
mod seeded_init;
#[cfg(test)]
pub(crate) mod testing;

pub use baseline::{BaselineState, CoordinateBaseline};
pub use batch::{CoordinateNll, TrainBatch, TrainExample};
pub use cache::{DecoderCache, KV_CHUNK};
pub use config::{Bottleneck, COORDS_PER_FACE, FaceConfig, StackConfig};
pub use constraints::{allowed_values, completion_exists, is_valid_next};
pub use device::parse_device;
pub use encoder::EncoderOutput;
pub use error::ModelError;
pub use face::{ENCODER_SCOPE, EncoderTraining, FaceModel, SequenceState, TrainLoss};
pub use generate::{
    DEFAULT_FACE_BEAM, DEFAULT_TEMPERATURE, FaceStream, FinishReason, GenerateOptions, Generation,
    MAX_FACE_BEAM, StepEvent, generate, step_generations,
};
pub use input::PointCloudInput;
pub use quantize::{Quantize, QuantizeReport};
pub use sampling::{Sampler, SamplingParams};
pub use seeded_init::seeded_var_builder;

/// A face: (z0 y0 x0 z1 y1 x1 z2 y2 x2), each coordinate in 0..Q.
pub use crate::tokenize::FaceToken;

pub type Result<T, E = ModelError> = std::result::Result<T, E>;
