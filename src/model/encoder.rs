//! The shape encoder (3DShape2VecSet): FPS-selected points query the whole point cloud by
//! cross-attention, self-attention layers refine them, a bottleneck squeezes them to the latent
//! set C (K x latent_dim).

use candle_core::{DType, Tensor};
use candle_nn::VarBuilder;

use super::attention::{CrossAttention, Dense, Mlp, Norm, SelfAttention};
use super::config::{Bottleneck, FaceConfig};
use super::fourier::FourierFeatures;
use super::{ModelError, Result};

/// Pre-norm self-attention + MLP (no positions: a point set has no order).
#[derive(Debug, Clone)]
struct EncoderBlock {
    attn_norm: Norm,
    attn: SelfAttention,
    mlp_norm: Norm,
    mlp: Mlp,
}

impl EncoderBlock {
    fn new(cfg: &FaceConfig, vb: VarBuilder) -> Result<Self> {
        let e = &cfg.encoder;
        Ok(Self {
            attn_norm: Norm::new(e.width, cfg.norm_eps, vb.pp("attn_norm"))?,
            attn: SelfAttention::new(e.width, e.heads, vb.pp("attn"))?,
            mlp_norm: Norm::new(e.width, cfg.norm_eps, vb.pp("mlp_norm"))?,
            mlp: Mlp::new(e.width, e.mlp_hidden, e.width, vb.pp("mlp"))?,
        })
    }

    fn dense_mut(&mut self) -> Vec<&mut Dense> {
        let mut layers = self.attn.dense_mut();
        layers.extend(self.mlp.dense_mut());
        layers
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let x = (x + self.attn.forward(&self.attn_norm.forward(x)?, None, None)?)?;
        Ok((&x + self.mlp.forward(&self.mlp_norm.forward(&x)?)?)?)
    }
}

/// The queries' one cross-attention block over all points.
#[derive(Debug, Clone)]
struct QueryBlock {
    query_norm: Norm,
    point_norm: Norm,
    attn: CrossAttention,
    mlp_norm: Norm,
    mlp: Mlp,
}

impl QueryBlock {
    fn new(cfg: &FaceConfig, vb: VarBuilder) -> Result<Self> {
        let e = &cfg.encoder;
        Ok(Self {
            query_norm: Norm::new(e.width, cfg.norm_eps, vb.pp("query_norm"))?,
            point_norm: Norm::new(e.width, cfg.norm_eps, vb.pp("point_norm"))?,
            attn: CrossAttention::new(e.width, e.heads, vb.pp("attn"))?,
            mlp_norm: Norm::new(e.width, cfg.norm_eps, vb.pp("mlp_norm"))?,
            mlp: Mlp::new(e.width, e.mlp_hidden, e.width, vb.pp("mlp"))?,
        })
    }

    fn dense_mut(&mut self) -> Vec<&mut Dense> {
        let mut layers = self.attn.dense_mut();
        layers.extend(self.mlp.dense_mut());
        layers
    }

    fn forward(&self, queries: &Tensor, points: &Tensor) -> Result<Tensor> {
        let (k, v) = self.attn.memory_kv(&self.point_norm.forward(points)?)?;
        let x = (queries + self.attn.forward(&self.query_norm.forward(queries)?, &k, &v)?)?;
        Ok((&x + self.mlp.forward(&self.mlp_norm.forward(&x)?)?)?)
    }
}

/// What the bottleneck produced: the latent means and, for a KL bottleneck, log-variances.
#[derive(Debug, Clone)]
pub struct EncoderOutput {
    pub mean: Tensor,
    pub logvar: Option<Tensor>,
}

impl EncoderOutput {
    /// Latents for training: a reparameterized sample for a KL bottleneck, else the mean.
    pub fn sample(&self) -> Result<Tensor> {
        match &self.logvar {
            None => Ok(self.mean.clone()),
            Some(logvar) => {
                let std = (logvar * 0.5)?.exp()?;
                let eps = std.randn_like(0.0, 1.0)?;
                Ok((&self.mean + (std * eps)?)?)
            }
        }
    }

    /// Mean KL divergence to N(0, I) per latent coordinate (zero without a KL bottleneck).
    pub fn kl(&self) -> Result<Tensor> {
        match &self.logvar {
            None => Ok(Tensor::zeros((), DType::F32, self.mean.device())?),
            Some(logvar) => {
                let terms = ((self.mean.sqr()? + logvar.exp()?)? - 1.0)?.sub(logvar)?;
                Ok((terms.mean_all()? * 0.5)?)
            }
        }
    }
}

#[derive(Debug, Clone)]
pub struct ShapeEncoder {
    fourier: FourierFeatures,
    point_embed: Dense,
    query_block: QueryBlock,
    layers: Vec<EncoderBlock>,
    norm: Norm,
    bottleneck: Dense,
    kind: Bottleneck,
    latent_dim: usize,
}

