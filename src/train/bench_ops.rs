//! A pass's building blocks timed one by one (`meshstream-train bench --ops`), forward and
//! backward, at the shapes of one pass of a training step: which of candle's kernels make a
//! step slow. Why: on an H200 a whole step runs at 3.9% of PyTorch's speed on the same
//! architecture (`docs/decisions.md`, "Training on a GPU"), and the phases of
//! [`super::bench::bench_train_step`] only say which part of the model holds the slow kernels.
//!
//! Each block runs on fresh random variables, the decoder's widths, and backward from the sum
//! of its output. Matrix products' share shows as TFLOP/s: the floating-point operations of
//! the matmuls inside (forward, and twice that backward) over the block's time.

use std::time::Instant;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use serde::Serialize;

use crate::model::attention::{
    CrossAttention, Dense, Mlp, Norm, Rope, SelfAttention, attend, causal_mask,
};
use crate::model::fused::softmax;
use crate::model::{FaceConfig, ModelError};

use super::TrainError;

/// One block's seconds per run, averaged over the timed runs.
#[derive(Debug, Clone, Serialize)]
pub struct OpTime {
    pub op: &'static str,
    /// The input's dimensions, e.g. `[18, 401, 256]`.
    pub shape: String,
    pub forward_s: f64,
    pub backward_s: f64,
    /// Floating-point operations of the matrix products in one forward pass (0: none).
    pub matmul_flops: f64,
}

impl OpTime {
    /// The matrix products' rate over forward and backward (whose products are twice the
    /// forward's); `None` for a block without any.
    pub fn matmul_tflops(&self) -> Option<f64> {
        let seconds = self.forward_s + self.backward_s;
        (self.matmul_flops > 0.0 && seconds > 0.0).then(|| 3.0 * self.matmul_flops / seconds / 1e12)
    }
}

/// The decoder's shapes in one pass of about `rows` face positions: sequences as long as the
/// face limit allows (start token included), as many as come nearest to `rows`.
struct PassShape {
    batch: usize,
    len: usize,
    width: usize,
    hidden: usize,
    heads: usize,
    latents: usize,
}

impl PassShape {
    fn new(cfg: &FaceConfig, rows: usize) -> Self {
        let len = (cfg.max_faces + 1).min(rows).max(1);
        Self {
            batch: ((rows + len / 2) / len).max(1),
            len,
            width: cfg.decoder.width,
            hidden: cfg.decoder.mlp_hidden,
            heads: cfg.decoder.heads,
            latents: cfg.num_latents,
        }
    }

    fn rows(&self) -> f64 {
        (self.batch * self.len) as f64
    }

    /// One head's scores or values over the whole causal square, for all heads.
    fn attention_flops(&self) -> f64 {
        let head_dim = (self.width / self.heads) as f64;
        2.0 * 2.0 * (self.batch * self.heads) as f64 * (self.len * self.len) as f64 * head_dim
    }

    fn projection_flops(&self, inputs: usize, outputs: usize) -> f64 {
        2.0 * self.rows() * (inputs * outputs) as f64
    }
}

/// One block: its name, its input's dimensions, its matrix products' forward operations, and
/// its forward pass.
struct Block<'a> {
    op: &'static str,
    shape: String,
    matmul_flops: f64,
    run: Box<dyn Fn() -> Result<Tensor, ModelError> + 'a>,
}

