//! Flow matching (rectified flow) and its Euler sampler.
//!
//! Convention (the paper only says "standard flow matching"; this is Liu et al.'s rectified
//! flow with time running from noise to data): `x_t = (1 - t) x0 + t x1`, with `x0 ~ N(0, I)`
//! the noise, `x1` the data and `t ~ U(0, 1)`; the model regresses the velocity
//! `dx_t/dt = x1 - x0` with a mean squared error. Sampling integrates `dx/dt = v(x, t)` from
//! t = 0 (noise) to t = 1 (data) with Euler steps of size 1/N (the paper: N = 100).
//!
//! Classifier-free guidance: `v = v_uncond + s (v_cond - v_uncond)`, with a guidance scale per
//! row so that requests with different scales share a batch (they must share the step count).

use candle_core::{Device, Tensor};
use rand::Rng;
use rand_distr::StandardNormal;

use crate::model::{ModelError, Result};

/// A learned (or exact) velocity field v(x_t, t | condition).
pub trait VelocityField {
    /// Whatever the field is conditioned on, prepared for a batch.
    type Condition;

    /// x_t (B, ...) at times t (B,) in [0, 1] -> velocity of the same shape as x_t.
    fn velocity(&self, x_t: &Tensor, t: &Tensor, cond: &Self::Condition) -> Result<Tensor>;
}

/// A tensor of i.i.d. standard normal values drawn from `rng` (so runs are reproducible).
pub fn gaussian_noise(shape: &[usize], rng: &mut impl Rng, device: &Device) -> Result<Tensor> {
    let n = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| rng.sample(StandardNormal)).collect();
    Ok(Tensor::from_vec(v, shape, device)?)
}

/// (B,) -> (B, 1, ..., 1) with the rank of `like`, for per-row broadcasting.
fn per_row(v: &Tensor, like: &Tensor) -> Result<Tensor> {
    let mut dims = vec![1; like.rank()];
    dims[0] = v.elem_count();
    Ok(v.reshape(dims)?)
}

/// `x_t = (1 - t) x0 + t x1` with t (B,).
pub fn interpolate(x0: &Tensor, x1: &Tensor, t: &Tensor) -> Result<Tensor> {
    let t = per_row(t, x1)?;
    Ok((x0.broadcast_mul(&(1.0 - &t)?)? + x1.broadcast_mul(&t)?)?)
}

/// The flow-matching loss on a batch of data `x1` (B, ...): noise and times drawn from `rng`,
/// mean squared error between the predicted and the target velocity `x1 - x0`.
pub fn loss<M: VelocityField>(
    model: &M,
    x1: &Tensor,
    cond: &M::Condition,
    rng: &mut impl Rng,
) -> Result<Tensor> {
    let b = x1.dim(0)?;
    let x0 = gaussian_noise(x1.dims(), rng, x1.device())?;
    let t: Vec<f32> = (0..b).map(|_| rng.random::<f32>()).collect();
    let t = Tensor::from_vec(t, b, x1.device())?;
    let x_t = interpolate(&x0, x1, &t)?;
    let target = (x1 - &x0)?;
    let v = model.velocity(&x_t, &t, cond)?;
    Ok((v - target)?.sqr()?.mean_all()?)
}

/// What to condition on while sampling, and how strongly (one scale per row).
#[derive(Debug, Clone)]
pub struct Guidance<'a, C> {
    pub cond: &'a C,
    pub uncond: &'a C,
    pub scales: Vec<f32>,
}

impl<'a, C> Guidance<'a, C> {
    /// Plain conditional sampling (scale 1 everywhere: no unconditional pass is run).
    pub fn conditional(cond: &'a C, batch: usize) -> Self {
        Self { cond, uncond: cond, scales: vec![1.0; batch] }
    }
}

/// `v_uncond + s (v_cond - v_uncond)` with s (B,) per row.
pub fn combine_guidance(v_cond: &Tensor, v_uncond: &Tensor, scales: &Tensor) -> Result<Tensor> {
    let s = per_row(scales, v_cond)?;
    Ok((v_uncond + (v_cond - v_uncond)?.broadcast_mul(&s)?)?)
}

