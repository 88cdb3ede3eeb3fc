//! The optimizers of the paper: Muon (Newton-Schulz orthogonalized momentum) for the 2-D
//! weight matrices of the transformer blocks, AdamW for everything else; a warm-up + cosine
//! schedule and global gradient-norm clipping.
//!
//! Written here rather than taken from candle-nn because a resumed run must continue exactly,
//! which needs the optimizer state (moments, momentum buffers) saved and restored, and
//! candle-nn's AdamW keeps its state private.

use std::collections::HashMap;

use candle_core::backprop::GradStore;
use candle_core::{DType, Result, Tensor, Var};
use candle_nn::VarMap;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct OptimConfig {
    pub weight_decay: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub muon_momentum: f64,
    /// Newton-Schulz iterations per Muon step.
    pub ns_steps: usize,
}

impl Default for OptimConfig {
    fn default() -> Self {
        Self {
            weight_decay: 0.1,
            beta1: 0.9,
            beta2: 0.95,
            eps: 1e-8,
            muon_momentum: 0.95,
            ns_steps: 5,
        }
    }
}

/// Which optimizer updates a parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rule {
    Muon,
    AdamW,
    /// AdamW without weight decay (norms, biases, embeddings).
    AdamWNoDecay,
}

struct Param {
    name: String,
    var: Var,
    rule: Rule,
    /// This parameter's learning rate as a share of the schedule's.
    lr_scale: f64,
    /// Muon: the momentum buffer. AdamW: the first moment.
    m: Tensor,
    /// AdamW: the second moment (unused by Muon).
    v: Tensor,
}

/// Muon + AdamW over the variables of a `VarMap`.
pub struct Optimizer {
    params: Vec<Param>,
    cfg: OptimConfig,
    step: u64,
}

/// The rule of the paper: 2-D matrices inside transformer blocks get Muon; other matrices
/// (embeddings, heads, input projections) AdamW with decay; vectors AdamW without decay.
pub fn default_rule(name: &str, rank: usize) -> Rule {
    let in_block = name.contains(".layers.") || name.contains(".blocks.");
    let is_embedding = name.contains("embed") || name.contains("start_token");
    match rank {
        2 if in_block && !is_embedding => Rule::Muon,
        2 if !is_embedding => Rule::AdamW,
        _ => Rule::AdamWNoDecay,
    }
}

impl Optimizer {
    pub fn new(
        varmap: &VarMap,
        cfg: OptimConfig,
        rule: impl Fn(&str, usize) -> Rule,
    ) -> Result<Self> {
        let vars =
            varmap.data().lock().map_err(|_| candle_core::Error::Msg("var map poisoned".into()))?;
        let mut names: Vec<&String> = vars.keys().collect();
        names.sort();
        let mut params = Vec::with_capacity(names.len());
        for name in names {
            let var = vars[name].clone();
            let rule = rule(name, var.rank());
            params.push(Param {
                name: name.clone(),
                m: var.zeros_like()?,
                v: var.zeros_like()?,
                var,
                rule,
                lr_scale: 1.0,
            });
        }
        Ok(Self { params, cfg, step: 0 })
    }

    /// Updates the parameters whose names start with `prefix` at `scale` times the learning
    /// rate (and so their weight decay too, which is decoupled). Returns how many values that
    /// covers, so that a prefix matching nothing is noticed.
    pub fn scale_learning_rate(&mut self, prefix: &str, scale: f64) -> usize {
        let mut covered = 0;
        for p in self.params.iter_mut().filter(|p| p.name.starts_with(prefix)) {
            p.lr_scale = scale;
            covered += p.var.elem_count();
        }
        covered
    }

    pub fn steps_taken(&self) -> u64 {
        self.step
    }

