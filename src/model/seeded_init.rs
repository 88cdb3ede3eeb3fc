//! Random initial weights that are the same on every run.

use std::sync::Mutex;

use candle_core::{DType, Device, Shape, Tensor, Var};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder, VarMap, init::NormalOrUniform};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal, Uniform};

/// A builder whose new variables go into `varmap`, each drawn from a generator seeded with
/// `seed` with the distribution its `Init` asks for, as training initializes them. Why: candle
/// draws a `VarMap`'s initial values from an unseeded generator, so a random network (and
/// whether, say, it ends a mesh at once) would change from run to run.
pub fn seeded_var_builder(varmap: &VarMap, seed: u64, device: &Device) -> VarBuilder<'static> {
    let backend =
        SeededInit { vars: varmap.clone(), rng: Mutex::new(ChaCha8Rng::seed_from_u64(seed)) };
    VarBuilder::from_backend(Box::new(backend), DType::F32, device.clone())
}

/// A `VarMap` backend that draws each new variable's values from a seeded generator, with the
/// distribution its `Init` asks for.
struct SeededInit {
    vars: VarMap,
    rng: Mutex<ChaCha8Rng>,
}

impl SeededInit {
    fn values(&self, shape: &Shape, init: Init) -> candle_core::Result<Vec<f32>> {
        let n = shape.elem_count();
        let draw = match init {
            Init::Const(v) => return Ok(vec![v as f32; n]),
            Init::Uniform { lo, up } => Draw::Uniform(lo, up),
            Init::Randn { mean, stdev } => Draw::Normal(mean, stdev),
            Init::Kaiming { dist, fan, non_linearity } => {
                let std = non_linearity.gain() / (fan.for_shape(shape) as f64).sqrt();
                match dist {
                    NormalOrUniform::Normal => Draw::Normal(0.0, std),
                    NormalOrUniform::Uniform => {
                        let bound = 3f64.sqrt() * std;
                        Draw::Uniform(-bound, bound)
                    }
                }
            }
        };
        let msg = |e: &dyn std::fmt::Display| candle_core::Error::Msg(e.to_string());
        let mut rng = self.rng.lock().unwrap_or_else(|p| p.into_inner());
        let rng = &mut *rng;
        Ok(match draw {
            Draw::Normal(mean, std) => {
                let d = Normal::new(mean, std).map_err(|e| msg(&e))?;
                d.sample_iter(rng).take(n).map(|x| x as f32).collect()
            }
            Draw::Uniform(lo, up) => {
                let d = Uniform::new(lo, up).map_err(|e| msg(&e))?;
                d.sample_iter(rng).take(n).map(|x| x as f32).collect()
            }
        })
    }
}

/// The distribution a random `Init` draws from.
enum Draw {
    Normal(f64, f64),
    Uniform(f64, f64),
}

impl SimpleBackend for SeededInit {
    fn get(
        &self,
        shape: Shape,
        name: &str,
        init: Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let mut vars = self.vars.data().lock().unwrap_or_else(|p| p.into_inner());
        if let Some(var) = vars.get(name) {
            if var.shape() != &shape {
                return Err(candle_core::Error::Msg(format!("{name}: asked for {shape:?} again")));
            }
            return Ok(var.as_tensor().clone());
        }
        let values = Tensor::from_vec(self.values(&shape, init)?, shape, dev)?.to_dtype(dtype)?;
        let var = Var::from_tensor(&values)?;
        let tensor = var.as_tensor().clone();
        vars.insert(name.to_string(), var);
        Ok(tensor)
    }

    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        Err(candle_core::Error::CannotFindTensor { path: name.to_string() })
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.vars.data().lock().unwrap_or_else(|p| p.into_inner()).contains_key(name)
    }
}
