//! Building blocks shared by the encoder, the face decoder and the per-coordinate baseline:
//! layer norm, MLP, rotary positions, self- and cross-attention.
//!
//! candle's fused RoPE has no backward pass, so it runs only when nothing in its input tracks
//! gradients; while training, the differentiable formula runs instead. The two paths agree to
//! float rounding. The softmax and the layer norm's normalization have backward passes of
//! their own ([`super::fused`]).

use std::sync::Arc;

use candle_core::quantized::{GgmlDType, QTensor};
use candle_core::{D, DType, Device, Tensor};
use candle_nn::kv_cache::KvCache;
use candle_nn::{Init, Linear, VarBuilder};

use super::few_rows;
use super::fused::{normalize, softmax};
use super::ragged::attend_rows;
use super::{ModelError, Result};

fn tracks(xs: &[&Tensor]) -> bool {
    xs.iter().any(|t| t.track_op())
}

/// Layer norm with weight and bias.
#[derive(Debug, Clone)]
pub struct Norm {
    weight: Tensor,
    bias: Tensor,
    eps: f32,
}

impl Norm {
    pub fn new(dim: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get_with_hints(dim, "weight", Init::Const(1.0))?,
            bias: vb.get_with_hints(dim, "bias", Init::Const(0.0))?,
            eps: eps as f32,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if tracks(&[x, &self.weight, &self.bias]) {
            Ok(normalize(x, self.eps)?.broadcast_mul(&self.weight)?.broadcast_add(&self.bias)?)
        } else {
            Ok(candle_nn::ops::layer_norm(&x.contiguous()?, &self.weight, &self.bias, self.eps)?)
        }
    }
}

/// A linear layer stored as candle's `Linear` ((out, in) weight named `weight`, optional
/// `bias`). For inference it also keeps a contiguous (in, out) copy: the gemm behind candle's
/// matmul is several times faster on many rows with that layout than with the transposed view
/// `Linear` multiplies by. A few rows go the other way round (see [`FEW_ROWS`]). A quantized
/// layer keeps its weight in a GGUF block type (see `super::quantize`), multiplied by candle's
/// quantized CPU kernels.
#[derive(Debug, Clone)]
pub enum Dense {
    Train(Linear),
    Infer {
        /// The weight's name without `.weight` (the layer's scope in the checkpoint).
        name: String,
        /// (out, in), contiguous.
        weight: Tensor,
        /// (in, out), contiguous.
        weight_t: Tensor,
        /// (out, in) in f16, when every weight is an f16 value (the shipped model's are) and
        /// the layer is on the CPU: what [`few_rows::linear`] reads, half the bytes.
        weight_f16: Option<Tensor>,
        bias: Option<Tensor>,
    },
    Quantized {
        name: String,
        /// (out, in), as stored in a GGUF file.
        weight: Arc<QTensor>,
        bias: Option<Tensor>,
    },
}

impl Dense {
    pub fn new(input: usize, output: usize, bias: bool, vb: VarBuilder) -> Result<Self> {
        let name = vb.prefix();
        let lin = if bias {
            candle_nn::linear(input, output, vb)?
        } else {
            candle_nn::linear_no_bias(input, output, vb)?
        };
        if lin.weight().track_op() {
            return Ok(Self::Train(lin));
        }
        Self::inference(name, lin.weight(), lin.bias().cloned())
    }

    /// The layer's scope in the checkpoint (its weight is `{name}.weight`).
    pub fn name(&self) -> Option<&str> {
        match self {
            Self::Train(_) => None,
            Self::Infer { name, .. } | Self::Quantized { name, .. } => Some(name),
        }
    }

    /// (in, out) features.
    pub fn features(&self) -> Result<(usize, usize)> {
        Ok(match self {
            Self::Train(lin) => lin.weight().t()?.dims2()?,
            Self::Infer { weight_t, .. } => weight_t.dims2()?,
            Self::Quantized { weight, .. } => {
                let (out, input) = weight.shape().dims2()?;
                (input, out)
            }
        })
    }