    /// How many parameters each rule updates, for the start-of-run summary.
    pub fn counts(&self) -> HashMap<&'static str, usize> {
        let mut out = HashMap::new();
        for p in &self.params {
            let key = match p.rule {
                Rule::Muon => "muon",
                Rule::AdamW => "adamw",
                Rule::AdamWNoDecay => "adamw-no-decay",
            };
            *out.entry(key).or_default() += p.var.elem_count();
        }
        out
    }

    /// One update with learning rate `lr` from the gradients in `grads` (parameters without
    /// a gradient are left alone).
    pub fn step(&mut self, grads: &GradStore, lr: f64) -> Result<()> {
        self.step += 1;
        let cfg = self.cfg;
        let t = self.step as i32;
        for p in &mut self.params {
            let Some(g) = grads.get(p.var.as_tensor()) else { continue };
            let w = p.var.as_tensor();
            let lr = lr * p.lr_scale;
            match p.rule {
                Rule::Muon => {
                    // Nesterov momentum, then orthogonalize the update.
                    p.m = ((&p.m * cfg.muon_momentum)? + g)?;
                    let nesterov = (g + (&p.m * cfg.muon_momentum)?)?;
                    let ortho = newton_schulz(&nesterov, cfg.ns_steps)?;
                    // Scaled to AdamW's typical update RMS (Liu et al., 2025), so one learning
                    // rate and weight decay serve both rules.
                    let (rows, cols) = w.dims2()?;
                    let scale = 0.2 * (rows.max(cols) as f64).sqrt();
                    let decayed = (w * (1.0 - lr * cfg.weight_decay))?;
                    p.var.set(&(decayed - (ortho * (lr * scale))?)?)?;
                }
                Rule::AdamW | Rule::AdamWNoDecay => {
                    p.m = ((&p.m * cfg.beta1)? + (g * (1.0 - cfg.beta1))?)?;
                    p.v = ((&p.v * cfg.beta2)? + (g.sqr()? * (1.0 - cfg.beta2))?)?;
                    let m_hat = (&p.m / (1.0 - cfg.beta1.powi(t)))?;
                    let v_hat = (&p.v / (1.0 - cfg.beta2.powi(t)))?;
                    let update = (m_hat / (v_hat.sqrt()? + cfg.eps)?)?;
                    let decay = if p.rule == Rule::AdamW { cfg.weight_decay } else { 0.0 };
                    let decayed = (w * (1.0 - lr * decay))?;
                    p.var.set(&(decayed - (update * lr)?)?)?;
                }
            }
        }
        Ok(())
    }

    /// The optimizer state as named tensors (for a checkpoint), with the step count.
    pub fn state(&self) -> Result<HashMap<String, Tensor>> {
        let mut out = HashMap::new();
        for p in &self.params {
            out.insert(format!("m.{}", p.name), p.m.clone());
            out.insert(format!("v.{}", p.name), p.v.clone());
        }
        out.insert("step".into(), Tensor::new(&[self.step as f64], &candle_core::Device::Cpu)?);
        Ok(out)
    }

    /// Restores a state saved by [`Optimizer::state`]; every tensor must be present with its
    /// parameter's shape.
    pub fn load_state(&mut self, state: &HashMap<String, Tensor>) -> Result<()> {
        let get = |key: String, like: &Tensor| -> Result<Tensor> {
            let t = state
                .get(&key)
                .ok_or_else(|| candle_core::Error::Msg(format!("optimizer state lacks {key}")))?;
            if t.shape() != like.shape() {
                candle_core::bail!(
                    "optimizer state {key}: expected {:?}, found {:?}",
                    like.shape(),
                    t.shape()
                );
            }
            t.to_device(like.device())?.to_dtype(like.dtype())
        };
        for p in &mut self.params {
            p.m = get(format!("m.{}", p.name), &p.m)?;
            p.v = get(format!("v.{}", p.name), &p.v)?;
        }
        let step = state
            .get("step")
            .ok_or_else(|| candle_core::Error::Msg("optimizer state lacks step".into()))?;
        self.step =
            step.to_dtype(DType::F64)?.to_vec1::<f64>()?.first().copied().unwrap_or(0.0) as u64;
        Ok(())
    }
}