/// The guided velocity at x (B, ...) and times t (one per row). Skips the pass a uniform
/// scale of 1 (only conditional) or 0 (only unconditional) does not need.
pub fn guided_velocity<M: VelocityField>(
    model: &M,
    x: &Tensor,
    times: &[f32],
    guidance: &Guidance<'_, M::Condition>,
) -> Result<Tensor> {
    let b = x.dim(0)?;
    if guidance.scales.len() != b || times.len() != b {
        return Err(ModelError::bad_input(format!(
            "{} guidance scales and {} times for a batch of {b}",
            guidance.scales.len(),
            times.len()
        )));
    }
    if let Some(s) = guidance.scales.iter().find(|s| !s.is_finite()) {
        return Err(ModelError::bad_input(format!("guidance scale {s} is not finite")));
    }
    let times = Tensor::from_slice(times, b, x.device())?;
    if guidance.scales.iter().all(|&s| s == 1.0) {
        return model.velocity(x, &times, guidance.cond);
    }
    let v_uncond = model.velocity(x, &times, guidance.uncond)?;
    if guidance.scales.iter().all(|&s| s == 0.0) {
        return Ok(v_uncond);
    }
    let v_cond = model.velocity(x, &times, guidance.cond)?;
    let scales = Tensor::from_slice(&guidance.scales, b, x.device())?;
    combine_guidance(&v_cond, &v_uncond, &scales)
}

/// Where a row is on its own schedule: about to take Euler step `step` (0-based) of `steps`.
/// Rows of one batch may be at different steps of different schedules, which is what lets a
/// scheduler add requests to a sampling batch at any time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RowStep {
    pub step: usize,
    pub steps: usize,
}

impl RowStep {
    pub fn is_done(self) -> bool {
        self.step >= self.steps
    }
}

/// One Euler step for every row, each on its own schedule: from t = step/steps to
/// t + 1/steps.
pub fn euler_step_rows<M: VelocityField>(
    model: &M,
    x: &Tensor,
    rows: &[RowStep],
    guidance: &Guidance<'_, M::Condition>,
) -> Result<Tensor> {
    if let Some(r) = rows.iter().find(|r| r.is_done()) {
        return Err(ModelError::bad_input(format!(
            "Euler step {} of {} out of range",
            r.step, r.steps
        )));
    }
    let dts: Vec<f32> = rows.iter().map(|r| 1.0 / r.steps as f32).collect();
    let times: Vec<f32> = rows.iter().zip(&dts).map(|(r, dt)| r.step as f32 * dt).collect();
    let v = guided_velocity(model, x, &times, guidance)?;
    let dt = per_row(&Tensor::from_vec(dts, rows.len(), x.device())?, x)?;
    Ok((x + v.broadcast_mul(&dt)?)?.detach())
}

/// Euler step `step` of `steps` (0-based) for the whole batch.
pub fn euler_step<M: VelocityField>(
    model: &M,
    x: &Tensor,
    step: usize,
    steps: usize,
    guidance: &Guidance<'_, M::Condition>,
) -> Result<Tensor> {
    euler_step_rows(model, x, &vec![RowStep { step, steps }; x.dim(0)?], guidance)
}