    /// The weight (out, in) and bias as f32 values, whatever the layer stores (a quantized
    /// weight dequantized), detached from any training graph.
    pub fn values(&self) -> Result<(Tensor, Option<Tensor>)> {
        Ok(match self {
            Self::Train(lin) => (lin.weight().detach(), lin.bias().map(Tensor::detach)),
            Self::Infer { weight, bias, .. } => (weight.clone(), bias.clone()),
            Self::Quantized { weight, bias, .. } => {
                (weight.dequantize(&weight.device())?, bias.clone())
            }
        })
    }

    /// Whether the layer's weights are training variables (they change as it trains).
    pub fn is_training(&self) -> bool {
        matches!(self, Self::Train(_))
    }

    /// An f32 inference layer of the weight (out, in), read or derived from others (its name
    /// says which).
    pub(crate) fn inference(name: String, weight: &Tensor, bias: Option<Tensor>) -> Result<Self> {
        Ok(Self::Infer {
            name,
            weight: weight.contiguous()?,
            weight_t: weight.t()?.contiguous()?,
            weight_f16: few_rows::exact_f16(weight)?,
            bias,
        })
    }

    /// The quantized weight, if this layer has one.
    pub fn quantized_weight(&self) -> Option<&Arc<QTensor>> {
        match self {
            Self::Quantized { weight, .. } => Some(weight),
            _ => None,
        }
    }

    /// Quantizes an inference layer's weight to `dtype`. Returns false, leaving the layer as
    /// it is, when its input features are not a multiple of the block size (a block never
    /// spans two rows of the weight).
    pub fn quantize(&mut self, dtype: GgmlDType) -> Result<bool> {
        let Self::Infer { name, weight, bias, .. } = self else {
            return Err(ModelError::bad_input(format!(
                "only an f32 inference layer can be quantized ({})",
                self.name().unwrap_or("a training layer")
            )));
        };
        if weight.dim(1)? % dtype.block_size() != 0 {
            return Ok(false);
        }
        let weight = Arc::new(QTensor::quantize(weight, dtype)?);
        *self = Self::Quantized { name: std::mem::take(name), weight, bias: bias.take() };
        Ok(true)
    }

    /// Replaces an inference layer's weight by an already quantized one of the same shape
    /// (read from a quantized model file).
    pub fn set_quantized(&mut self, weight: Arc<QTensor>) -> Result<()> {
        let (input, output) = self.features()?;
        let Self::Infer { name, bias, .. } = self else {
            return Err(ModelError::bad_input(
                "only an f32 inference layer takes a quantized weight",
            ));
        };
        if weight.shape().dims() != [output, input] {
            return Err(ModelError::bad_input(format!(
                "quantized weight {:?} for {name}, which is ({output}, {input})",
                weight.shape().dims()
            )));
        }
        *self = Self::Quantized { name: std::mem::take(name), weight, bias: bias.take() };
        Ok(())
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dims = x.dims();
        let (rows, input) = (x.elem_count() / dims[dims.len() - 1], dims[dims.len() - 1]);
        // (rows, out) -> x's dimensions with the last one `out`.
        let as_x = |y: Tensor| -> Result<Tensor> {
            let mut out_dims = dims.to_vec();
            out_dims[dims.len() - 1] = y.dim(1)?;
            Ok(y.reshape(out_dims)?)
        };
        match self {
            Self::Train(lin) => {
                // As one 2-D matmul: candle's `Linear` broadcasts the weight over the batch,
                // whose backward pass then materializes a weight gradient per batch entry.
                let y = x.reshape((rows, input))?.matmul(&lin.weight().t()?)?;
                as_x(add_bias(y, lin.bias())?)
            }
            Self::Infer { weight, weight_t, weight_f16, bias, .. } => {
                if rows <= FEW_ROWS && x.device().is_cpu() {
                    let x = x.contiguous()?.reshape((rows, input))?;
                    let narrowest = weight_f16.as_ref().unwrap_or(weight);
                    if let Some(y) = few_rows::linear(&x, narrowest, bias.as_ref())? {
                        return as_x(y);
                    }
                    // (W x^T)^T: the rows become the gemm's narrow side.
                    let y = weight.matmul(&x.t()?)?.t()?;
                    return as_x(add_bias(y, bias.as_ref())?);
                }
                // CUDA's matmul takes only row- or column-major operands; a context built by
                // concatenating narrowed tensors is neither (the CPU takes any layout).
                let y = x.contiguous()?.broadcast_matmul(weight_t)?;
                add_bias(y, bias.as_ref())
            }
            Self::Quantized { weight, bias, .. } => {
                // What `QMatMul::forward` does for a quantized weight, without wrapping it.
                let y = x.contiguous()?.apply_op1_no_bwd(weight.as_ref())?;
                add_bias(y, bias.as_ref())
            }
        }
    }
}

