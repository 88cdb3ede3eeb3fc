//! The diffusion transformer: a velocity field over the K (normalized) latent vectors,
//! conditioned on a timestep and on image tokens.
//!
//! - No positions: the latents are a set (FPS-selected queries that the face decoder reads by
//!   cross-attention), so the DiT is permutation-equivariant over them, as in 3DShape2VecSet.
//! - The timestep enters through adaLN-Zero (DiT): each block's three sub-layers (self-attention,
//!   cross-attention to the image tokens, MLP) get a shift, a scale and a gate computed from the
//!   timestep embedding by a zero-initialized linear layer, so a fresh block is the identity and
//!   a fresh model outputs zero velocity.
//! - Image tokens are layer-normed and projected to the DiT's width once; a learned null token
//!   set of the same shape stands for "no image" (classifier-free guidance). Each block's
//!   cross-attention keys/values of a condition are computed once ([`Dit::condition`]) and
//!   reused by every sampling step.
//!
//! Weight names: `latent_in`, `time_mlp.fc1/fc2`, `cond_norm`, `cond_proj`, `null_tokens`,
//! `blocks.N.{modulation, self_attn.qkv/out, cross_attn.q/kv/out, mlp.fc1/fc2}`,
//! `final_modulation`, `out`.

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{Init, VarBuilder};

use super::config::DitConfig;
use super::flow::VelocityField;
use crate::model::attention::{CrossAttention, Dense, Mlp, Norm, SelfAttention};
use crate::model::{ModelError, Result};

/// DiT's convention: the timestep t in [0, 1] is scaled to [0, 1000] before the sinusoids, so
/// the usual 10,000-period frequency ladder resolves it.
const TIME_SCALE: f64 = 1000.0;
const MAX_PERIOD: f64 = 10_000.0;

/// A linear layer whose weight and bias start at zero (adaLN-Zero). The variables are created
/// with a zero init first; `Dense::new` then finds them and does not re-initialize them.
fn zero_dense(input: usize, output: usize, vb: VarBuilder) -> Result<Dense> {
    vb.get_with_hints((output, input), "weight", Init::Const(0.0))?;
    vb.get_with_hints(output, "bias", Init::Const(0.0))?;
    Dense::new(input, output, true, vb)
}

/// Layer norm without learned parameters (adaLN supplies the affine part). Uses candle's fused
/// kernel only when nothing tracks gradients (it has no backward pass).
#[derive(Debug, Clone)]
struct PlainNorm {
    ones: Tensor,
    zeros: Tensor,
    eps: f32,
}