/// Integrates from the noise `x0` (t = 0) to data (t = 1) in `steps` Euler steps.
pub fn sample<M: VelocityField>(
    model: &M,
    x0: &Tensor,
    steps: usize,
    guidance: &Guidance<'_, M::Condition>,
) -> Result<Tensor> {
    if steps == 0 {
        return Err(ModelError::bad_input("the sampler needs at least one step"));
    }
    let mut x = x0.clone();
    for step in 0..steps {
        x = euler_step(model, &x, step, steps, guidance)?;
    }
    Ok(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::DType;
    use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarBuilder, VarMap};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// The exact velocity field of a Gaussian data distribution N(mu, sigma^2 I): x_t is
    /// N(t mu, s_t^2) with s_t^2 = (1-t)^2 + t^2 sigma^2, and the flow that maps noise z to
    /// mu + sigma z has v = mu + (t sigma^2 - (1 - t)) / s_t^2 (x - t mu). With `cond`
    /// selecting (mu, sigma), it also stands in for a conditional model.
    struct GaussianField;

    impl VelocityField for GaussianField {
        type Condition = (f32, f32);

        fn velocity(&self, x: &Tensor, t: &Tensor, &(mu, sigma): &(f32, f32)) -> Result<Tensor> {
            let t = per_row(t, x)?;
            let s2 = ((1.0 - &t)?.sqr()? + (t.sqr()? * f64::from(sigma * sigma))?)?;
            let gain = ((&t * f64::from(sigma * sigma))? - (1.0 - &t)?)?.div(&s2)?;
            let centred = x.broadcast_sub(&(&t * f64::from(mu))?)?;
            Ok((centred.broadcast_mul(&gain)? + f64::from(mu))?)
        }
    }

    fn max_abs(t: &Tensor) -> f32 {
        t.flatten_all().unwrap().to_vec1::<f32>().unwrap().iter().fold(0.0, |m, v| m.max(v.abs()))
    }

    #[test]
    fn euler_with_the_exact_field_converges_as_the_steps_grow() {
        let dev = Device::Cpu;
        let (mu, sigma) = (1.5f32, 0.5f32);
        let z = gaussian_noise(&[64, 3], &mut ChaCha8Rng::seed_from_u64(1), &dev).unwrap();
        let exact = ((&z * f64::from(sigma)).unwrap() + f64::from(mu)).unwrap();
        let cond = (mu, sigma);
        let errors: Vec<f32> = [5, 20, 100]
            .iter()
            .map(|&n| {
                let x = sample(&GaussianField, &z, n, &Guidance::conditional(&cond, 64)).unwrap();
                max_abs(&(x - &exact).unwrap())
            })
            .collect();
        // Euler is first order: the error falls with 1/N.
        assert!(errors[0] > errors[1] && errors[1] > errors[2], "{errors:?}");
        assert!(errors[2] < 0.05, "{errors:?}");
        assert!(errors[1] < errors[0] / 2.0, "{errors:?}");
    }

    #[test]
    fn guidance_scale_1_is_conditional_and_0_unconditional() {
        let dev = Device::Cpu;
        let x = gaussian_noise(&[4, 2], &mut ChaCha8Rng::seed_from_u64(2), &dev).unwrap();
        let (cond, uncond) = ((2.0f32, 0.3f32), (-1.0f32, 1.0f32));
        let t = Tensor::full(0.3f32, 4, &dev).unwrap();
        let v_c = GaussianField.velocity(&x, &t, &cond).unwrap();
        let v_u = GaussianField.velocity(&x, &t, &uncond).unwrap();
        for (scale, expect) in [(1.0, &v_c), (0.0, &v_u)] {
            let g = Guidance { cond: &cond, uncond: &uncond, scales: vec![scale; 4] };
            let v = guided_velocity(&GaussianField, &x, &[0.3; 4], &g).unwrap();
            assert!(max_abs(&(v - expect).unwrap()) < 1e-6);
            // The combination formula itself (run when rows have different scales).
            let s = Tensor::full(scale, 4, &dev).unwrap();
            let combined = combine_guidance(&v_c, &v_u, &s).unwrap();
            assert!(max_abs(&(combined - expect).unwrap()) < 1e-5);
        }
        // Mixed scales in one batch: each row gets its own.
        let g = Guidance { cond: &cond, uncond: &uncond, scales: vec![1.0, 0.0, 3.0, 1.0] };
        let v =
            guided_velocity(&GaussianField, &x, &[0.3; 4], &g).unwrap().to_vec2::<f32>().unwrap();
        let (c, u) = (v_c.to_vec2::<f32>().unwrap(), v_u.to_vec2::<f32>().unwrap());
        for j in 0..2 {
            assert!((v[0][j] - c[0][j]).abs() < 1e-5);
            assert!((v[1][j] - u[1][j]).abs() < 1e-5);
            assert!((v[2][j] - (u[2][j] + 3.0 * (c[2][j] - u[2][j]))).abs() < 1e-4);
        }
        let bad = Guidance { cond: &cond, uncond: &uncond, scales: vec![1.0; 3] };
        assert!(guided_velocity(&GaussianField, &x, &[0.3; 4], &bad).is_err());
        assert!(euler_step(&GaussianField, &x, 5, 5, &bad).is_err());
        assert!(sample(&GaussianField, &x, 0, &Guidance::conditional(&cond, 4)).is_err());
    }

    /// A small MLP velocity field on 2-D points, for the toy flow-matching test.
    struct ToyField {
        layers: Vec<candle_nn::Linear>,
    }

    impl VelocityField for ToyField {
        type Condition = ();

        fn velocity(&self, x: &Tensor, t: &Tensor, _: &()) -> Result<Tensor> {
            // Raw t: the DiT's 1000-scaled sinusoids are too high-frequency for a small MLP.
            let mut h = Tensor::cat(&[x, &t.unsqueeze(1)?], 1)?;
            for (i, layer) in self.layers.iter().enumerate() {
                h = candle_core::Module::forward(layer, &h)?;
                if i + 1 < self.layers.len() {
                    h = h.silu()?;
                }
            }
            Ok(h)
        }
    }

    const CENTRES: [[f32; 2]; 3] = [[-2.0, 0.0], [2.0, 0.0], [0.0, 2.5]];
    const STD: f32 = 0.3;

    fn mixture_batch(n: usize, rng: &mut impl Rng) -> Tensor {
        let v: Vec<f32> = (0..n)
            .flat_map(|_| {
                let c = CENTRES[rng.random_range(0..3)];
                let (a, b): (f32, f32) = (rng.sample(StandardNormal), rng.sample(StandardNormal));
                [c[0] + STD * a, c[1] + STD * b]
            })
            .collect();
        Tensor::from_vec(v, (n, 2), &Device::Cpu).unwrap()
    }

    #[test]
    fn flow_matching_learns_a_gaussian_mixture() {
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        let sizes = [3, 128, 128, 128, 2];
        let layers = sizes
            .windows(2)
            .enumerate()
            .map(|(i, w)| candle_nn::linear(w[0], w[1], vb.pp(i.to_string())).unwrap())
            .collect();
        let model = ToyField { layers };
        let params = ParamsAdamW { lr: 3e-3, weight_decay: 0.0, ..Default::default() };
        let mut opt = AdamW::new(varmap.all_vars(), params).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let steps = 1500;
        for step in 0..steps {
            // Cosine decay to a tenth: the late small steps sharpen the modes.
            let progress = step as f64 / steps as f64;
            opt.set_learning_rate(
                3e-4 + 2.7e-3 * 0.5 * (1.0 + (std::f64::consts::PI * progress).cos()),
            );
            let x1 = mixture_batch(256, &mut rng);
            let l = loss(&model, &x1, &(), &mut rng).unwrap();
            opt.backward_step(&l).unwrap();
        }

        let n = 3000;
        let x0 = gaussian_noise(&[n, 2], &mut rng, &dev).unwrap();
        let x = sample(&model, &x0, 50, &Guidance::conditional(&(), n)).unwrap();
        let points = x.to_vec2::<f32>().unwrap();
        // Assign each sample to its nearest centre and compare per-component statistics.
        let mut groups: [Vec<[f32; 2]>; 3] = Default::default();
        for p in &points {
            let d = |c: &[f32; 2]| (p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2);
            let k = (0..3).min_by(|&a, &b| d(&CENTRES[a]).total_cmp(&d(&CENTRES[b]))).unwrap();
            groups[k].push([p[0], p[1]]);
        }
        for (k, g) in groups.iter().enumerate() {
            // Weights: 1/3 each; with n = 3000 the standard error of a weight is 0.009, so
            // 0.06 leaves room for the model's own error while a dropped or merged mode fails.
            let weight = g.len() as f32 / n as f32;
            assert!((weight - 1.0 / 3.0).abs() < 0.06, "component {k} has weight {weight}");
            for axis in 0..2 {
                let mean = g.iter().map(|p| p[axis]).sum::<f32>() / g.len() as f32;
                let var = g.iter().map(|p| (p[axis] - mean).powi(2)).sum::<f32>() / g.len() as f32;
                // A component mean from ~1000 samples has a standard error of 0.01; 0.1 (a third
                // of the component std) catches modes pulled towards each other, which is what
                // an underfit velocity field does. Stds within 25%: an underfit field blurs the
                // modes (we saw +40% with a third of the training), a collapsed one shrinks them.
                let centre = CENTRES[k][axis];
                assert!((mean - centre).abs() < 0.1, "component {k} axis {axis}: mean {mean}");
                let std = var.sqrt();
                assert!(
                    (std / STD - 1.0).abs() < 0.25,
                    "component {k} axis {axis}: std {std} vs {STD}"
                );
            }
        }
    }

    #[test]
    fn the_loss_is_the_mse_to_the_straight_line_velocity() {
        // A field that outputs zero: the loss is E|x1 - x0|^2 = |x1|^2 + 1 per coordinate.
        struct Zero;
        impl VelocityField for Zero {
            type Condition = ();
            fn velocity(&self, x: &Tensor, _: &Tensor, _: &()) -> Result<Tensor> {
                Ok(x.zeros_like()?)
            }
        }
        let x1 = Tensor::full(2.0f32, (512, 16), &Device::Cpu).unwrap();
        let l = loss(&Zero, &x1, &(), &mut ChaCha8Rng::seed_from_u64(3)).unwrap();
        let l = l.to_scalar::<f32>().unwrap();
        assert!((l - 5.0).abs() < 0.1, "{l}");
        let t = Tensor::new(&[0.25f32], &Device::Cpu).unwrap();
        let x0 = Tensor::new(&[[4.0f32]], &Device::Cpu).unwrap();
        let x1 = Tensor::new(&[[8.0f32]], &Device::Cpu).unwrap();
        assert_eq!(interpolate(&x0, &x1, &t).unwrap().to_vec2::<f32>().unwrap(), [[5.0]]);
    }
}