/// Up to this many rows, an f32 layer multiplies on the CPU as `(W x^T)^T` (up to
/// [`few_rows::MAX_ROWS`], in a kernel of its own, [`few_rows::linear`]): the gemm behind
/// candle's matmul pads a few rows up to its kernel's 8 or 16, but takes its 4 columns as
/// they are. Decoding one step on one thread (`bench decode`), that was 1.25x the faces/s
/// at batch 4, 1.3x at batch 16 and 1.2x at 32, but 0.77x at 128 (and 0.5x encoding 1,024
/// points): many rows keep `x W^T`.
const FEW_ROWS: usize = 32;

fn add_bias(y: Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    Ok(match bias {
        Some(b) => y.broadcast_add(b)?,
        None => y,
    })
}

/// Two linear layers with a SiLU between (candle's GELU kernels cost ten times as much on the
/// CPU, a visible share of a decode step).
#[derive(Debug, Clone)]
pub struct Mlp {
    fc1: Dense,
    fc2: Dense,
}

impl Mlp {
    pub fn new(input: usize, hidden: usize, output: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            fc1: Dense::new(input, hidden, true, vb.pp("fc1"))?,
            fc2: Dense::new(hidden, output, true, vb.pp("fc2"))?,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.fc2.forward(&self.fc1.forward(x)?.silu()?)
    }

    pub fn dense_mut(&mut self) -> Vec<&mut Dense> {
        vec![&mut self.fc1, &mut self.fc2]
    }

    /// The first and the second layer.
    pub fn layers(&self) -> (&Dense, &Dense) {
        (&self.fc1, &self.fc2)
    }
}

/// Rotary position tables for positions `0..max_positions`.
#[derive(Debug, Clone)]
pub struct Rope {
    cos: Tensor,
    sin: Tensor,
    max_positions: usize,
}

impl Rope {
    pub fn new(head_dim: usize, max_positions: usize, theta: f64, device: &Device) -> Result<Self> {
        let half = head_dim / 2;
        let inv_freq: Vec<f32> =
            (0..half).map(|i| (theta.powf(-((2 * i) as f64) / head_dim as f64)) as f32).collect();
        let inv_freq = Tensor::from_vec(inv_freq, (1, half), device)?;
        let pos = Tensor::arange(0u32, max_positions as u32, device)?
            .to_dtype(DType::F32)?
            .reshape((max_positions, 1))?;
        let angles = pos.broadcast_mul(&inv_freq)?;
        Ok(Self { cos: angles.cos()?, sin: angles.sin()?, max_positions })
    }

    pub fn max_positions(&self) -> usize {
        self.max_positions
    }

    fn check(&self, position: usize) -> Result<()> {
        if position >= self.max_positions {
            return Err(ModelError::SequenceTooLong { position, limit: self.max_positions });
        }
        Ok(())
    }

    /// `x`: (B, H, T, hd) at positions `0..T`.
    pub fn apply_prefix(&self, x: &Tensor) -> Result<Tensor> {
        let t = x.dim(2)?;
        if t == 0 {
            return Ok(x.clone());
        }
        self.check(t - 1)?;
        let cos = self.cos.narrow(0, 0, t)?;
        let sin = self.sin.narrow(0, 0, t)?;
        if x.track_op() {
            rope_differentiable(x, &cos.unsqueeze(0)?, &sin.unsqueeze(0)?)
        } else {
            Ok(candle_nn::rotary_emb::rope(&x.contiguous()?, &cos, &sin)?)
        }
    }

