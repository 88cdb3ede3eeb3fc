//! Random weights that are the same on every run.

/// Every variable of `varmap` drawn again from a generator seeded with `seed`: a matrix from a
/// normal distribution of variance 1 / its input width, a vector kept where it is constant (a
/// norm's weight, a zero bias) and zero otherwise. Why: candle draws a `VarMap`'s initial
/// values from an unseeded generator, so a test's random network, and whether it ends a mesh
/// at once, would change from run to run (one in CI did end every candidate at once).
pub fn redraw_from_seed(varmap: &candle_nn::VarMap, seed: u64) {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let vars = varmap.data().lock().unwrap();
    let mut names: Vec<&String> = vars.keys().collect();
    names.sort();
    for name in names {
        let var = &vars[name];
        let t = var.as_tensor();
        let values = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let drawn: Vec<f32> = match t.dims() {
            [.., width] if t.rank() >= 2 => {
                let normal = Normal::new(0.0, 1.0 / (*width as f32).sqrt()).unwrap();
                (0..values.len()).map(|_| normal.sample(&mut rng)).collect()
            }
            _ if values.iter().all(|&v| v == values[0]) => continue,
            _ => vec![0.0; values.len()],
        };
        let shape = t.shape().clone();
        var.set(&candle_core::Tensor::from_vec(drawn, shape, t.device()).unwrap()).unwrap();
    }
}
