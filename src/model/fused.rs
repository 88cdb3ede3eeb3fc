//! candle's fused softmax and layer norm, trainable.
//!
//! Why: candle's fused kernels have no backward pass, so training ran their composed formulas
//! (the softmax's max, subtract, exp, sum and divide; the layer norm's ten or so), a kernel
//! each forward and more backward. On an H200 the composed softmax took 0.95 ms forward over
//! one pass's attention scores, (21, 4, 401, 401), where its matmuls take hundredths of a
//! millisecond (`docs/decisions.md`, "Training on a GPU"); on the CPU its backward took 4 times
//! the one here. Here the fused kernel runs forward, and the gradient is written out as a few
//! tensor operations.

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp2, D, Layout, Shape, Tensor};

use super::Result;

/// Softmax over the last dimension of `x`, with a gradient when `x` tracks one.
pub fn softmax(x: &Tensor) -> Result<Tensor> {
    if !x.track_op() {
        return Ok(candle_nn::ops::softmax_last_dim(x)?);
    }
    let y = candle_nn::ops::softmax_last_dim(&x.detach().contiguous()?)?;
    // dx = y (g - sum(g y)).
    let gradient = |_: &Tensor, y: &Tensor, g: &Tensor| {
        let dot = (g * y)?.sum_keepdim(D::Minus1)?;
        y * g.broadcast_sub(&dot)?
    };
    Ok(x.apply_op2(&y, WithGradient { name: "softmax-gradient", gradient })?)
}

/// `x` normalized over its last dimension to mean 0 and variance 1 (variance plus `eps`), as a
/// layer norm does before its weight and bias, with a gradient when `x` tracks one.
pub fn normalize(x: &Tensor, eps: f32) -> Result<Tensor> {
    let d = x.dim(D::Minus1)?;
    let ones = Tensor::ones(d, x.dtype(), x.device())?;
    let y = candle_nn::ops::layer_norm(&x.detach().contiguous()?, &ones, &ones.zeros_like()?, eps)?;
    if !x.track_op() {
        return Ok(y);
    }
    // dx = (g - mean(g) - y mean(g y)) / sqrt(var(x) + eps).
    let gradient = move |x: &Tensor, y: &Tensor, g: &Tensor| {
        let centered = x.broadcast_sub(&x.mean_keepdim(D::Minus1)?)?;
        let std = (centered.sqr()?.mean_keepdim(D::Minus1)? + f64::from(eps))?.sqrt()?;
        let along = y.broadcast_mul(&(g * y)?.mean_keepdim(D::Minus1)?)?;
        (g.broadcast_sub(&g.mean_keepdim(D::Minus1)?)? - along)?.broadcast_div(&std)
    };
    Ok(x.apply_op2(&y, WithGradient { name: "normalize-gradient", gradient })?)
}

/// Applied to (x, f(x)), f(x) computed by a fused kernel: forward, a copy of f(x); backward,
/// `gradient(x, f(x), the gradient of f(x))`, the gradient of x.
struct WithGradient<F> {
    name: &'static str,
    gradient: F,
}

/// The copy clones the whole storage: f(x) must be all of it, as a fresh kernel's output is.
fn check_whole(y: &Layout) -> candle_core::Result<()> {
    if y.is_contiguous() && y.start_offset() == 0 {
        Ok(())
    } else {
        candle_core::bail!("a fused kernel's output must be a whole contiguous tensor")
    }
}

impl<F> CustomOp2 for WithGradient<F>
where
    F: Fn(&Tensor, &Tensor, &Tensor) -> candle_core::Result<Tensor> + Send + Sync,
{
    fn name(&self) -> &'static str {
        self.name
    }

    fn cpu_fwd(
        &self,
        _: &CpuStorage,
        _: &Layout,
        y: &CpuStorage,
        y_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        check_whole(y_layout)?;
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
        check_whole(y_layout)?;
        Ok((y.try_clone(y_layout)?, y_layout.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        _: &Tensor,
        y: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        Ok((Some((self.gradient)(x, y, grad)?), None))
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{DType, Device, Var};

    use super::*;
    use crate::model::testing::max_abs_diff;

    /// The gradients of `vars` of the sum of `y` weighted by `weights`.
    fn gradients(y: &Tensor, weights: &Tensor, vars: &[&Var]) -> Vec<Tensor> {
        let grads = (y * weights).unwrap().sum_all().unwrap().backward().unwrap();
        vars.iter().map(|v| grads.get(v.as_tensor()).unwrap().clone()).collect()
    }

    /// Each of `fused` within `tolerance` of the largest value of the matching `composed`.
    fn assert_close(fused: &[Tensor], composed: &[Tensor], tolerance: f32) {
        for (f, c) in fused.iter().zip(composed) {
            let scale = c.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
            assert!(scale > 0.1, "a gradient worth comparing: {scale}");
            let diff = max_abs_diff(f, c);
            assert!(diff < tolerance * scale, "{diff} against {scale}");
        }
    }

    #[test]
    fn the_softmax_has_the_composed_formulas_values_and_gradients() {
        let device = Device::Cpu;
        let x = Var::randn(0f32, 3.0, (2, 3, 5, 7), &device).unwrap();
        let weights = Tensor::randn(0f32, 1.0, (2, 3, 5, 7), &device).unwrap();
        let composed = candle_nn::ops::softmax(x.as_tensor(), D::Minus1).unwrap();
        let fused = softmax(x.as_tensor()).unwrap();
        assert!(max_abs_diff(&fused, &composed) < 1e-6);
        assert_close(
            &gradients(&fused, &weights, &[&x]),
            &gradients(&composed, &weights, &[&x]),
            1e-5,
        );
    }

    #[test]
    fn the_layer_norm_has_the_composed_formulas_values_and_gradients() {
        let device = Device::Cpu;
        let x = Var::randn(0.5f32, 2.0, (3, 4, 16), &device).unwrap();
        let weight = Var::randn(1f32, 0.5, 16, &device).unwrap();
        let bias = Var::randn(0f32, 0.5, 16, &device).unwrap();
        let weights = Tensor::randn(0f32, 1.0, (3, 4, 16), &device).unwrap();
        let eps = 1e-5;
        let composed = candle_nn::ops::layer_norm_slow(x.as_tensor(), &weight, &bias, eps).unwrap();
        let fused = normalize(x.as_tensor(), eps)
            .unwrap()
            .broadcast_mul(&weight)
            .unwrap()
            .broadcast_add(&bias)
            .unwrap();
        assert!(max_abs_diff(&fused, &composed) < 1e-5);
        let vars = [&x, &weight, &bias];
        assert_close(
            &gradients(&fused, &weights, &vars),
            &gradients(&composed, &weights, &vars),
            1e-5,
        );
    }

    #[test]
    fn without_gradients_they_are_the_fused_kernels() {
        let x = Tensor::randn(0f32, 1.0, (4, 9), &Device::Cpu).unwrap();
        let fused = candle_nn::ops::softmax_last_dim(&x).unwrap();
        assert_eq!(max_abs_diff(&softmax(&x).unwrap(), &fused), 0.0);
        let (ones, zeros) = (
            Tensor::ones(9, DType::F32, &Device::Cpu).unwrap(),
            Tensor::zeros(9, DType::F32, &Device::Cpu).unwrap(),
        );
        let fused = candle_nn::ops::layer_norm(&x, &ones, &zeros, 1e-5).unwrap();
        assert_eq!(max_abs_diff(&normalize(&x, 1e-5).unwrap(), &fused), 0.0);
    }
}
