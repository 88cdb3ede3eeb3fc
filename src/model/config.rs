//! Model configuration, the named presets, and a parameter count that needs no allocation.
//!
//! The config is stored as `config.json` next to the weights, so every field is serde.

use serde::{Deserialize, Serialize};

use super::ModelError;

/// The sizes of one transformer stack (the encoder's or the decoder's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StackConfig {
    pub width: usize,
    pub layers: usize,
    pub heads: usize,
    /// Hidden size of each block's MLP.
    pub mlp_hidden: usize,
}

impl StackConfig {
    pub fn head_dim(&self) -> usize {
        self.width / self.heads.max(1)
    }
}

/// How the encoder's output is squeezed to `latent_dim`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Bottleneck {
    /// A plain linear projection (the paper's autoencoder).
    Linear,
    /// A Gaussian bottleneck (mean and log-variance) with a KL penalty of the given weight: a
    /// smoother latent space for the image-conditioned diffusion model.
    Kl { weight: f64 },
}

/// Everything that fixes the architecture. Presets: [`FaceConfig::tiny`], [`FaceConfig::base`],
/// [`FaceConfig::large`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FaceConfig {
    /// Q: quantization levels per coordinate; tokens are `0..Q`.
    pub quant_levels: usize,
    /// The longest mesh (in faces) the decoder is built for (its position limit).
    pub max_faces: usize,
    /// Surface points (with normals) the encoder reads.
    pub num_points: usize,
    /// How the encoder's points are drawn: the `num_points` farthest apart, in turn, of this
    /// many times as many drawn at random, so that they spread evenly over the surface; 1
    /// draws them independently. Training and inference both follow it, and the weights do
    /// not depend on it (a fine-tune may change it).
    #[serde(default = "FaceConfig::independent_points")]
    pub point_oversampling: usize,
    /// K: latent vectors, i.e. FPS-selected queries.
    pub num_latents: usize,
    /// Width of a latent vector after the bottleneck.
    pub latent_dim: usize,
    pub bottleneck: Bottleneck,
    /// Octaves of the Fourier features of points and normals.
    pub fourier_frequencies: usize,
    pub encoder: StackConfig,
    pub decoder: StackConfig,
    /// Width of each per-slot coordinate embedding (9 of them are concatenated).
    pub coord_embed_dim: usize,
    /// Hidden width of each CausalMLP sub-head.
    pub head_hidden: usize,
    pub rope_theta: f64,
    pub norm_eps: f64,
}

/// The most [`FaceConfig::point_oversampling`] a config may ask for: farthest point sampling
/// costs `num_points` passes over the oversampled points.
pub const MAX_POINT_OVERSAMPLING: usize = 64;

/// Coordinates per face: (z0 y0 x0 z1 y1 x1 z2 y2 x2).
pub const COORDS_PER_FACE: usize = 9;

/// The largest Q a config may ask for.
pub const MAX_QUANT_LEVELS: usize = 4096;

impl FaceConfig {
    /// The CPU default: about 7M parameters, sized for training on two cores.
    pub fn tiny() -> Self {
        Self {
            quant_levels: 128,
            max_faces: 400,
            num_points: 1024,
            point_oversampling: 1,
            num_latents: 128,
            latent_dim: 64,
            bottleneck: Bottleneck::Linear,
            fourier_frequencies: 8,
            encoder: StackConfig { width: 192, layers: 2, heads: 4, mlp_hidden: 768 },
            decoder: StackConfig { width: 256, layers: 4, heads: 4, mlp_hidden: 1024 },
            coord_embed_dim: 32,
            head_hidden: 256,
            rope_theta: 10_000.0,
            norm_eps: 1e-5,
        }
    }

    /// The paper's model: encoder 8 x 768, decoder 24 x 1024, about 500M parameters.
    pub fn base() -> Self {
        Self {
            quant_levels: 128,
            max_faces: 4000,
            num_points: 8192,
            point_oversampling: 1,
            num_latents: 2048,
            latent_dim: 64,
            bottleneck: Bottleneck::Linear,
            fourier_frequencies: 8,
            encoder: StackConfig { width: 768, layers: 8, heads: 12, mlp_hidden: 3072 },
            decoder: StackConfig { width: 1024, layers: 24, heads: 16, mlp_hidden: 4096 },
            coord_embed_dim: 64,
            head_hidden: 1024,
            rope_theta: 10_000.0,
            norm_eps: 1e-5,
        }
    }