    /// The tables' rows at `positions` (row `r` of a batch at `positions[r]`), looked up once
    /// per decoder step for every layer's queries and keys.
    pub fn rows(&self, positions: &[usize]) -> Result<RopeRows> {
        if let Some(&p) = positions.iter().max() {
            self.check(p)?;
        }
        let idx: Vec<u32> = positions.iter().map(|&p| p as u32).collect();
        let idx = Tensor::from_vec(idx, positions.len(), self.cos.device())?;
        Ok(RopeRows {
            cos: self.cos.index_select(&idx, 0)?.unsqueeze(1)?,
            sin: self.sin.index_select(&idx, 0)?.unsqueeze(1)?,
        })
    }
}

/// Rotary tables for one position per batch row: (B, 1, hd/2) each.
#[derive(Debug, Clone)]
pub struct RopeRows {
    cos: Tensor,
    sin: Tensor,
}

impl RopeRows {
    /// `x`: (B, H, 1, hd).
    pub fn apply(&self, x: &Tensor) -> Result<Tensor> {
        if x.track_op() {
            rope_differentiable(x, &self.cos, &self.sin)
        } else {
            Ok(candle_nn::rotary_emb::rope(&x.contiguous()?, &self.cos, &self.sin)?)
        }
    }
}

/// The rotate-half RoPE of candle's `rope`, built from differentiable ops.
/// `cos`/`sin`: (1 or B, T, hd/2).
fn rope_differentiable(x: &Tensor, cos: &Tensor, sin: &Tensor) -> Result<Tensor> {
    let cos = Tensor::cat(&[cos, cos], D::Minus1)?.unsqueeze(1)?;
    let sin = Tensor::cat(&[sin, sin], D::Minus1)?.unsqueeze(1)?;
    let half = x.dim(D::Minus1)? / 2;
    let x1 = x.narrow(D::Minus1, 0, half)?;
    let x2 = x.narrow(D::Minus1, half, half)?;
    let rotated = Tensor::cat(&[&x2.neg()?, &x1], D::Minus1)?;
    Ok((x.broadcast_mul(&cos)? + rotated.broadcast_mul(&sin)?)?)
}

/// The most attention scores (f32, 1 MiB) [`attend`] makes at once on the CPU; past them it
/// takes one head at a time, with the same products. Why: the engine maps blocks from 1 MiB up
/// on their own ([`crate::engine::MAP_FROM_BYTES`]), so the encoder's cross-attention (4 heads
/// of 128 queries by 1,024 points, three 2 MiB intermediates) faulted in and zeroed fresh pages
/// in every pass; a head's 512 KiB come from the heap and stay in the cache between the
/// matmuls and the softmax. Encoding a whole mesh's 4 clouds took 32 ms against 37-42
/// (`docs/decisions.md`, "The encoder's attention takes a head at a time").
const CPU_SCORES_AT_ONCE: usize = crate::engine::MAP_FROM_BYTES / size_of::<f32>();

/// Scaled dot-product attention. q: (B, H, Tq, hd), k/v: (B, H, Tk, hd), `mask` additive and
/// broadcastable to (B, H, Tq, Tk).
pub fn attend(q: &Tensor, k: &Tensor, v: &Tensor, mask: Option<&Tensor>) -> Result<Tensor> {
    let (b, heads, tq, _) = q.dims4()?;
    let scores = b * heads * tq * k.dim(2)?;
    // A mask may differ by head, and training keeps every op for its gradients: both whole.
    if heads == 1
        || scores <= CPU_SCORES_AT_ONCE
        || mask.is_some()
        || q.track_op()
        || !q.device().is_cpu()
    {
        return attend_at_once(q, k, v, mask);
    }
    let head = |t: &Tensor, h| t.narrow(1, h, 1);
    let outs = (0..heads)
        .map(|h| attend_at_once(&head(q, h)?, &head(k, h)?, &head(v, h)?, None))
        .collect::<Result<Vec<_>>>()?;
    Ok(Tensor::cat(&outs, 1)?)
}

