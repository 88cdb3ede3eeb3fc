//! Picking one class from logits: greedy (the paper's default) or sampling with temperature,
//! top-k and top-p, from a seeded generator so that a request is reproducible.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::ModelError;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SamplingParams {
    /// 0 means greedy.
    pub temperature: f32,
    /// Keep only the k most likely classes.
    pub top_k: Option<usize>,
    /// Keep the smallest set of most likely classes whose probability reaches p.
    pub top_p: Option<f32>,
    pub seed: u64,
}

impl Default for SamplingParams {
    fn default() -> Self {
        Self::greedy()
    }
}

impl SamplingParams {
    pub fn greedy() -> Self {
        Self { temperature: 0.0, top_k: None, top_p: None, seed: 0 }
    }

    pub fn validate(&self) -> Result<(), ModelError> {
        if !(self.temperature.is_finite() && self.temperature >= 0.0) {
            return Err(ModelError::bad_input(format!(
                "temperature {} must be >= 0",
                self.temperature
            )));
        }
        if self.top_k == Some(0) {
            return Err(ModelError::bad_input("top_k must be at least 1"));
        }
        if let Some(p) = self.top_p
            && !(p > 0.0 && p <= 1.0)
        {
            return Err(ModelError::bad_input(format!("top_p {p} must be in (0, 1]")));
        }
        Ok(())
    }
}

#[derive(Debug, Clone)]
pub struct Sampler {
    params: SamplingParams,
    rng: ChaCha8Rng,
}

impl Sampler {
    pub fn new(params: SamplingParams) -> Self {
        let rng = ChaCha8Rng::seed_from_u64(params.seed);
        Self { params, rng }
    }

    /// Temperature 0: the most likely class, no randomness.
    pub fn is_greedy(&self) -> bool {
        self.params.temperature <= 0.0
    }

    /// Picks a class among those for which `allowed` is true; `None` when none is.
    /// Non-finite logits count as the least likely.
    pub fn pick(&mut self, logits: &[f32], allowed: impl Fn(usize) -> bool) -> Option<usize> {
        let score = |l: f32| if l.is_finite() { l } else { f32::MIN };
        if self.is_greedy() {
            // Greedy: the first maximum, so ties go to the lower class.
            return logits
                .iter()
                .enumerate()
                .filter(|(i, _)| allowed(*i))
                .fold(None, |best: Option<(usize, f32)>, (i, &l)| match best {
                    Some((_, b)) if b >= score(l) => best,
                    _ => Some((i, score(l))),
                })
                .map(|(i, _)| i);
        }
        let mut cands: Vec<(usize, f32)> = logits
            .iter()
            .enumerate()
            .filter(|(i, _)| allowed(*i))
            .map(|(i, &l)| (i, score(l)))
            .collect();
        if cands.is_empty() {
            return None;
        }
        // Stable sort: ties keep the lower class first.
        cands.sort_by(|a, b| b.1.total_cmp(&a.1));
        if let Some(k) = self.params.top_k {
            cands.truncate(k);
        }
        let t = self.params.temperature;
        let top = cands[0].1;
        let mut probs: Vec<f32> = cands.iter().map(|(_, l)| ((l - top) / t).exp()).collect();
        let total: f32 = probs.iter().sum();
        probs.iter_mut().for_each(|p| *p /= total);
        if let Some(p) = self.params.top_p {
            let mut acc = 0.0;
            let keep = probs.iter().position(|&x| {
                acc += x;
                acc >= p
            });
            probs.truncate(keep.map_or(probs.len(), |i| i + 1));
        }
        let total: f32 = probs.iter().sum();
        let mut u = self.rng.random::<f32>() * total;
        for (i, p) in probs.iter().enumerate() {
            if u < *p {
                return Some(cands[i].0);
            }
            u -= p;
        }
        Some(cands[probs.len() - 1].0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn greedy_takes_the_best_allowed() {
        let mut s = Sampler::new(SamplingParams::greedy());
        let logits = [1.0, 5.0, 3.0, f32::NAN];
        assert_eq!(s.pick(&logits, |_| true), Some(1));
        assert_eq!(s.pick(&logits, |i| i != 1), Some(2));
        assert_eq!(s.pick(&logits, |i| i == 3), Some(3));
        assert_eq!(s.pick(&logits, |_| false), None);
    }

    #[test]
    fn sampling_respects_top_k_and_seed() {
        let params = SamplingParams { temperature: 1.0, top_k: Some(2), top_p: None, seed: 7 };
        let logits = [0.0, 0.1, 0.2, 0.3];
        let draw = |p: SamplingParams| {
            let mut s = Sampler::new(p);
            (0..200).map(|_| s.pick(&logits, |_| true).unwrap()).collect::<Vec<_>>()
        };
        let a = draw(params.clone());
        assert!(a.iter().all(|&i| i == 2 || i == 3));
        assert!(a.contains(&2) && a.contains(&3));
        assert_eq!(a, draw(params));
    }

    #[test]
    fn tiny_top_p_is_greedy() {
        let mut s = Sampler::new(SamplingParams {
            temperature: 1.0,
            top_k: None,
            top_p: Some(1e-6),
            seed: 1,
        });
        assert!((0..50).all(|_| s.pick(&[0.0, 2.0, 1.0], |_| true) == Some(1)));
    }

    #[test]
    fn bad_params_are_rejected() {
        let mut p = SamplingParams::greedy();
        p.temperature = -1.0;
        assert!(p.validate().is_err());
        let p = SamplingParams { top_p: Some(0.0), ..SamplingParams::greedy() };
        assert!(p.validate().is_err());
        let p = SamplingParams { top_k: Some(0), ..SamplingParams::greedy() };
        assert!(p.validate().is_err());
    }
}
