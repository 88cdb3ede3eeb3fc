//! Image encoders: an image (B, 3, S, S) with values in [0, 1] to tokens (B, N, C) for the
//! DiT's cross-attention.
//!
//! - [`PatchEncoder`] (the default): non-overlapping patches, linearly embedded, plus learned
//!   positions and a few pre-norm transformer layers. Trained together with the DiT.
//! - [`Dinov2Encoder`]: a frozen DINOv2 ViT from candle-transformers (the paper conditions on
//!   DINOv3, which candle does not implement). It loads the safetensors layout of candle's
//!   DINOv2 example (`patch_embed.proj`, `cls_token`, `pos_embed`, `blocks.N.*`, `norm`,
//!   `head`; the classification `head` is required by candle's constructor though unused here).
//!   Its tokens are the patch tokens of the last block after the final norm. No real DINOv2
//!   weights can be downloaded in this build environment, so the tests only exercise the
//!   loading plumbing and the shapes with randomly initialized weights.

use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::{Init, VarBuilder};
use candle_transformers::models::dinov2::DinoVisionTransformer;

use super::config::{Dinov2Config, ImageEncoderConfig, PatchEncoderConfig};
use crate::model::attention::{Dense, Mlp, Norm, SelfAttention};
use crate::model::{ModelError, Result};

/// ImageNet channel statistics, which DINOv2 was trained with.
const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// Checks that `images` is (B, 3, size, size).
fn check_images(images: &Tensor, size: usize) -> Result<()> {
    match images.dims() {
        [_, 3, h, w] if *h == size && *w == size => Ok(()),
        dims => Err(ModelError::bad_input(format!(
            "images have shape {dims:?}, the encoder expects (B, 3, {size}, {size})"
        ))),
    }
}

/// A pre-norm transformer layer: self-attention then MLP, each with a residual.
#[derive(Debug, Clone)]
struct EncoderLayer {
    attn_norm: Norm,
    attn: SelfAttention,
    mlp_norm: Norm,
    mlp: Mlp,
}

impl EncoderLayer {
    fn new(cfg: &PatchEncoderConfig, eps: f64, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            attn_norm: Norm::new(cfg.width, eps, vb.pp("attn_norm"))?,
            attn: SelfAttention::new(cfg.width, cfg.heads, vb.pp("attn"))?,
            mlp_norm: Norm::new(cfg.width, eps, vb.pp("mlp_norm"))?,
            mlp: Mlp::new(cfg.width, cfg.mlp_hidden, cfg.width, vb.pp("mlp"))?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let x = (x + self.attn.forward(&self.attn_norm.forward(x)?, None, None)?)?;
        Ok((&x + self.mlp.forward(&self.mlp_norm.forward(&x)?)?)?)
    }
}

/// The default image encoder. Weight names: `patch_embed`, `positions`, `layers.N.*`, `norm`.
#[derive(Debug, Clone)]
pub struct PatchEncoder {
    cfg: PatchEncoderConfig,
    patch_embed: Dense,
    positions: Tensor,
    layers: Vec<EncoderLayer>,
    norm: Norm,
}

