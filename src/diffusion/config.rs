//! The diffusion model's configuration, its presets, and a parameter count that needs no
//! allocation. Stored as `config.json` next to the weights, so every field is serde.

use serde::{Deserialize, Serialize};

use crate::model::ModelError;

/// Per-channel statistics of the autoencoder's latents. The DiT works on
/// `(latent - mean) / std`; storing the statistics in the config makes inference undo exactly
/// the normalization training applied.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LatentStats {
    pub mean: Vec<f32>,
    pub std: Vec<f32>,
}

impl LatentStats {
    /// Zero mean, unit std: the identity normalization.
    pub fn identity(latent_dim: usize) -> Self {
        Self { mean: vec![0.0; latent_dim], std: vec![1.0; latent_dim] }
    }
}

/// The default image encoder: patches of the image, linearly embedded, with learned positions
/// and a few transformer layers, trained together with the DiT.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PatchEncoderConfig {
    /// Side of the square input image in pixels; a multiple of `patch_size`.
    pub image_size: usize,
    pub patch_size: usize,
    pub width: usize,
    pub layers: usize,
    pub heads: usize,
    pub mlp_hidden: usize,
}

/// A frozen DINOv2 ViT (candle-transformers' implementation, patch size 14), loaded from a
/// safetensors file the user supplies. Its weights are not part of a diffusion checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Dinov2Config {
    /// Side of the square input image in pixels; a multiple of 14 (518 is the size the
    /// position table was trained at; other sizes interpolate it).
    pub image_size: usize,
    pub depth: usize,
    pub embed_dim: usize,
    pub heads: usize,
}

/// DINOv2's patch size (fixed in candle-transformers).
pub const DINOV2_PATCH: usize = 14;

/// Which network turns an image into the tokens the DiT cross-attends to.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ImageEncoderConfig {
    Patch(PatchEncoderConfig),
    Dinov2(Dinov2Config),
}

impl ImageEncoderConfig {
    pub fn image_size(&self) -> usize {
        match self {
            Self::Patch(p) => p.image_size,
            Self::Dinov2(d) => d.image_size,
        }
    }

    fn patch_size(&self) -> usize {
        match self {
            Self::Patch(p) => p.patch_size,
            Self::Dinov2(_) => DINOV2_PATCH,
        }
    }

    /// Tokens per image: one per patch.
    pub fn num_tokens(&self) -> usize {
        let side = self.image_size() / self.patch_size().max(1);
        side * side
    }

    /// Width of one image token.
    pub fn token_dim(&self) -> usize {
        match self {
            Self::Patch(p) => p.width,
            Self::Dinov2(d) => d.embed_dim,
        }
    }
}

/// Everything that fixes the diffusion model. Presets: [`DitConfig::tiny`], [`DitConfig::base`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DitConfig {
    /// K: latent vectors per shape (the face autoencoder's `num_latents`).
    pub num_latents: usize,
    /// Width of a latent vector (the face autoencoder's `latent_dim`).
    pub latent_dim: usize,
    pub width: usize,
    pub layers: usize,
    pub heads: usize,
    /// Hidden size of each block's MLP.
    pub mlp_hidden: usize,
    /// Sinusoid frequencies of the timestep embedding (its width is twice this).
    pub timestep_frequencies: usize,
    pub latent_stats: LatentStats,
    /// Probability that training replaces a row's image tokens with the learned null
    /// condition, which is what classifier-free guidance needs at sampling time.
    pub condition_dropout: f64,
    pub image_encoder: ImageEncoderConfig,
    pub norm_eps: f64,
    /// [`encoder_fingerprint`](crate::model::checkpoint::encoder_fingerprint) of the face
    /// autoencoder whose latents this model learned to generate, recorded by training: the
    /// model is refused beside a face model with another encoder. `None` in models made before
    /// it was recorded, which are paired unchecked.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub encoder_fingerprint: Option<String>,
}