impl PlainNorm {
    fn new(dim: usize, eps: f64, device: &Device) -> Result<Self> {
        Ok(Self {
            ones: Tensor::ones(dim, DType::F32, device)?,
            zeros: Tensor::zeros(dim, DType::F32, device)?,
            eps: eps as f32,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if x.track_op() {
            Ok(candle_nn::ops::layer_norm_slow(x, &self.ones, &self.zeros, self.eps)?)
        } else {
            Ok(candle_nn::ops::layer_norm(&x.contiguous()?, &self.ones, &self.zeros, self.eps)?)
        }
    }

    /// `norm(x) * (1 + scale) + shift`; shift/scale (B, 1, d).
    fn modulate(&self, x: &Tensor, shift: &Tensor, scale: &Tensor) -> Result<Tensor> {
        Ok(self.forward(x)?.broadcast_mul(&(scale + 1.0)?)?.broadcast_add(shift)?)
    }
}

/// Splits a (B, n*d) modulation into n tensors of shape (B, 1, d).
fn chunks(m: &Tensor, n: usize) -> Result<Vec<Tensor>> {
    let d = m.dim(D::Minus1)? / n;
    (0..n).map(|i| Ok(m.narrow(D::Minus1, i * d, d)?.unsqueeze(1)?)).collect()
}

/// Sinusoidal embedding of timesteps t (B,) in [0, 1]: (B, 2F) as [cos | sin].
pub fn timestep_embedding(t: &Tensor, frequencies: usize) -> Result<Tensor> {
    let freqs: Vec<f32> = (0..frequencies)
        .map(|i| (-(MAX_PERIOD.ln()) * i as f64 / frequencies as f64).exp() as f32)
        .collect();
    let freqs = Tensor::from_vec(freqs, (1, frequencies), t.device())?;
    let args = (t.to_dtype(DType::F32)?.unsqueeze(1)? * TIME_SCALE)?.broadcast_mul(&freqs)?;
    Ok(Tensor::cat(&[args.cos()?, args.sin()?], D::Minus1)?)
}

/// One block: adaLN-Zero-modulated self-attention, cross-attention and MLP.
#[derive(Debug, Clone)]
pub struct DitBlock {
    norm: PlainNorm,
    modulation: Dense,
    self_attn: SelfAttention,
    cross_attn: CrossAttention,
    mlp: Mlp,
}

impl DitBlock {
    pub fn new(cfg: &DitConfig, vb: VarBuilder) -> Result<Self> {
        let w = cfg.width;
        Ok(Self {
            norm: PlainNorm::new(w, cfg.norm_eps, vb.device())?,
            modulation: zero_dense(w, 9 * w, vb.pp("modulation"))?,
            self_attn: SelfAttention::new(w, cfg.heads, vb.pp("self_attn"))?,
            cross_attn: CrossAttention::new(w, cfg.heads, vb.pp("cross_attn"))?,
            mlp: Mlp::new(w, cfg.mlp_hidden, w, vb.pp("mlp"))?,
        })
    }

    /// Keys and values of the condition tokens (B, N, width) for this block.
    pub fn memory_kv(&self, memory: &Tensor) -> Result<(Tensor, Tensor)> {
        self.cross_attn.memory_kv(memory)
    }

    /// x (B, K, width); `c` (B, width) the SiLU of the timestep embedding; `kv` from
    /// [`DitBlock::memory_kv`].
    pub fn forward(&self, x: &Tensor, c: &Tensor, kv: &(Tensor, Tensor)) -> Result<Tensor> {
        let m = chunks(&self.modulation.forward(c)?, 9)?;
        let h = self.norm.modulate(x, &m[0], &m[1])?;
        let x = (x + self.self_attn.forward(&h, None, None)?.broadcast_mul(&m[2])?)?;
        let h = self.norm.modulate(&x, &m[3], &m[4])?;
        let x = (&x + self.cross_attn.forward(&h, &kv.0, &kv.1)?.broadcast_mul(&m[5])?)?;
        let h = self.norm.modulate(&x, &m[6], &m[7])?;
        Ok((&x + self.mlp.forward(&h)?.broadcast_mul(&m[8])?)?)
    }
}

/// A condition ready for the DiT: every block's cross-attention keys and values, for a batch.
#[derive(Debug, Clone)]
pub struct DitCondition {
    kv: Vec<(Tensor, Tensor)>,
    batch: usize,
}

impl DitCondition {
    pub fn batch(&self) -> usize {
        self.batch
    }

    /// The rows of `self` followed by the rows of `other` (conditions of the same DiT).
    pub fn concat(&self, other: &Self) -> Result<Self> {
        if self.kv.len() != other.kv.len() {
            return Err(ModelError::bad_input("conditions of different DiTs"));
        }
        let kv = self
            .kv
            .iter()
            .zip(&other.kv)
            .map(|((k1, v1), (k2, v2))| {
                Ok((Tensor::cat(&[k1, k2], 0)?, Tensor::cat(&[v1, v2], 0)?))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { kv, batch: self.batch + other.batch })
    }

    /// The rows at `rows`, in that order.
    pub fn select(&self, rows: &[u32]) -> Result<Self> {
        let device = match self.kv.first() {
            Some((k, _)) => k.device().clone(),
            None => return Ok(Self { kv: Vec::new(), batch: rows.len() }),
        };
        let idx = Tensor::from_slice(rows, rows.len(), &device)?;
        let kv = self
            .kv
            .iter()
            .map(|(k, v)| Ok((k.index_select(&idx, 0)?, v.index_select(&idx, 0)?)))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { kv, batch: rows.len() })
    }
}

#[derive(Debug, Clone)]
pub struct Dit {
    cfg: DitConfig,
    latent_in: Dense,
    time_mlp: Mlp,
    cond_norm: Norm,
    cond_proj: Dense,
    /// (N, width): the "no image" condition.
    null_tokens: Tensor,
    blocks: Vec<DitBlock>,
    final_norm: PlainNorm,
    final_modulation: Dense,
    out: Dense,
}

impl Dit {
    pub fn new(cfg: &DitConfig, vb: VarBuilder) -> Result<Self> {
        cfg.validate()?;
        let (w, c) = (cfg.width, cfg.image_encoder.token_dim());
        let blocks = (0..cfg.layers)
            .map(|i| DitBlock::new(cfg, vb.pp(format!("blocks.{i}"))))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            cfg: cfg.clone(),
            latent_in: Dense::new(cfg.latent_dim, w, true, vb.pp("latent_in"))?,
            time_mlp: Mlp::new(2 * cfg.timestep_frequencies, w, w, vb.pp("time_mlp"))?,
            cond_norm: Norm::new(c, cfg.norm_eps, vb.pp("cond_norm"))?,
            cond_proj: Dense::new(c, w, true, vb.pp("cond_proj"))?,
            null_tokens: vb.get_with_hints(
                (cfg.image_encoder.num_tokens(), w),
                "null_tokens",
                Init::Randn { mean: 0.0, stdev: 0.02 },
            )?,
            blocks,
            final_norm: PlainNorm::new(w, cfg.norm_eps, vb.device())?,
            final_modulation: zero_dense(w, 2 * w, vb.pp("final_modulation"))?,
            out: zero_dense(w, cfg.latent_dim, vb.pp("out"))?,
        })
    }