/// [`attend`] for every head in one pass.
fn attend_at_once(q: &Tensor, k: &Tensor, v: &Tensor, mask: Option<&Tensor>) -> Result<Tensor> {
    let scale = 1.0 / (q.dim(D::Minus1)? as f64).sqrt();
    let w = (q.matmul(&k.t()?)? * scale)?;
    let w = match mask {
        Some(m) => w.broadcast_add(m)?,
        None => w,
    };
    Ok(softmax(&w)?.matmul(v)?)
}

/// Additive causal mask (T, T): 0 on and below the diagonal, -inf above.
pub fn causal_mask(t: usize, device: &Device) -> Result<Tensor> {
    let mask: Vec<f32> = (0..t)
        .flat_map(|i| (0..t).map(move |j| if j > i { f32::NEG_INFINITY } else { 0.0 }))
        .collect();
    Ok(Tensor::from_vec(mask, (t, t), device)?)
}

/// (B, T, H*hd) -> (B, H, T, hd), contiguous.
fn split_heads(x: &Tensor, heads: usize) -> Result<Tensor> {
    let (b, t, d) = x.dims3()?;
    Ok(x.reshape((b, t, heads, d / heads))?.transpose(1, 2)?.contiguous()?)
}

/// (B, H, T, hd) -> (B, T, H*hd).
fn merge_heads(x: &Tensor) -> Result<Tensor> {
    let (b, h, t, hd) = x.dims4()?;
    Ok(x.transpose(1, 2)?.reshape((b, t, h * hd))?)
}

/// Multi-head self-attention with a fused qkv projection, optionally rotary.
#[derive(Debug, Clone)]
pub struct SelfAttention {
    qkv: Dense,
    out: Dense,
    heads: usize,
}

impl SelfAttention {
    pub fn new(dim: usize, heads: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            qkv: Dense::new(dim, 3 * dim, false, vb.pp("qkv"))?,
            out: Dense::new(dim, dim, false, vb.pp("out"))?,
            heads,
        })
    }

    pub fn dense_mut(&mut self) -> Vec<&mut Dense> {
        vec![&mut self.qkv, &mut self.out]
    }

    fn project(&self, x: &Tensor) -> Result<(Tensor, Tensor, Tensor)> {
        let (b, t, d) = x.dims3()?;
        let hd = d / self.heads;
        let qkv =
            self.qkv.forward(x)?.reshape((b, t, 3, self.heads, hd))?.permute((2, 0, 3, 1, 4))?;
        Ok((qkv.get(0)?.contiguous()?, qkv.get(1)?.contiguous()?, qkv.get(2)?.contiguous()?))
    }

    /// Whole sequences: x (B, T, d) at positions `0..T`.
    pub fn forward(
        &self,
        x: &Tensor,
        rope: Option<&Rope>,
        mask: Option<&Tensor>,
    ) -> Result<Tensor> {
        let (q, k, v) = self.project(x)?;
        let (q, k) = match rope {
            Some(r) => (r.apply_prefix(&q)?, r.apply_prefix(&k)?),
            None => (q, k),
        };
        self.out.forward(&merge_heads(&attend(&q, &k, &v, mask)?)?)
    }

    /// One new position per row: x (B, 1, d); row `r` is at the position `rope` was looked up
    /// for and owns `caches[r]`, which this call extends by one entry.
    pub fn step(&self, x: &Tensor, rope: &RopeRows, caches: &mut [&mut KvCache]) -> Result<Tensor> {
        let (q, k, v) = self.project(x)?;
        let q = rope.apply(&q)?;
        let k = rope.apply(&k)?;
        let kv = caches
            .iter_mut()
            .enumerate()
            .map(|(r, cache)| {
                // Detached: a cache must never hold on to an autograd graph.
                Ok(cache.append(&k.narrow(0, r, 1)?.detach(), &v.narrow(0, r, 1)?.detach())?)
            })
            .collect::<Result<Vec<_>>>()?;
        self.out.forward(&merge_heads(&attend_rows(&q, &kv)?)?)
    }
}

/// Multi-head cross-attention from a sequence to a memory of the same width.
#[derive(Debug, Clone)]
pub struct CrossAttention {
    q: Dense,
    kv: Dense,
    out: Dense,
    heads: usize,
}