/// Times each block `repeats` times (after one untimed run) at the shapes of a pass of `rows`
/// face positions of a model configured as `cfg`.
pub fn bench_ops(
    cfg: &FaceConfig,
    rows: usize,
    repeats: usize,
    device: &Device,
) -> Result<Vec<OpTime>, TrainError> {
    let s = PassShape::new(cfg, rows);
    let (b, t, d, h) = (s.batch, s.len, s.width, s.hidden);
    let hd = d / s.heads;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, device);
    let mask = causal_mask(t, device)?;
    let rope = Rope::new(hd, t, cfg.rope_theta, device)?;
    let up = Dense::new(d, h, true, vb.pp("up"))?;
    let mlp = Mlp::new(d, h, d, vb.pp("mlp"))?;
    let norm = Norm::new(d, cfg.norm_eps, vb.pp("norm"))?;
    let self_attn = SelfAttention::new(d, s.heads, vb.pp("self"))?;
    let cross_attn = CrossAttention::new(d, s.heads, vb.pp("cross"))?;

    let x = random(&[b, t, d], device)?;
    let flat = x.reshape((b * t, d))?;
    let weight = random(&[d, h], device)?;
    let memory = random(&[b, s.latents, d], device)?;
    let heads = [b, s.heads, t, hd];
    let (q, k, v) = (random(&heads, device)?, random(&heads, device)?, random(&heads, device)?);
    let scores = random(&[b, s.heads, t, t], device)?;

    let x_shape = format!("{:?}", x.dims());
    let cross_flops = 2.0 * s.projection_flops(d, d)
        + 2.0 * (b * s.latents * d * 2 * d) as f64
        + s.attention_flops() * s.latents as f64 / t as f64;
    let blocks = [
        Block {
            op: "matmul",
            shape: format!("{:?} x {:?}", flat.dims(), weight.dims()),
            matmul_flops: s.projection_flops(d, h),
            run: Box::new(|| Ok(flat.matmul(&weight)?)),
        },
        Block {
            op: "linear with bias",
            shape: x_shape.clone(),
            matmul_flops: s.projection_flops(d, h),
            run: Box::new(|| up.forward(&x)),
        },
        Block {
            op: "MLP (SiLU)",
            shape: x_shape.clone(),
            matmul_flops: 2.0 * s.projection_flops(d, h),
            run: Box::new(|| mlp.forward(&x)),
        },
        Block {
            op: "layer norm",
            shape: x_shape.clone(),
            matmul_flops: 0.0,
            run: Box::new(|| norm.forward(&x)),
        },
        Block {
            op: "softmax",
            shape: format!("{:?}", scores.dims()),
            matmul_flops: 0.0,
            run: Box::new(|| softmax(&scores)),
        },
        Block {
            op: "causal attention core",
            shape: format!("{:?}", q.dims()),
            matmul_flops: s.attention_flops(),
            run: Box::new(|| attend(&q, &k, &v, Some(&mask))),
        },
        Block {
            op: "self-attention (RoPE)",
            shape: x_shape.clone(),
            matmul_flops: s.projection_flops(d, 3 * d)
                + s.projection_flops(d, d)
                + s.attention_flops(),
            run: Box::new(|| self_attn.forward(&x, Some(&rope), Some(&mask))),
        },
        Block {
            op: "cross-attention",
            shape: format!("{x_shape} to {:?}", memory.dims()),
            matmul_flops: cross_flops,
            run: Box::new(|| {
                let (k, v) = cross_attn.memory_kv(&memory)?;
                cross_attn.forward(&x, &k, &v)
            }),
        },
    ];
    blocks
        .into_iter()
        .map(|block| {
            let (forward_s, backward_s) = time_block(&*block.run, repeats, device)?;
            Ok(OpTime {
                op: block.op,
                shape: block.shape,
                forward_s,
                backward_s,
                matmul_flops: block.matmul_flops,
            })
        })
        .collect()
}

/// Mean seconds of a block's forward pass and of the backward pass from its output's sum, each
/// waited out on the device. The sum itself is timed by neither: candle's CUDA kernel reduces
/// to one value in one thread block, which over a pass's output takes longer than the block.
fn time_block(
    run: &dyn Fn() -> Result<Tensor, ModelError>,
    repeats: usize,
    device: &Device,
) -> Result<(f64, f64), TrainError> {
    let (mut forward, mut backward) = (0.0, 0.0);
    for index in 0..=repeats {
        device.synchronize()?;
        let started = Instant::now();
        let y = run()?;
        device.synchronize()?;
        let forwarded = Instant::now();
        let sum = y.sum_all()?;
        device.synchronize()?;
        let summed = Instant::now();
        let grads = sum.backward()?;
        device.synchronize()?;
        let done = Instant::now();
        drop(grads);
        if index > 0 {
            forward += (forwarded - started).as_secs_f64();
            backward += (done - summed).as_secs_f64();
        }
    }
    let n = repeats.max(1) as f64;
    Ok((forward / n, backward / n))
}

fn random(dims: &[usize], device: &Device) -> candle_core::Result<Tensor> {
    Ok(Var::randn(0f32, 1.0, dims, device)?.as_tensor().clone())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_block_is_timed_forward_and_backward() {
        let cfg = FaceConfig::micro();
        let times = bench_ops(&cfg, 100, 1, &Device::Cpu).unwrap();
        let names: std::collections::HashSet<_> = times.iter().map(|t| t.op).collect();
        assert_eq!(names.len(), times.len(), "a block timed twice: {times:?}");
        assert!(names.contains("softmax") && names.contains("cross-attention"), "{names:?}");
        for t in &times {
            assert!(t.forward_s > 0.0 && t.backward_s > 0.0, "{t:?}");
            let has_matmuls = !matches!(t.op, "layer norm" | "softmax");
            assert_eq!(t.matmul_tflops().is_some(), has_matmuls, "{t:?}");
        }
        // A pass of 100 rows holds two whole sequences of the micro model's 41 positions.
        assert!(times[0].shape.starts_with("[82, 32]"), "{}", times[0].shape);
    }
}