    /// The paper's large model: about 1.2B parameters, 65,536 points, Q = 1024. The paper does
    /// not give its face limit; 8000 is our choice.
    pub fn large() -> Self {
        Self {
            quant_levels: 1024,
            max_faces: 8000,
            num_points: 65_536,
            point_oversampling: 1,
            num_latents: 2048,
            latent_dim: 64,
            bottleneck: Bottleneck::Linear,
            fourier_frequencies: 8,
            encoder: StackConfig { width: 1024, layers: 16, heads: 16, mlp_hidden: 4096 },
            decoder: StackConfig { width: 1536, layers: 24, heads: 16, mlp_hidden: 6144 },
            coord_embed_dim: 64,
            head_hidden: 1536,
            rope_theta: 10_000.0,
            norm_eps: 1e-5,
        }
    }

    /// A very small model for unit tests: builds and runs in milliseconds.
    #[cfg(test)]
    pub(crate) fn micro() -> Self {
        Self {
            quant_levels: 16,
            max_faces: 40,
            num_points: 64,
            point_oversampling: 1,
            num_latents: 8,
            latent_dim: 8,
            bottleneck: Bottleneck::Linear,
            fourier_frequencies: 4,
            encoder: StackConfig { width: 32, layers: 1, heads: 2, mlp_hidden: 64 },
            decoder: StackConfig { width: 32, layers: 2, heads: 2, mlp_hidden: 64 },
            coord_embed_dim: 8,
            head_hidden: 32,
            rope_theta: 10_000.0,
            norm_eps: 1e-5,
        }
    }

    /// A preset by name: `tiny`, `base` or `large`.
    pub fn preset(name: &str) -> Result<Self, ModelError> {
        match name {
            "tiny" => Ok(Self::tiny()),
            "base" => Ok(Self::base()),
            "large" => Ok(Self::large()),
            other => Err(ModelError::InvalidConfig(format!(
                "unknown preset {other:?} (expected tiny, base or large)"
            ))),
        }
    }

    /// What configs saved before [`Self::point_oversampling`] did: draw points independently.
    pub(crate) fn independent_points() -> usize {
        1
    }

    /// Whether weights made for `other` fit this config: everything but how points are drawn.
    pub fn same_weights(&self, other: &Self) -> bool {
        *self == Self { point_oversampling: self.point_oversampling, ..other.clone() }
    }

    /// Width of the Fourier features of one point with its normal (6 inputs, each kept raw
    /// plus a sine and a cosine per octave).
    pub fn fourier_width(&self) -> usize {
        6 * (2 * self.fourier_frequencies + 1)
    }

    /// Checks what the code relies on, so that a hand-edited `config.json` fails early and
    /// clearly instead of deep inside a matmul.
    pub fn validate(&self) -> Result<(), ModelError> {
        let bad = |m: String| Err(ModelError::InvalidConfig(m));
        // Tokens are u16, and the constraint masks walk all Q values per coordinate.
        if !(2..=MAX_QUANT_LEVELS).contains(&self.quant_levels) {
            return bad(format!(
                "quant_levels {} not in 2..={MAX_QUANT_LEVELS}",
                self.quant_levels
            ));
        }
        for (name, v) in [
            ("max_faces", self.max_faces),
            ("num_points", self.num_points),
            ("num_latents", self.num_latents),
            ("latent_dim", self.latent_dim),
            ("coord_embed_dim", self.coord_embed_dim),
            ("head_hidden", self.head_hidden),
        ] {
            if v == 0 {
                return bad(format!("{name} must be positive"));
            }
        }
        if !(1..=MAX_POINT_OVERSAMPLING).contains(&self.point_oversampling) {
            return bad(format!(
                "point_oversampling {} not in 1..={MAX_POINT_OVERSAMPLING}",
                self.point_oversampling
            ));
        }
        if self.num_latents > self.num_points {
            return bad(format!(
                "num_latents {} exceeds num_points {}",
                self.num_latents, self.num_points
            ));
        }
        for (name, s) in [("encoder", &self.encoder), ("decoder", &self.decoder)] {
            if s.width == 0 || s.heads == 0 || s.mlp_hidden == 0 || s.width % s.heads != 0 {
                return bad(format!(
                    "{name}: width {} must be a positive multiple of heads {}",
                    s.width, s.heads
                ));
            }
        }
        if !self.decoder.head_dim().is_multiple_of(2) {
            return bad(format!(
                "decoder head dim {} must be even for RoPE",
                self.decoder.head_dim()
            ));
        }
        if let Bottleneck::Kl { weight } = self.bottleneck
            && !(weight.is_finite() && weight >= 0.0)
        {
            return bad(format!("KL weight {weight} must be finite and >= 0"));
        }
        if !(self.rope_theta.is_finite() && self.rope_theta > 0.0) {
            return bad(format!("rope_theta {} must be positive", self.rope_theta));
        }
        Ok(())
    }

