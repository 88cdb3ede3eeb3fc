//! Softmax over the last dimension by candle's fused kernel, trainable.
//!
//! Why: candle's fused softmax has no backward pass, so training ran the composed formula
//! (max, subtract, exp, sum, divide), a kernel each forward and more backward. On an H200 that
//! took 0.95 ms forward over one pass's attention scores, (21, 4, 401, 401), where its matmuls
//! take hundredths of a millisecond (`docs/decisions.md`, "Training on a GPU"); on the CPU its
//! backward took 4 times the one below. Here the fused kernel runs forward and the gradient is
//! y (g - sum(g y)), four kernels.

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp2, D, Layout, Shape, Tensor};

use super::Result;

/// Softmax over the last dimension of `x`, with a gradient when `x` tracks one.
pub fn softmax(x: &Tensor) -> Result<Tensor> {
    if !x.track_op() {
        return Ok(candle_nn::ops::softmax_last_dim(x)?);
    }
    let y = candle_nn::ops::softmax_last_dim(&x.detach().contiguous()?)?;
    Ok(x.apply_op2(&y, SoftmaxGradient)?)
}

/// Applied to (x, softmax(x)): forward, a copy of the softmax already computed; backward, the
/// softmax's gradient with respect to x.
struct SoftmaxGradient;

impl SoftmaxGradient {
    /// The copy below clones the whole storage: the softmax must be all of it, as a fresh
    /// kernel's output is.
    fn check(y: &Layout) -> candle_core::Result<()> {
        if y.is_contiguous() && y.start_offset() == 0 {
            Ok(())
        } else {
            candle_core::bail!("softmax-gradient: the softmax must be a whole contiguous tensor")
        }
    }
}

impl CustomOp2 for SoftmaxGradient {
    fn name(&self) -> &'static str {
        "softmax-gradient"
    }

    fn cpu_fwd(
        &self,
        _: &CpuStorage,
        _: &Layout,
        y: &CpuStorage,
        y_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        Self::check(y_layout)?;
        Ok((y.try_clone(y_layout)?, y_layout.shape().clone()))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        _: &candle_core::CudaStorage,
        _: &Layout,
        y: &candle_core::CudaStorage,
        y_layout: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        Self::check(y_layout)?;
        Ok((y.try_clone(y_layout)?, y_layout.shape().clone()))
    }

    fn bwd(
        &self,
        _: &Tensor,
        _: &Tensor,
        y: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let dot = (grad * y)?.sum_keepdim(D::Minus1)?;
        Ok((Some((y * grad.broadcast_sub(&dot)?)?), None))
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Var};

    use super::*;
    use crate::model::testing::max_abs_diff;

    #[test]
    fn values_and_gradients_are_the_composed_formulas() {
        let device = Device::Cpu;
        let x = Var::randn(0f32, 3.0, (2, 3, 5, 7), &device).unwrap();
        let weights = Tensor::randn(0f32, 1.0, (2, 3, 5, 7), &device).unwrap();
        let composed = candle_nn::ops::softmax(x.as_tensor(), D::Minus1).unwrap();
        let fused = softmax(x.as_tensor()).unwrap();
        assert!(max_abs_diff(&fused, &composed) < 1e-6);

        let grad_of = |y: &Tensor| {
            let grads = (y * &weights).unwrap().sum_all().unwrap().backward().unwrap();
            grads.get(x.as_tensor()).unwrap().clone()
        };
        let (fused_grad, composed_grad) = (grad_of(&fused), grad_of(&composed));
        let scale = composed_grad.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(scale > 0.1, "a gradient worth comparing: {scale}");
        assert!(max_abs_diff(&fused_grad, &composed_grad) < 1e-5 * scale);
    }

    #[test]
    fn without_gradients_it_is_the_fused_kernel() {
        let x = Tensor::randn(0f32, 1.0, (4, 9), &Device::Cpu).unwrap();
        let fused = candle_nn::ops::softmax_last_dim(&x).unwrap();
        assert_eq!(max_abs_diff(&softmax(&x).unwrap(), &fused), 0.0);
    }
}