impl DitConfig {
    /// The CPU default, sized for the `tiny` face autoencoder (K = 128, latent_dim = 64):
    /// about 4.7M parameters with its patch encoder.
    pub fn tiny() -> Self {
        Self {
            num_latents: 128,
            latent_dim: 64,
            width: 192,
            layers: 4,
            heads: 4,
            mlp_hidden: 768,
            timestep_frequencies: 128,
            latent_stats: LatentStats::identity(64),
            encoder_fingerprint: None,
            condition_dropout: 0.1,
            image_encoder: ImageEncoderConfig::Patch(PatchEncoderConfig {
                image_size: 64,
                patch_size: 8,
                width: 192,
                layers: 2,
                heads: 4,
                mlp_hidden: 768,
            }),
            norm_eps: 1e-6,
        }
    }

    /// The paper's size (about 350M parameters in the DiT) for the `base` autoencoder
    /// (K = 2048, latent_dim = 64), conditioned on a frozen DINOv2 ViT-L/14 (the paper uses
    /// DINOv3, which candle does not implement).
    pub fn base() -> Self {
        Self {
            num_latents: 2048,
            latent_dim: 64,
            width: 768,
            layers: 24,
            heads: 12,
            mlp_hidden: 3072,
            timestep_frequencies: 128,
            latent_stats: LatentStats::identity(64),
            encoder_fingerprint: None,
            condition_dropout: 0.1,
            image_encoder: ImageEncoderConfig::Dinov2(Dinov2Config {
                image_size: 518,
                depth: 24,
                embed_dim: 1024,
                heads: 16,
            }),
            norm_eps: 1e-6,
        }
    }

    /// A very small model for unit tests.
    #[cfg(test)]
    pub(crate) fn micro() -> Self {
        Self {
            num_latents: 8,
            latent_dim: 4,
            width: 32,
            layers: 2,
            heads: 2,
            mlp_hidden: 64,
            timestep_frequencies: 8,
            latent_stats: LatentStats::identity(4),
            encoder_fingerprint: None,
            condition_dropout: 0.1,
            image_encoder: ImageEncoderConfig::Patch(PatchEncoderConfig {
                image_size: 16,
                patch_size: 4,
                width: 16,
                layers: 1,
                heads: 2,
                mlp_hidden: 32,
            }),
            norm_eps: 1e-6,
        }
    }

    /// A preset by name: `tiny` or `base`.
    pub fn preset(name: &str) -> Result<Self, ModelError> {
        match name {
            "tiny" => Ok(Self::tiny()),
            "base" => Ok(Self::base()),
            other => Err(ModelError::InvalidConfig(format!(
                "unknown diffusion preset {other:?} (expected tiny or base)"
            ))),
        }
    }

    pub fn head_dim(&self) -> usize {
        self.width / self.heads.max(1)
    }

    /// Checks what the code relies on, so that a hand-edited `config.json` fails early and
    /// clearly instead of deep inside a matmul.
    pub fn validate(&self) -> Result<(), ModelError> {
        let bad = |m: String| Err(ModelError::InvalidConfig(m));
        for (name, v) in [
            ("num_latents", self.num_latents),
            ("latent_dim", self.latent_dim),
            ("mlp_hidden", self.mlp_hidden),
            ("timestep_frequencies", self.timestep_frequencies),
        ] {
            if v == 0 {
                return bad(format!("{name} must be positive"));
            }
        }
        if self.width == 0 || self.heads == 0 || !self.width.is_multiple_of(self.heads) {
            return bad(format!(
                "width {} must be a positive multiple of heads {}",
                self.width, self.heads
            ));
        }
        let stats = &self.latent_stats;
        if stats.mean.len() != self.latent_dim || stats.std.len() != self.latent_dim {
            return bad(format!(
                "latent_stats has {} means and {} stds, expected latent_dim = {}",
                stats.mean.len(),
                stats.std.len(),
                self.latent_dim
            ));
        }
        if stats.mean.iter().any(|m| !m.is_finite())
            || stats.std.iter().any(|s| !(s.is_finite() && *s > 0.0))
        {
            return bad("latent_stats must be finite with positive stds".into());
        }
        if !(0.0..=1.0).contains(&self.condition_dropout) {
            return bad(format!("condition_dropout {} not in [0, 1]", self.condition_dropout));
        }
        if !(self.norm_eps.is_finite() && self.norm_eps > 0.0) {
            return bad(format!("norm_eps {} must be positive", self.norm_eps));
        }
        let encoder = &self.image_encoder;
        let (size, patch) = (encoder.image_size(), encoder.patch_size());
        if patch == 0 || size == 0 || !size.is_multiple_of(patch) {
            return bad(format!(
                "image encoder: image_size {size} must be a positive multiple of the patch size \
                 {patch}"
            ));
        }
        let (width, heads, mlp) = match encoder {
            ImageEncoderConfig::Patch(p) => (p.width, p.heads, p.mlp_hidden),
            ImageEncoderConfig::Dinov2(d) => (d.embed_dim, d.heads, 1),
        };
        if width == 0 || heads == 0 || mlp == 0 || !width.is_multiple_of(heads) {
            return bad(format!(
                "image encoder: width {width} must be a positive multiple of heads {heads}"
            ));
        }
        Ok(())
    }