    pub fn config(&self) -> &DitConfig {
        &self.cfg
    }

    fn kv_of(&self, memory: &Tensor) -> Result<DitCondition> {
        let kv = self.blocks.iter().map(|b| b.memory_kv(memory)).collect::<Result<Vec<_>>>()?;
        Ok(DitCondition { kv, batch: memory.dim(0)? })
    }

    /// Prepares image tokens (B, N, token_dim) as a condition. `keep` (B,) of 0/1 floats, if
    /// given, replaces the rows where it is 0 with the null condition (condition dropout).
    pub fn condition(&self, image_tokens: &Tensor, keep: Option<&Tensor>) -> Result<DitCondition> {
        let (b, n, c) = image_tokens.dims3()?;
        let enc = &self.cfg.image_encoder;
        if (n, c) != (enc.num_tokens(), enc.token_dim()) {
            return Err(ModelError::bad_input(format!(
                "image tokens are {n} x {c}, the DiT expects {} x {}",
                enc.num_tokens(),
                enc.token_dim()
            )));
        }
        let memory = self.cond_proj.forward(&self.cond_norm.forward(image_tokens)?)?;
        let memory = match keep {
            None => memory,
            Some(keep) => {
                if keep.dims() != [b] {
                    return Err(ModelError::bad_input(format!(
                        "keep mask has shape {:?}, expected ({b},)",
                        keep.dims()
                    )));
                }
                let keep = keep.to_dtype(DType::F32)?.reshape((b, 1, 1))?;
                let drop = (1.0 - &keep)?;
                (memory.broadcast_mul(&keep)?
                    + self.null_tokens.unsqueeze(0)?.broadcast_mul(&drop)?)?
            }
        };
        self.kv_of(&memory)
    }

    /// The null ("no image") condition for a batch of `batch` rows.
    pub fn null_condition(&self, batch: usize) -> Result<DitCondition> {
        let (n, w) = self.null_tokens.dims2()?;
        let memory = self.null_tokens.unsqueeze(0)?.broadcast_as((batch, n, w))?.contiguous()?;
        self.kv_of(&memory)
    }

    /// Velocity at normalized latents x_t (B, K, latent_dim) and times t (B,) in [0, 1].
    pub fn forward(&self, x: &Tensor, t: &Tensor, cond: &DitCondition) -> Result<Tensor> {
        let (b, k, d) = x.dims3()?;
        if (k, d) != (self.cfg.num_latents, self.cfg.latent_dim) {
            return Err(ModelError::bad_input(format!(
                "latents are {k} x {d}, the DiT expects {} x {}",
                self.cfg.num_latents, self.cfg.latent_dim
            )));
        }
        if t.dims() != [b] || cond.batch != b {
            return Err(ModelError::bad_input(format!(
                "batch mismatch: latents {b}, timesteps {:?}, condition {}",
                t.dims(),
                cond.batch
            )));
        }
        let temb = timestep_embedding(t, self.cfg.timestep_frequencies)?;
        let c = self.time_mlp.forward(&temb)?.silu()?;
        let mut h = self.latent_in.forward(x)?;
        for (block, kv) in self.blocks.iter().zip(&cond.kv) {
            h = block.forward(&h, &c, kv)?;
        }
        let m = chunks(&self.final_modulation.forward(&c)?, 2)?;
        self.out.forward(&self.final_norm.modulate(&h, &m[0], &m[1])?)
    }
}

impl VelocityField for Dit {
    type Condition = DitCondition;

    fn velocity(&self, x_t: &Tensor, t: &Tensor, cond: &DitCondition) -> Result<Tensor> {
        self.forward(x_t, t, cond)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diffusion::checkpoint::inference_weights;
    use candle_nn::VarMap;

    fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
        crate::model::testing::max_abs_diff(a, b)
    }

