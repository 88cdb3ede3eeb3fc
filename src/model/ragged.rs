//! Single-query attention for a batch of sequences that each attend to their own keys and
//! values (of different lengths): the decode step of continuous batching. On the CPU it runs as
//! one loop over plain slices, because a per-row chain of candle ops (narrow, matmul, softmax,
//! matmul for every row, head and layer) costs far more in op overhead than the arithmetic.

use candle_core::{Storage, Tensor};

use super::Result;
use super::attention::attend;

/// q: (B, H, 1, hd); `kv[r]`: row r's keys and values, (1, H, L_r, hd) each (views into a
/// cache, or one set broadcast to every head, are fine). Returns (B, H, 1, hd).
pub fn attend_rows(q: &Tensor, kv: &[(Tensor, Tensor)]) -> Result<Tensor> {
    if let Some(out) = attend_rows_cpu(q, kv)? {
        return Ok(out);
    }
    let outs = kv
        .iter()
        .enumerate()
        // Contiguous: CUDA's matmul takes no broadcast views (latents shared by every head).
        .map(|(r, (k, v))| attend(&q.narrow(0, r, 1)?, &k.contiguous()?, &v.contiguous()?, None))
        .collect::<Result<Vec<_>>>()?;
    Ok(Tensor::cat(&outs, 0)?)
}

/// Dot product with eight independent partial sums, so that the compiler can vectorize it (a
/// single running sum fixes the order of the additions and stays scalar).
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ca.remainder().iter().zip(cb.remainder()).map(|(x, y)| x * y).sum();
    for (x, y) in ca.zip(cb) {
        for ((s, a), b) in acc.iter_mut().zip(x).zip(y) {
            *s += a * b;
        }
    }
    acc.iter().sum::<f32>() + tail
}

/// A (1, H, L, hd) f32 tensor on the CPU whose last dimension is contiguous: its slice, offset
/// and strides of the head and position dimensions.
struct View<'a> {
    data: &'a [f32],
    offset: usize,
    head_stride: usize,
    pos_stride: usize,
    len: usize,
}

fn with_view<T>(t: &Tensor, heads: usize, hd: usize, f: impl FnOnce(&View) -> T) -> Option<T> {
    let (storage, layout) = t.storage_and_layout();
    let Storage::Cpu(cpu) = &*storage else { return None };
    let data = cpu.as_slice::<f32>().ok()?;
    let dims = layout.dims();
    let stride = layout.stride();
    if dims.len() != 4 || dims[0] != 1 || dims[1] != heads || dims[3] != hd || stride[3] != 1 {
        return None;
    }
    let view = View {
        data,
        offset: layout.start_offset(),
        head_stride: stride[1],
        pos_stride: stride[2],
        len: dims[2],
    };
    // Bounds, once, so that the loops below cannot index out of range.
    let last = view.offset
        + (heads - 1) * view.head_stride
        + view.len.saturating_sub(1) * view.pos_stride
        + hd;
    (view.len > 0 && last <= data.len()).then(|| f(&view))
}

fn attend_rows_cpu(q: &Tensor, kv: &[(Tensor, Tensor)]) -> Result<Option<Tensor>> {
    let (b, heads, t, hd) = q.dims4()?;
    if t != 1 || b != kv.len() || q.track_op() || !q.device().is_cpu() {
        return Ok(None);
    }
    let q = q.contiguous()?;
    let Ok(qs) = q.flatten_all()?.to_vec1::<f32>() else { return Ok(None) };
    let scale = 1.0 / (hd as f32).sqrt();
    let mut out = vec![0f32; b * heads * hd];
    let mut scores = Vec::new();
    for (r, (k, v)) in kv.iter().enumerate() {
        let done = with_view(k, heads, hd, |kv_k| {
            with_view(v, heads, hd, |kv_v| {
                if kv_v.len != kv_k.len {
                    return false;
                }
                for h in 0..heads {
                    let qh = &qs[(r * heads + h) * hd..][..hd];
                    scores.clear();
                    scores.extend((0..kv_k.len).map(|l| {
                        let at = kv_k.offset + h * kv_k.head_stride + l * kv_k.pos_stride;
                        let key = &kv_k.data[at..at + hd];
                        dot(qh, key) * scale
                    }));
                    let max = scores.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                    let mut total = 0.0;
                    for s in scores.iter_mut() {
                        *s = (*s - max).exp();
                        total += *s;
                    }
                    let o = &mut out[(r * heads + h) * hd..][..hd];
                    for (l, p) in scores.iter().enumerate() {
                        let at = kv_v.offset + h * kv_v.head_stride + l * kv_v.pos_stride;
                        let w = p / total;
                        for (acc, x) in o.iter_mut().zip(&kv_v.data[at..at + hd]) {
                            *acc += w * x;
                        }
                    }
                }
                true
            })
        })
        .flatten();
        if done != Some(true) {
            return Ok(None);
        }
    }
    Ok(Some(Tensor::from_vec(out, (b, heads, 1, hd), q.device())?))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::testing::max_abs_diff;
    use candle_core::Device;

    #[test]
    fn matches_the_op_by_op_path_on_cache_views() {
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (3, 2, 1, 8), &dev).unwrap();
        let lens = [1usize, 5, 12];
        let kv: Vec<(Tensor, Tensor)> = lens
            .iter()
            .map(|&l| {
                // Views into larger buffers, like a KV cache's.
                let k = Tensor::randn(0f32, 1.0, (1, 2, 16, 8), &dev).unwrap();
                let v = Tensor::randn(0f32, 1.0, (1, 2, 16, 8), &dev).unwrap();
                (k.narrow(2, 0, l).unwrap(), v.narrow(2, 0, l).unwrap())
            })
            .collect();
        let fast = attend_rows_cpu(&q, &kv).unwrap().expect("cpu path");
        for (r, (k, v)) in kv.iter().enumerate() {
            let slow = attend(&q.narrow(0, r, 1).unwrap(), k, v, None).unwrap();
            assert!(max_abs_diff(&fast.narrow(0, r, 1).unwrap(), &slow) < 1e-5);
        }
    }

    #[test]
    fn matches_the_op_by_op_path_on_keys_shared_by_every_head() {
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (2, 3, 1, 4), &dev).unwrap();
        let kv: Vec<(Tensor, Tensor)> = (0..2)
            .map(|_| {
                let shared = Tensor::randn(0f32, 1.0, (1, 1, 5, 4), &dev).unwrap();
                let view = shared.broadcast_as((1, 3, 5, 4)).unwrap();
                (view.clone(), view)
            })
            .collect();
        let fast = attend_rows_cpu(&q, &kv).unwrap().expect("cpu path");
        for (r, (k, v)) in kv.iter().enumerate() {
            let (k, v) = (k.contiguous().unwrap(), v.contiguous().unwrap());
            let slow = attend(&q.narrow(0, r, 1).unwrap(), &k, &v, None).unwrap();
            assert!(max_abs_diff(&fast.narrow(0, r, 1).unwrap(), &slow) < 1e-5);
        }
    }
}