/// Approximately orthogonalizes `g` (the nearest semi-orthogonal matrix, up to the quintic
/// iteration's tolerance): singular values are pushed into roughly [0.7, 1.2].
pub fn newton_schulz(g: &Tensor, steps: usize) -> Result<Tensor> {
    // Coefficients of Jordan et al.'s quintic, tuned to converge fast from small singular values.
    let (a, b, c) = (3.4445, -4.7750, 2.0315);
    let (rows, cols) = g.dims2()?;
    let transposed = rows > cols;
    let mut x = if transposed { g.t()? } else { g.clone() };
    let norm = x.sqr()?.sum_all()?.sqrt()?;
    x = x.broadcast_div(&(norm + 1e-7)?)?;
    for _ in 0..steps {
        let xt = x.t()?;
        let gram = x.matmul(&xt)?;
        let poly = ((&gram * b)? + (gram.matmul(&gram)? * c)?)?;
        x = ((&x * a)? + poly.matmul(&x)?)?;
    }
    if transposed { x.t()?.contiguous() } else { Ok(x) }
}

/// Scales all gradients so their global L2 norm is at most `max_norm`; returns the norm
/// before clipping. Parameters without a gradient are skipped.
pub fn clip_grad_norm(grads: &mut GradStore, vars: &[Var], max_norm: f64) -> Result<f64> {
    // Each gradient's sum of squares stays on the device; one copy brings them all back.
    let squares = vars
        .iter()
        .filter_map(|var| grads.get(var.as_tensor()))
        .map(|g| g.sqr()?.sum_all())
        .collect::<Result<Vec<_>>>()?;
    let norm = if squares.is_empty() {
        0.0
    } else {
        let squares = Tensor::stack(&squares, 0)?.to_dtype(DType::F64)?.to_vec1::<f64>()?;
        squares.iter().sum::<f64>().sqrt()
    };
    if norm.is_finite() && norm > max_norm && max_norm > 0.0 {
        let factor = max_norm / norm;
        for var in vars {
            if let Some(g) = grads.remove(var.as_tensor()) {
                grads.insert(var.as_tensor(), (g * factor)?);
            }
        }
    }
    Ok(norm)
}