    fn randn(shape: &[usize]) -> Tensor {
        Tensor::randn(0f32, 1.0, shape, &Device::Cpu).unwrap()
    }

    #[test]
    fn a_fresh_block_is_the_identity_and_a_fresh_dit_outputs_zero() {
        let cfg = DitConfig::micro();
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let dit = Dit::new(&cfg, vb).unwrap();
        let block = &dit.blocks[0];
        let x = randn(&[3, cfg.num_latents, cfg.width]);
        let c = randn(&[3, cfg.width]);
        let cond = dit.null_condition(3).unwrap();
        let y = block.forward(&x, &c, &cond.kv[0]).unwrap();
        assert_eq!(max_abs_diff(&x, &y), 0.0);

        let x = randn(&[3, cfg.num_latents, cfg.latent_dim]);
        let t = Tensor::new(&[0.1f32, 0.5, 0.9], &Device::Cpu).unwrap();
        let v = dit.forward(&x, &t, &cond).unwrap();
        assert_eq!(v.dims(), x.dims());
        assert_eq!(v.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap(), 0.0);
    }

    #[test]
    fn shapes_for_batch_1_and_8_with_random_weights() {
        let cfg = DitConfig::micro();
        let varmap = VarMap::new();
        Dit::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu)).unwrap();
        // Give the zero-initialized layers weights, so the test sees a non-trivial output.
        for var in varmap.all_vars() {
            var.set(&var.randn_like(0.0, 0.1).unwrap()).unwrap();
        }
        let dit = Dit::new(&cfg, inference_weights(&varmap, &Device::Cpu)).unwrap();
        let enc = &cfg.image_encoder;
        for b in [1, 8] {
            let x = randn(&[b, cfg.num_latents, cfg.latent_dim]);
            let t = Tensor::ones(b, DType::F32, &Device::Cpu).unwrap();
            let tokens = randn(&[b, enc.num_tokens(), enc.token_dim()]);
            let cond = dit.condition(&tokens, None).unwrap();
            let v = dit.forward(&x, &t, &cond).unwrap();
            assert_eq!(v.dims(), &[b, cfg.num_latents, cfg.latent_dim]);
            let null = dit.forward(&x, &t, &dit.null_condition(b).unwrap()).unwrap();
            assert!(max_abs_diff(&v, &null) > 1e-4, "the image must change the velocity");

            // A keep mask of zeros is exactly the null condition; of ones, the image.
            let zeros = Tensor::zeros(b, DType::F32, &Device::Cpu).unwrap();
            let dropped = dit.condition(&tokens, Some(&zeros)).unwrap();
            assert!(max_abs_diff(&dit.forward(&x, &t, &dropped).unwrap(), &null) < 1e-5);
            let ones = Tensor::ones(b, DType::F32, &Device::Cpu).unwrap();
            let kept = dit.condition(&tokens, Some(&ones)).unwrap();
            assert!(max_abs_diff(&dit.forward(&x, &t, &kept).unwrap(), &v) < 1e-5);
        }
    }

    #[test]
    fn wrong_shapes_are_errors_not_panics() {
        let cfg = DitConfig::micro();
        let varmap = VarMap::new();
        let dit =
            Dit::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu)).unwrap();
        let cond = dit.null_condition(2).unwrap();
        let t = Tensor::ones(2, DType::F32, &Device::Cpu).unwrap();
        let bad = randn(&[2, cfg.num_latents + 1, cfg.latent_dim]);
        assert!(matches!(dit.forward(&bad, &t, &cond), Err(ModelError::BadInput(_))));
        let x = randn(&[3, cfg.num_latents, cfg.latent_dim]);
        assert!(matches!(dit.forward(&x, &t, &cond), Err(ModelError::BadInput(_))));
        assert!(matches!(dit.condition(&randn(&[1, 2, 3]), None), Err(ModelError::BadInput(_))));
    }

    #[test]
    fn timestep_embedding_is_cos_then_sin() {
        let t = Tensor::new(&[0.0f32, 0.25], &Device::Cpu).unwrap();
        let e = timestep_embedding(&t, 4).unwrap().to_vec2::<f32>().unwrap();
        assert_eq!(e[0], vec![1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
        // Frequency 0 is 1: cos(250), sin(250).
        assert!((e[1][0] - 250f32.cos()).abs() < 1e-4 && (e[1][4] - 250f32.sin()).abs() < 1e-4);
    }
}