impl PatchEncoder {
    pub fn new(cfg: &PatchEncoderConfig, eps: f64, vb: VarBuilder) -> Result<Self> {
        let p = cfg.patch_size;
        let grid = cfg.image_size / p.max(1);
        let layers = (0..cfg.layers)
            .map(|i| EncoderLayer::new(cfg, eps, vb.pp(format!("layers.{i}"))))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            cfg: cfg.clone(),
            patch_embed: Dense::new(3 * p * p, cfg.width, true, vb.pp("patch_embed"))?,
            positions: vb.get_with_hints(
                (grid * grid, cfg.width),
                "positions",
                Init::Randn { mean: 0.0, stdev: 0.02 },
            )?,
            layers,
            norm: Norm::new(cfg.width, eps, vb.pp("norm"))?,
        })
    }

    /// images (B, 3, S, S) in [0, 1] -> tokens (B, (S/p)^2, width), patches in row-major order.
    pub fn forward(&self, images: &Tensor) -> Result<Tensor> {
        check_images(images, self.cfg.image_size)?;
        let b = images.dim(0)?;
        let p = self.cfg.patch_size;
        let g = self.cfg.image_size / p;
        let x = ((images * 2.0)? - 1.0)?
            .reshape((b, 3, g, p, g, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .contiguous()?
            .reshape((b, g * g, 3 * p * p))?;
        let mut x = self.patch_embed.forward(&x)?.broadcast_add(&self.positions)?;
        for layer in &self.layers {
            x = layer.forward(&x)?;
        }
        self.norm.forward(&x)
    }
}

/// A frozen DINOv2 backbone.
#[derive(Debug)]
pub struct Dinov2Encoder {
    cfg: Dinov2Config,
    vit: DinoVisionTransformer,
    mean: Tensor,
    std: Tensor,
}

impl Dinov2Encoder {
    /// Builds the network from `vb` (names as in candle's DINOv2).
    pub fn new(cfg: &Dinov2Config, vb: VarBuilder) -> Result<Self> {
        let device = vb.device().clone();
        let vit = DinoVisionTransformer::new(vb, cfg.depth, cfg.embed_dim, cfg.heads)?;
        Ok(Self {
            cfg: cfg.clone(),
            vit,
            mean: Tensor::from_slice(&IMAGENET_MEAN, (1, 3, 1, 1), &device)?,
            std: Tensor::from_slice(&IMAGENET_STD, (1, 3, 1, 1), &device)?,
        })
    }

    /// Loads DINOv2 weights from a safetensors file the user points at.
    pub fn load(cfg: &Dinov2Config, weights: &Path, device: &Device) -> Result<Self> {
        let bad = |message: String| ModelError::BadCheckpoint { path: weights.into(), message };
        if !weights.is_file() {
            return Err(ModelError::Io {
                path: weights.into(),
                error: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
            });
        }
        let tensors =
            candle_core::safetensors::load(weights, device).map_err(|e| bad(e.to_string()))?;
        let vb = VarBuilder::from_tensors(tensors, DType::F32, device);
        Self::new(cfg, vb).map_err(|e| bad(format!("not DINOv2 weights for this config: {e}")))
    }

    /// images (B, 3, S, S) in [0, 1] -> patch tokens (B, (S/14)^2, embed_dim).
    pub fn forward(&self, images: &Tensor) -> Result<Tensor> {
        check_images(images, self.cfg.image_size)?;
        let x = images.broadcast_sub(&self.mean)?.broadcast_div(&self.std)?;
        let last = self.cfg.depth.saturating_sub(1);
        // candle's DINOv2 concatenates its (1, 1, C) class token without broadcasting it over
        // the batch, so it takes one image at a time.
        let per_image = (0..x.dim(0)?)
            .map(|i| {
                let tokens = self.vit.get_intermediate_layers(
                    &x.narrow(0, i, 1)?,
                    &[last],
                    false,
                    false,
                    true,
                )?;
                Ok(tokens.get(0)?)
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Tensor::cat(&per_image, 0)?)
    }
}

/// The image encoder a [`super::DitConfig`] chose.
#[derive(Debug)]
pub enum ImageEncoder {
    Patch(PatchEncoder),
    Dinov2(Dinov2Encoder),
}

impl ImageEncoder {
    /// images (B, 3, S, S) in [0, 1] -> tokens (B, N, token_dim).
    pub fn encode(&self, images: &Tensor) -> Result<Tensor> {
        match self {
            Self::Patch(e) => e.forward(images),
            Self::Dinov2(e) => e.forward(images),
        }
    }

    /// Whether this encoder matches `cfg` (a DINOv2 encoder is built separately).
    pub(crate) fn matches(&self, cfg: &ImageEncoderConfig) -> bool {
        match (self, cfg) {
            (Self::Patch(e), ImageEncoderConfig::Patch(c)) => &e.cfg == c,
            (Self::Dinov2(e), ImageEncoderConfig::Dinov2(c)) => &e.cfg == c,
            _ => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_nn::VarMap;

    #[test]
    fn patch_encoder_shapes_and_patch_order() {
        let cfg = PatchEncoderConfig {
            image_size: 16,
            patch_size: 4,
            width: 8,
            layers: 1,
            heads: 2,
            mlp_hidden: 16,
        };
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let enc = PatchEncoder::new(&cfg, 1e-6, vb).unwrap();
        for b in [1, 3] {
            let images = Tensor::rand(0f32, 1.0, (b, 3, 16, 16), &Device::Cpu).unwrap();
            assert_eq!(enc.forward(&images).unwrap().dims(), &[b, 16, 8]);
        }
        let wrong = Tensor::zeros((1, 3, 15, 16), DType::F32, &Device::Cpu).unwrap();
        assert!(matches!(enc.forward(&wrong), Err(ModelError::BadInput(_))));
    }

    #[test]
    fn dinov2_loads_random_weights_from_safetensors_and_gives_patch_tokens() {
        let cfg = Dinov2Config { image_size: 56, depth: 2, embed_dim: 32, heads: 2 };
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        Dinov2Encoder::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &dev)).unwrap();
        for var in varmap.all_vars() {
            var.set(&var.randn_like(0.0, 0.05).unwrap()).unwrap();
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dinov2.safetensors");
        varmap.save(&path).unwrap();
        let enc = Dinov2Encoder::load(&cfg, &path, &dev).unwrap();
        let images = Tensor::rand(0f32, 1.0, (2, 3, 56, 56), &dev).unwrap();
        let tokens = ImageEncoder::Dinov2(enc).encode(&images).unwrap();
        // 56 / 14 = 4 patches a side.
        assert_eq!(tokens.dims(), &[2, 16, 32]);
        let values = tokens.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(values.iter().all(|v| v.is_finite()));

        // A config that does not fit the file, and a missing file, are clear errors.
        let wider = Dinov2Config { embed_dim: 64, heads: 4, ..cfg.clone() };
        assert!(matches!(
            Dinov2Encoder::load(&wider, &path, &dev),
            Err(ModelError::BadCheckpoint { .. })
        ));
        assert!(matches!(
            Dinov2Encoder::load(&cfg, &dir.path().join("none"), &dev),
            Err(ModelError::Io { .. })
        ));
    }
}