impl CrossAttention {
    pub fn new(dim: usize, heads: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            q: Dense::new(dim, dim, false, vb.pp("q"))?,
            kv: Dense::new(dim, 2 * dim, false, vb.pp("kv"))?,
            out: Dense::new(dim, dim, false, vb.pp("out"))?,
            heads,
        })
    }

    pub fn dense_mut(&mut self) -> Vec<&mut Dense> {
        vec![&mut self.q, &mut self.kv, &mut self.out]
    }

    /// Keys and values of a memory (B, K, d): two (B, H, K, hd) tensors.
    pub fn memory_kv(&self, memory: &Tensor) -> Result<(Tensor, Tensor)> {
        let (b, k, d) = memory.dims3()?;
        let hd = d / self.heads;
        let kv = self
            .kv
            .forward(memory)?
            .reshape((b, k, 2, self.heads, hd))?
            .permute((2, 0, 3, 1, 4))?;
        Ok((kv.get(0)?.contiguous()?, kv.get(1)?.contiguous()?))
    }

    /// x (B, T, d) attends to the memory keys/values of the same batch.
    pub fn forward(&self, x: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
        let q = split_heads(&self.q.forward(x)?, self.heads)?;
        self.out.forward(&merge_heads(&attend(&q, k, v, None)?)?)
    }

    /// This layer folded onto the latents that `up` lifts to its memory, for decoding one
    /// position at a time (see [`LatentCrossAttention`]). Its projections have no biases (see
    /// [`Self::new`]); `up`'s bias is folded in.
    pub fn on_latents(&self, up: &Dense) -> Result<LatentCrossAttention> {
        // In f64, so that the folded weights round once.
        let f64_of = |t: &Tensor| t.to_dtype(DType::F64);
        let (up_w, up_b) = up.values()?;
        let (u, lift) = (f64_of(&up_w)?, up_b.map(|b| f64_of(&b)).transpose()?);
        let (d, latent) = u.dims2()?;
        let (heads, hd) = (self.heads, d / self.heads);
        let wq = f64_of(&self.q.values()?.0)?.reshape((heads, hd, d))?;
        let wkv = f64_of(&self.kv.values()?.0)?;
        let (wk, wv) = (wkv.narrow(0, 0, d)?, wkv.narrow(0, d, d)?);
        let wo = f64_of(&self.out.values()?.0)?;
        // Head h's keys are latents x (Wk_h U)^T plus a constant, which the softmax drops, so
        // its scores are latents . (Wk_h U)^T q_h. The softmax scale stays head_dim's.
        let keys = wk.reshape((heads, hd, d))?.broadcast_matmul(&u)?;
        let scale = (latent as f64 / hd as f64).sqrt();
        let query = (keys.transpose(1, 2)?.matmul(&wq)? * scale)?.reshape((heads * latent, d))?;
        // Its output is Wo_h (Wv_h U) (weighted latents) + Wo_h Wv_h u, the weights summing to 1.
        let values = wv.reshape((heads, hd, d))?.broadcast_matmul(&u)?;
        let wo_h = wo.reshape((d, heads, hd))?.transpose(0, 1)?.contiguous()?;
        let out = wo_h.matmul(&values)?.transpose(0, 1)?.reshape((d, heads * latent))?;
        let bias =
            lift.map(|b| wo.matmul(&wv.matmul(&b.unsqueeze(1)?)?)?.squeeze(1)).transpose()?;
        let f32_of = |t: Tensor| t.to_dtype(DType::F32);
        let name = |from: &Dense| format!("{} folded onto the latents", from.name().unwrap_or("?"));
        Ok(LatentCrossAttention {
            query: Dense::inference(name(&self.q), &f32_of(query)?, None)?,
            out: Dense::inference(name(&self.out), &f32_of(out)?, bias.map(f32_of).transpose()?)?,
            heads,
        })
    }
}