    /// Trainable parameters: the DiT and, for the patch encoder, the image encoder trained
    /// with it (a DINOv2 backbone is frozen and not counted). A unit test checks it against an
    /// instantiated model.
    pub fn parameter_count(&self) -> usize {
        let (w, c) = (self.width, self.image_encoder.token_dim());
        let n = self.image_encoder.num_tokens();
        let block =
            linear(w, 9 * w) + 8 * w * w + linear(w, self.mlp_hidden) + linear(self.mlp_hidden, w);
        let dit = linear(self.latent_dim, w)
            + linear(2 * self.timestep_frequencies, w)
            + linear(w, w)
            + 2 * c
            + linear(c, w)
            + n * w
            + self.layers * block
            + linear(w, 2 * w)
            + linear(w, self.latent_dim);
        let encoder = match &self.image_encoder {
            ImageEncoderConfig::Patch(p) => {
                let e = p.width;
                let layer = 4 * e + 4 * e * e + linear(e, p.mlp_hidden) + linear(p.mlp_hidden, e);
                linear(3 * p.patch_size * p.patch_size, e) + n * e + p.layers * layer + 2 * e
            }
            ImageEncoderConfig::Dinov2(_) => 0,
        };
        dit + encoder
    }
}

fn linear(i: usize, o: usize) -> usize {
    i * o + o
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_validate_and_have_the_promised_sizes() {
        for cfg in [DitConfig::tiny(), DitConfig::base(), DitConfig::micro()] {
            cfg.validate().unwrap();
        }
        let tiny = DitConfig::tiny().parameter_count();
        assert!((2_000_000..=8_000_000).contains(&tiny), "tiny has {tiny} parameters");
        let base = DitConfig::base().parameter_count() as f64;
        assert!((base / 350e6 - 1.0).abs() < 0.10, "base has {base} parameters");
        assert!(DitConfig::preset("huge").is_err());
    }

    #[test]
    fn config_round_trips_through_json() {
        let cfg = DitConfig::base();
        let json = serde_json::to_string(&cfg).unwrap();
        assert_eq!(serde_json::from_str::<DitConfig>(&json).unwrap(), cfg);
    }

    #[test]
    fn validate_rejects_inconsistent_sizes() {
        let mut cfg = DitConfig::tiny();
        cfg.heads = 5;
        assert!(cfg.validate().is_err());
        let mut cfg = DitConfig::tiny();
        cfg.latent_stats.std[3] = 0.0;
        assert!(cfg.validate().is_err());
        let mut cfg = DitConfig::tiny();
        cfg.latent_stats.mean.pop();
        assert!(cfg.validate().is_err());
        let mut cfg = DitConfig::tiny();
        cfg.condition_dropout = 1.5;
        assert!(cfg.validate().is_err());
        let mut cfg = DitConfig::base();
        if let ImageEncoderConfig::Dinov2(d) = &mut cfg.image_encoder {
            d.image_size = 500;
        }
        assert!(cfg.validate().is_err());
    }
}
