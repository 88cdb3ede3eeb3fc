//! Image-to-mesh, the library part: a diffusion transformer (DiT) that generates the FACE
//! autoencoder's latent set C (K vectors of `latent_dim`) from an image by flow matching
//! (paper, section 3.4); the unchanged face decoder then turns C into a mesh.
//!
//! - [`config`]: [`DitConfig`] with presets `tiny` (CPU) and `base` (the paper's ~350M).
//! - [`image`]: bytes (PNG/JPEG/WebP) to a square RGB image, with limits checked before
//!   decoding; [`framing`] finds the object and frames it as in the training renders.
//! - [`image_encoder`]: image to tokens: a patch encoder trained with the DiT (default) or a
//!   frozen DINOv2 backbone.
//! - [`dit`]: the velocity network (adaLN-Zero blocks with self- and cross-attention).
//! - [`flow`]: the flow-matching loss, classifier-free guidance and the Euler sampler, generic
//!   over any [`flow::VelocityField`].
//! - [`latent_model`]: [`DiffusionModel`] ties them together (training loss, batched
//!   step-by-step sampling) and [`checkpoint`] saves and loads it.
//!
//! Errors are the model's [`ModelError`](crate::model::ModelError); image decoding has its own
//! [`ImageInputError`].

pub mod checkpoint;
pub mod config;
pub mod dit;
pub mod flow;
pub mod framing;
pub mod image;
pub mod image_encoder;
pub mod latent_model;

pub use config::{
    DINOV2_PATCH, Dinov2Config, DitConfig, ImageEncoderConfig, LatentStats, PatchEncoderConfig,
};
pub use dit::{Dit, DitCondition};
pub use flow::{Guidance, RowStep, VelocityField};
pub use framing::{Framing, NoObject};
pub use image::{ImageInputError, ImageOptions, PreparedImage, decode_image, images_to_tensor};
pub use image_encoder::{Dinov2Encoder, ImageEncoder, PatchEncoder};
pub use latent_model::{DiffusionModel, LatentSampling, latent_stats};