    /// Number of trainable parameters of the FACE model (encoder, decoder, head), computed
    /// from the sizes alone. A unit test checks it against an instantiated model.
    pub fn parameter_count(&self) -> usize {
        let (q, dc, dl) = (self.quant_levels, self.coord_embed_dim, self.latent_dim);
        let (e, d) = (&self.encoder, &self.decoder);
        let bottleneck_out = match self.bottleneck {
            Bottleneck::Linear => dl,
            Bottleneck::Kl { .. } => 2 * dl,
        };
        let encoder = linear(self.fourier_width(), e.width)
            + 3 * norm(e.width)
            + cross_attention(e.width)
            + mlp(e.width, e.mlp_hidden)
            + e.layers * encoder_block(e)
            + norm(e.width)
            + linear(e.width, bottleneck_out);
        let decoder = linear(dl, d.width)
            + COORDS_PER_FACE * q * dc
            + linear(COORDS_PER_FACE * dc, d.width)
            + linear(d.width, d.width)
            + d.width
            + d.layers * decoder_block(d)
            + norm(d.width);
        let head: usize = (0..COORDS_PER_FACE)
            .map(|j| {
                linear(d.width + j * dc, self.head_hidden)
                    + linear(self.head_hidden, q + usize::from(j == 0))
            })
            .sum();
        encoder + decoder + head
    }
}

fn linear(i: usize, o: usize) -> usize {
    i * o + o
}

fn norm(d: usize) -> usize {
    2 * d
}

fn mlp(d: usize, hidden: usize) -> usize {
    linear(d, hidden) + linear(hidden, d)
}

/// Fused qkv and output projection, no biases.
fn self_attention(d: usize) -> usize {
    4 * d * d
}

/// Query, fused key/value and output projection, no biases.
fn cross_attention(d: usize) -> usize {
    4 * d * d
}

fn encoder_block(s: &StackConfig) -> usize {
    2 * norm(s.width) + self_attention(s.width) + mlp(s.width, s.mlp_hidden)
}

pub(crate) fn decoder_block(s: &StackConfig) -> usize {
    3 * norm(s.width)
        + self_attention(s.width)
        + cross_attention(s.width)
        + mlp(s.width, s.mlp_hidden)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_validate_and_roundtrip_through_json() {
        for name in ["tiny", "base", "large"] {
            let cfg = FaceConfig::preset(name).unwrap();
            cfg.validate().unwrap();
            let json = serde_json::to_string_pretty(&cfg).unwrap();
            let back: FaceConfig = serde_json::from_str(&json).unwrap();
            assert_eq!(back, cfg);
        }
        assert!(FaceConfig::preset("huge").is_err());
    }

    #[test]
    fn base_is_within_ten_percent_of_the_papers_500m() {
        let n = FaceConfig::base().parameter_count() as f64;
        assert!((n / 500e6 - 1.0).abs() < 0.10, "base has {n} parameters");
    }

    #[test]
    fn large_and_tiny_are_the_sizes_the_docs_promise() {
        let large = FaceConfig::large().parameter_count() as f64;
        assert!((large / 1.2e9 - 1.0).abs() < 0.10, "large has {large} parameters");
        let tiny = FaceConfig::tiny().parameter_count();
        assert!((5_000_000..=10_000_000).contains(&tiny), "tiny has {tiny} parameters");
    }

    #[test]
    fn validate_rejects_inconsistent_sizes() {
        let mut cfg = FaceConfig::tiny();
        cfg.decoder.heads = 3;
        assert!(cfg.validate().is_err());
        let mut cfg = FaceConfig::tiny();
        cfg.num_latents = cfg.num_points + 1;
        assert!(cfg.validate().is_err());
        let mut cfg = FaceConfig::tiny();
        cfg.bottleneck = Bottleneck::Kl { weight: f64::NAN };
        assert!(cfg.validate().is_err());
        for oversampling in [0, MAX_POINT_OVERSAMPLING + 1] {
            let cfg = FaceConfig { point_oversampling: oversampling, ..FaceConfig::tiny() };
            assert!(cfg.validate().is_err(), "{oversampling}");
        }
    }

    #[test]
    fn configs_saved_before_point_oversampling_draw_points_independently() {
        let mut json = serde_json::to_value(FaceConfig::tiny()).unwrap();
        json.as_object_mut().unwrap().remove("point_oversampling");
        let old: FaceConfig = serde_json::from_value(json).unwrap();
        assert_eq!(old.point_oversampling, 1);
        let spread = FaceConfig { point_oversampling: 4, ..old.clone() };
        assert!(old.same_weights(&spread) && spread != old);
        assert!(!old.same_weights(&FaceConfig { num_latents: 64, ..spread }));
    }
}