/// Linear warm-up to `peak`, then cosine decay to `peak * min_ratio` at `total` steps.
pub fn learning_rate(step: u64, warmup: u64, total: u64, peak: f64, min_ratio: f64) -> f64 {
    if step < warmup {
        return peak * (step + 1) as f64 / warmup as f64;
    }
    let span = total.saturating_sub(warmup).max(1) as f64;
    let progress = ((step - warmup) as f64 / span).min(1.0);
    let cosine = 0.5 * (1.0 + (std::f64::consts::PI * progress).cos());
    peak * (min_ratio + (1.0 - min_ratio) * cosine)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// Extreme eigenvalues of a symmetric positive semi-definite matrix by power iteration
    /// (on G for the largest, on lambda_max I - G for the smallest).
    fn extreme_eigenvalues(g: &[Vec<f32>]) -> (f64, f64) {
        let n = g.len();
        let power = |shift: f64, sign: f64| -> f64 {
            let mut v = vec![1.0f64; n];
            let mut lambda = 0.0;
            for _ in 0..500 {
                let w: Vec<f64> = (0..n)
                    .map(|i| {
                        let gv: f64 = (0..n).map(|j| g[i][j] as f64 * v[j]).sum();
                        shift * v[i] + sign * gv
                    })
                    .collect();
                lambda = w.iter().map(|x| x * x).sum::<f64>().sqrt();
                v = w.iter().map(|x| x / lambda).collect();
            }
            lambda
        };
        let max = power(0.0, 1.0);
        (max - power(max, -1.0), max)
    }

    #[test]
    fn newton_schulz_returns_a_near_orthogonal_update() {
        let dev = Device::Cpu;
        for (rows, cols) in [(32, 96), (96, 32), (48, 128)] {
            // A gradient-like matrix: random, with one direction stronger than the rest.
            let g = Tensor::randn(0f32, 1.0, (rows, cols), &dev).unwrap();
            let spike = Tensor::ones((rows, cols), DType::F32, &dev).unwrap();
            let g = (g + (spike * 3.0).unwrap()).unwrap();
            let x = newton_schulz(&g, 5).unwrap();
            assert_eq!(x.dims2().unwrap(), (rows, cols));
            let xt = x.t().unwrap();
            let small = if rows <= cols { x.matmul(&xt) } else { xt.matmul(&x) };
            let (lo, hi) = extreme_eigenvalues(&small.unwrap().to_vec2::<f32>().unwrap());
            // Singular values are the square roots; the quintic leaves them in about [0.7, 1.2].
            let (lo, hi) = (lo.max(0.0).sqrt(), hi.sqrt());
            assert!(lo > 0.6 && hi < 1.25, "({rows}x{cols}) singular values in [{lo}, {hi}]");
        }
    }

    #[test]
    fn schedule_warms_up_then_decays() {
        assert!((learning_rate(0, 10, 100, 1.0, 0.1) - 0.1).abs() < 1e-12);
        assert!((learning_rate(9, 10, 100, 1.0, 0.1) - 1.0).abs() < 1e-12);
        assert!((learning_rate(100, 10, 100, 1.0, 0.1) - 0.1).abs() < 1e-12);
        assert!(learning_rate(50, 10, 100, 1.0, 0.1) < learning_rate(20, 10, 100, 1.0, 0.1));
    }

    #[test]
    fn optimizer_minimizes_a_quadratic_and_state_round_trips() {
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        let vb = candle_nn::VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        let w = vb.get_with_hints((8, 8), "dec.layers.0.w", candle_nn::Init::Const(1.0)).unwrap();
        let b = vb.get_with_hints(8, "dec.bias", candle_nn::Init::Const(1.0)).unwrap();
        let target = Tensor::eye(8, DType::F32, &dev).unwrap();
        let cfg = OptimConfig { weight_decay: 0.0, ..Default::default() };
        let mut opt = Optimizer::new(&varmap, cfg, default_rule).unwrap();
        assert_eq!(opt.counts()["muon"], 64);
        let loss = |w: &Tensor, b: &Tensor| -> Tensor {
            ((w - &target).unwrap().sqr().unwrap().sum_all().unwrap()
                + b.sqr().unwrap().sum_all().unwrap())
            .unwrap()
        };
        let first = loss(&w, &b).to_scalar::<f32>().unwrap();
        for _ in 0..150 {
            let grads = loss(&w, &b).backward().unwrap();
            opt.step(&grads, 0.1).unwrap();
        }
        let w = varmap.data().lock().unwrap()["dec.layers.0.w"].as_tensor().clone();
        let b = varmap.data().lock().unwrap()["dec.bias"].as_tensor().clone();
        let last = loss(&w, &b).to_scalar::<f32>().unwrap();
        assert!(last < first * 0.1, "{first} -> {last}");

        let state = opt.state().unwrap();
        let mut other = Optimizer::new(&varmap, cfg, default_rule).unwrap();
        other.load_state(&state).unwrap();
        assert_eq!(other.steps_taken(), 150);
        let mut broken = state.clone();
        broken.remove("m.dec.bias");
        assert!(other.load_state(&broken).unwrap_err().to_string().contains("m.dec.bias"));
    }

    #[test]
    fn a_scaled_prefix_moves_by_its_share_of_the_step() {
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        let vb = candle_nn::VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        let init = candle_nn::Init::Const(1.0);
        let enc = vb.get_with_hints(4, "encoder.bias", init).unwrap();
        let dec = vb.get_with_hints(4, "decoder.bias", init).unwrap();
        let mut opt = Optimizer::new(&varmap, OptimConfig::default(), default_rule).unwrap();
        assert_eq!(opt.scale_learning_rate("encoder.", 0.25), 4);
        assert_eq!(opt.scale_learning_rate("nothing.", 0.5), 0);
        let grads = (enc.sum_all().unwrap() + dec.sum_all().unwrap()).unwrap().backward().unwrap();
        opt.step(&grads, 0.1).unwrap();
        let moved = |name: &str| {
            let v = varmap.data().lock().unwrap()[name].as_tensor().to_vec1::<f32>().unwrap();
            1.0 - v[0]
        };
        // AdamW's first step moves every value by the learning rate (no decay on biases).
        assert!((moved("decoder.bias") - 0.1).abs() < 1e-4, "{}", moved("decoder.bias"));
        assert!((moved("encoder.bias") - 0.025).abs() < 1e-4, "{}", moved("encoder.bias"));
    }
}
