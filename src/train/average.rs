//! An exponential moving average of a run's weights (Polyak averaging), kept beside the
//! weights the optimizer moves.
//!
//! Why: at the small batches these machines afford, consecutive checkpoints of one run differ
//! more in what they decode exactly than in their loss (a box rebuilt face for face at one
//! checkpoint and two grid steps too wide at the next). The average over the last few hundred
//! steps sits between those updates' noise; a run that keeps one evaluates, keeps as best and
//! exports the average, and checkpoints it next to the raw weights so `--resume` continues it.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};
use candle_nn::VarMap;

use crate::model::checkpoint::detached_weights;

use super::{TrainError, checkpoint};

/// The averaged weights, by variable name.
pub struct WeightAverage {
    decay: f64,
    weights: HashMap<String, Tensor>,
}

impl WeightAverage {
    /// Starts the average at the current weights of `varmap`. `decay` in [0, 1): the share of
    /// the average that each step keeps; 1 / (1 - decay) steps is about how far back it
    /// reaches.
    pub fn start(decay: f64, varmap: &VarMap) -> Result<Self, TrainError> {
        if !(0.0..1.0).contains(&decay) {
            return Err(TrainError::Config(format!(
                "a weight-average decay must be in [0, 1), got {decay}"
            )));
        }
        // A copy: a detached tensor shares the variable's storage, which the optimizer
        // overwrites in place.
        let weights = detached_weights(varmap)
            .into_iter()
            .map(|(name, t)| Ok((name, t.copy()?)))
            .collect::<Result<_, TrainError>>()?;
        Ok(Self { decay, weights })
    }

    /// Replaces the averaged weights with those a checkpoint kept in its
    /// [`checkpoint::average_dir`].
    pub fn restore(&mut self, dir: &Path, device: &Device) -> Result<(), TrainError> {
        let shapes =
            self.weights.iter().map(|(name, t)| (name.clone(), t.dims().to_vec())).collect();
        self.weights = checkpoint::read_weights(dir, &shapes, device)?;
        Ok(())
    }

    /// Folds in the weights of `varmap` after the optimizer's step `step` (the run's count,
    /// from 1; a resumed run goes on counting). Early on the decay is lower, (1 + step) /
    /// (10 + step), so that the average leaves its starting point (random weights, in a fresh
    /// run) within tens of steps rather than `1 / (1 - decay)`.
    pub fn update(&mut self, varmap: &VarMap, step: u64) -> Result<(), TrainError> {
        let d = self.decay_at(step);
        for (name, current) in detached_weights(varmap) {
            if let Some(average) = self.weights.get_mut(&name) {
                *average = ((&*average * d)? + (current * (1.0 - d))?)?;
            }
        }
        Ok(())
    }

    fn decay_at(&self, step: u64) -> f64 {
        let warm = (1.0 + step as f64) / (10.0 + step as f64);
        self.decay.min(warm)
    }

    pub fn weights(&self) -> &HashMap<String, Tensor> {
        &self.weights
    }
}

#[cfg(test)]
mod tests {
    use candle_core::DType;
    use candle_nn::Init;

    use super::*;

    fn one_var(value: f32) -> (VarMap, candle_core::Var) {
        let varmap = VarMap::new();
        let t = varmap.get((2, 3), "w", Init::Const(f64::from(value)), DType::F32, &Device::Cpu);
        let var = varmap.all_vars().pop().unwrap();
        assert_eq!(t.unwrap().dims(), &[2, 3]);
        (varmap, var)
    }

    fn value(avg: &WeightAverage) -> Vec<f32> {
        avg.weights()["w"].flatten_all().unwrap().to_vec1().unwrap()
    }

    #[test]
    fn the_average_follows_the_weights_by_its_decay() {
        let (varmap, var) = one_var(0.0);
        let mut avg = WeightAverage::start(0.5, &varmap).unwrap();
        // Late steps use the configured decay: each update moves halfway to the weights.
        var.set(&Tensor::full(4f32, (2, 3), &Device::Cpu).unwrap()).unwrap();
        avg.update(&varmap, 100).unwrap();
        assert!(value(&avg).iter().all(|&v| v == 2.0), "{:?}", value(&avg));
        avg.update(&varmap, 101).unwrap();
        assert!(value(&avg).iter().all(|&v| v == 3.0));
        // The optimizer's variable itself is left alone.
        assert_eq!(var.flatten_all().unwrap().to_vec1::<f32>().unwrap(), vec![4.0; 6]);
    }

    #[test]
    fn early_steps_forget_the_start_faster() {
        let (varmap, var) = one_var(0.0);
        let mut avg = WeightAverage::start(0.999, &varmap).unwrap();
        var.set(&Tensor::ones((2, 3), DType::F32, &Device::Cpu).unwrap()).unwrap();
        // Step 1 keeps 2/11 of the start, not 0.999 of it.
        avg.update(&varmap, 1).unwrap();
        let kept = 1.0 - value(&avg)[0];
        assert!((kept - 2.0 / 11.0).abs() < 1e-6, "{kept}");
        assert_eq!(avg.decay_at(1_000_000), 0.999);
    }

    #[test]
    fn a_decay_outside_zero_to_one_is_refused() {
        let (varmap, _) = one_var(0.0);
        for decay in [1.0, -0.1, f64::NAN] {
            assert!(WeightAverage::start(decay, &varmap).is_err(), "{decay}");
        }
    }
}