/// Cross-attention folded onto the latents it attends to, as DeepSeek-V2's multi-head latent
/// attention absorbs its projections: each head's query is mapped to latent_dim and attends to
/// the latents themselves, and the weighted latents are mapped to the output. Why: decoding,
/// every row of a step reads its own memory; as keys and values of every layer that is 2 x
/// layers x K x width floats a row (1 MiB for the shipped model, read from memory at every
/// step), as latents K x latent_dim (32 KiB, one set for every layer). The two folded
/// projections replace the query and output ones (the same multiply-adds where heads x
/// latent_dim = width, as in the shipped model), and nothing is computed per sequence when it
/// starts.
#[derive(Debug, Clone)]
pub struct LatentCrossAttention {
    /// d -> heads x latent_dim.
    query: Dense,
    /// heads x latent_dim -> d.
    out: Dense,
    heads: usize,
}

impl LatentCrossAttention {
    /// x (B, 1, d); row `r` attends to its own latents `latents[r]` ((1, K, latent_dim) each),
    /// so rows of different requests share one call.
    pub fn step(&self, x: &Tensor, latents: &[Tensor]) -> Result<Tensor> {
        let q = split_heads(&self.query.forward(x)?, self.heads)?;
        let memories = latents
            .iter()
            .map(|l| {
                let (_, k, latent) = l.dims3()?;
                // Every head attends to the same latents: a view, not a copy.
                let l = l.unsqueeze(1)?.broadcast_as((1, self.heads, k, latent))?;
                Ok((l.clone(), l))
            })
            .collect::<Result<Vec<_>>>()?;
        self.out.forward(&merge_heads(&attend_rows(&q, &memories)?)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_nn::VarMap;

    #[test]
    fn fast_and_differentiable_paths_agree() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (2, 3, 5, 8), &dev).unwrap();
        let rope = Rope::new(8, 16, 10_000.0, &dev).unwrap();
        let fast = rope.apply_prefix(&x).unwrap();
        let cos = rope.cos.narrow(0, 0, 5).unwrap().unsqueeze(0).unwrap();
        let sin = rope.sin.narrow(0, 0, 5).unwrap().unsqueeze(0).unwrap();
        let slow = rope_differentiable(&x, &cos, &sin).unwrap();
        let diff = (fast - slow).unwrap().abs().unwrap().max_all().unwrap();
        assert!(diff.to_scalar::<f32>().unwrap() < 1e-5);

        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        let norm = Norm::new(8, 1e-5, vb.pp("n")).unwrap();
        let tracked = norm.forward(&x).unwrap();
        let detached =
            Norm { weight: norm.weight.detach(), bias: norm.bias.detach(), eps: norm.eps };
        let fast = detached.forward(&x).unwrap();
        let diff = (tracked - fast).unwrap().abs().unwrap().max_all().unwrap();
        assert!(diff.to_scalar::<f32>().unwrap() < 1e-5);
    }

    /// Past the scores it makes at once, attention takes a head at a time and gets the same
    /// values, bit for bit (reconstructions stay byte for byte the same), also for a batch.
    #[test]
    fn attention_a_head_at_a_time_is_attention_at_once() {
        let dev = Device::Cpu;
        for (b, tq, tk) in [(1, 128, 1024), (3, 64, 700)] {
            assert!(4 * b * tq * tk > CPU_SCORES_AT_ONCE);
            let q = Tensor::randn(0f32, 1.0, (b, 4, tq, 16), &dev).unwrap();
            let k = Tensor::randn(0f32, 1.0, (b, 4, tk, 16), &dev).unwrap();
            let v = Tensor::randn(0f32, 1.0, (b, 4, tk, 16), &dev).unwrap();
            let split = attend(&q, &k, &v, None).unwrap();
            let whole = attend_at_once(&q, &k, &v, None).unwrap();
            assert_eq!(split.dims(), whole.dims());
            let (split, whole) = (split.flatten_all().unwrap(), whole.flatten_all().unwrap());
            assert_eq!(split.to_vec1::<f32>().unwrap(), whole.to_vec1::<f32>().unwrap());
        }
    }

    #[test]
    fn positions_past_the_table_are_an_error() {
        let dev = Device::Cpu;
        let rope = Rope::new(4, 3, 10_000.0, &dev).unwrap();
        assert!(matches!(
            rope.rows(&[3]),
            Err(ModelError::SequenceTooLong { position: 3, limit: 3 })
        ));
    }
}