impl ShapeEncoder {
    pub fn new(cfg: &FaceConfig, vb: VarBuilder) -> Result<Self> {
        let e = &cfg.encoder;
        let out = match cfg.bottleneck {
            Bottleneck::Linear => cfg.latent_dim,
            Bottleneck::Kl { .. } => 2 * cfg.latent_dim,
        };
        Ok(Self {
            fourier: FourierFeatures::new(cfg.fourier_frequencies, vb.device())?,
            point_embed: Dense::new(cfg.fourier_width(), e.width, true, vb.pp("point_embed"))?,
            query_block: QueryBlock::new(cfg, vb.pp("query_block"))?,
            layers: (0..e.layers)
                .map(|i| EncoderBlock::new(cfg, vb.pp(format!("layers.{i}"))))
                .collect::<Result<_>>()?,
            norm: Norm::new(e.width, cfg.norm_eps, vb.pp("norm"))?,
            bottleneck: Dense::new(e.width, out, true, vb.pp("bottleneck"))?,
            kind: cfg.bottleneck,
            latent_dim: cfg.latent_dim,
        })
    }

    /// Every linear layer, in checkpoint order.
    pub fn dense_mut(&mut self) -> Vec<&mut Dense> {
        let mut layers = vec![&mut self.point_embed];
        layers.extend(self.query_block.dense_mut());
        layers.extend(self.layers.iter_mut().flat_map(EncoderBlock::dense_mut));
        layers.push(&mut self.bottleneck);
        layers
    }

    /// points, normals: (B, M, 3) f32; query_indices: (B, K) u32 indices into the M points
    /// (farthest point sampling picks them).
    pub fn forward(
        &self,
        points: &Tensor,
        normals: &Tensor,
        query_indices: &Tensor,
    ) -> Result<EncoderOutput> {
        self.forward_with_max_index(points, normals, query_indices, None)
    }

    /// [`Self::forward`], given the largest query index when the host knows it: reading it
    /// from the device would make the host wait for the device in every training pass.
    pub fn forward_with_max_index(
        &self,
        points: &Tensor,
        normals: &Tensor,
        query_indices: &Tensor,
        max_index: Option<u32>,
    ) -> Result<EncoderOutput> {
        let (b, m, c) = points.dims3()?;
        if c != 3 || normals.dims() != points.dims() {
            return Err(ModelError::bad_input(format!(
                "points {:?} and normals {:?} must both be (B, M, 3)",
                points.dims(),
                normals.dims()
            )));
        }
        let (qb, k) = query_indices.dims2()?;
        if qb != b || query_indices.dtype() != DType::U32 {
            return Err(ModelError::bad_input(format!(
                "query indices {:?} ({:?}) must be (B={b}, K) u32",
                query_indices.dims(),
                query_indices.dtype()
            )));
        }
        if k == 0 {
            return Err(ModelError::bad_input("no query indices"));
        }
        let max = match max_index {
            Some(max) => max as usize,
            None => query_indices.max_all()?.to_scalar::<u32>()? as usize,
        };
        if max >= m {
            return Err(ModelError::bad_input(format!(
                "query index {max} is not below the point count {m}"
            )));
        }
        let input = Tensor::cat(&[points, normals], 2)?;
        let embedded = self.point_embed.forward(&self.fourier.forward(&input)?)?;
        // Each row's queries gathered along its points. A gather's gradient (scatter_add)
        // runs on CUDA one thread per (row, channel); a lookup's (`index_select` on the
        // flattened batch) one per channel, looping over every query of the batch.
        let width = embedded.dim(2)?;
        let index = query_indices.unsqueeze(2)?.broadcast_as((b, k, width))?.contiguous()?;
        let queries = embedded.contiguous()?.gather(&index, 1)?;
        let mut x = self.query_block.forward(&queries, &embedded)?;
        for layer in &self.layers {
            x = layer.forward(&x)?;
        }
        let z = self.bottleneck.forward(&self.norm.forward(&x)?)?;
        Ok(match self.kind {
            Bottleneck::Linear => EncoderOutput { mean: z, logvar: None },
            Bottleneck::Kl { .. } => EncoderOutput {
                mean: z.narrow(2, 0, self.latent_dim)?,
                logvar: Some(z.narrow(2, self.latent_dim, self.latent_dim)?.clamp(-30f32, 20f32)?),
            },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::testing::{max_abs_diff, random_model};
    use candle_core::Device;

    #[test]
    fn kl_bottleneck_encodes_its_mean_and_samples_for_training() {
        let mut cfg = FaceConfig::micro();
        cfg.bottleneck = Bottleneck::Kl { weight: 1e-3 };
        let (_, model) = random_model(&cfg);
        let dev = Device::Cpu;
        let pts = Tensor::randn(0f32, 1.0, (2, cfg.num_points, 3), &dev).unwrap();
        let idx: Vec<u32> = (0..2 * cfg.num_latents as u32).map(|i| i % 7).collect();
        let idx = Tensor::from_vec(idx, (2, cfg.num_latents), &dev).unwrap();
        let a = model.encode(&pts, &pts, &idx).unwrap();
        assert_eq!(a.dims(), &[2, cfg.num_latents, cfg.latent_dim]);
        assert_eq!(max_abs_diff(&a, &model.encode(&pts, &pts, &idx).unwrap()), 0.0);
        let out = model.encode_train(&pts, &pts, &idx).unwrap();
        assert!(max_abs_diff(&out.sample().unwrap(), &a) > 0.0);
        assert!(out.kl().unwrap().to_scalar::<f32>().unwrap() >= 0.0);
    }
}
