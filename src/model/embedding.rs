//! Coordinate embeddings (one table per slot of the 9) and the face-pooling MLP that turns a
//! whole face into one token. The CausalMLP head reuses the same coordinate tables for the
//! coordinates it has already chosen.

use candle_core::{DType, Tensor};
use candle_nn::{Embedding, VarBuilder};

use super::Result;
use super::attention::{Dense, Mlp};
use super::config::{COORDS_PER_FACE, FaceConfig};

#[derive(Debug, Clone)]
pub struct CoordEmbedding {
    /// The 9 tables stacked: row `slot * Q + value`.
    table: Embedding,
    quant_levels: usize,
    dim: usize,
}

impl CoordEmbedding {
    pub fn new(cfg: &FaceConfig, vb: VarBuilder) -> Result<Self> {
        let rows = COORDS_PER_FACE * cfg.quant_levels;
        Ok(Self {
            table: candle_nn::embedding(rows, cfg.coord_embed_dim, vb)?,
            quant_levels: cfg.quant_levels,
            dim: cfg.coord_embed_dim,
        })
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The 9 tables stacked, (9 * Q, dim): row `slot * Q + value`.
    pub fn tables(&self) -> &Tensor {
        self.table.embeddings()
    }

    /// tokens (..., n) u32 holding the coordinates of slots `first_slot..first_slot + n`
    /// -> (..., n * dim), the per-slot embeddings concatenated.
    pub fn embed(&self, tokens: &Tensor, first_slot: usize) -> Result<Tensor> {
        let n = tokens.dim(candle_core::D::Minus1)?;
        if self.table.embeddings().track_op() {
            return self.embed_one_hot(tokens, first_slot, n);
        }
        let offsets: Vec<u32> =
            (first_slot..first_slot + n).map(|s| (s * self.quant_levels) as u32).collect();
        let offsets = Tensor::from_vec(offsets, n, tokens.device())?;
        let ids = tokens.to_dtype(DType::U32)?.broadcast_add(&offsets)?;
        let e = ids.apply(&self.table)?;
        Ok(e.flatten_from(e.rank() - 2)?)
    }

    /// [`Self::embed`] for training: each slot's one-hot rows times its table, one batched
    /// matmul, so that the gradient is a matmul too. A lookup's gradient (`index_add`) runs on
    /// CUDA one thread per embedding column, each looping over every index of the batch in
    /// turn: 32 threads over hundreds of thousands of indices per training step.
    fn embed_one_hot(&self, tokens: &Tensor, first_slot: usize, n: usize) -> Result<Tensor> {
        let (q, dim) = (self.quant_levels, self.dim);
        let rows = tokens.elem_count() / n.max(1);
        let device = tokens.device();
        // (n, rows, 1) == (1, 1, Q): slot-major one-hot rows.
        let slots = tokens.to_dtype(DType::U32)?.reshape((rows, n))?.t()?.contiguous()?;
        let levels = Tensor::arange(0u32, q as u32, device)?.reshape((1, 1, q))?;
        let one_hot = slots.unsqueeze(2)?.broadcast_eq(&levels)?.to_dtype(DType::F32)?;
        let tables =
            self.table.embeddings().narrow(0, first_slot * q, n * q)?.reshape((n, q, dim))?;
        let e = one_hot.matmul(&tables)?.transpose(0, 1)?.reshape((rows, n * dim))?;
        let mut dims = tokens.dims().to_vec();
        if let Some(last) = dims.last_mut() {
            *last = n * dim;
        }
        Ok(e.reshape(dims)?)
    }
}

/// Face pooling: the 9 concatenated coordinate embeddings -> one d_model token.
#[derive(Debug, Clone)]
pub struct FacePooling {
    mlp: Mlp,
}

impl FacePooling {
    pub fn new(cfg: &FaceConfig, vb: VarBuilder) -> Result<Self> {
        let d = cfg.decoder.width;
        Ok(Self { mlp: Mlp::new(COORDS_PER_FACE * cfg.coord_embed_dim, d, d, vb)? })
    }

    pub fn dense_mut(&mut self) -> Vec<&mut Dense> {
        self.mlp.dense_mut()
    }

    /// embedded faces (..., 9 * dim) -> (..., d_model).
    pub fn forward(&self, embedded: &Tensor) -> Result<Tensor> {
        self.mlp.forward(embedded)
    }
}

#[cfg(test)]
mod tests {
    use candle_core::Device;
    use candle_nn::VarMap;

    use super::*;

    #[test]
    fn training_embeds_and_learns_as_the_lookup_does() {
        let cfg = FaceConfig { quant_levels: 16, coord_embed_dim: 4, ..FaceConfig::micro() };
        let varmap = VarMap::new();
        let trained =
            CoordEmbedding::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu))
                .unwrap();
        let table = varmap.all_vars().pop().unwrap();
        // The same table behind a plain lookup, as inference builds it.
        let lookup = CoordEmbedding {
            table: Embedding::new(table.as_tensor().detach(), cfg.coord_embed_dim),
            ..trained.clone()
        };
        let tokens =
            Tensor::new(&[[[3u32, 15, 0], [7, 7, 1]], [[0, 2, 9], [15, 4, 4]]], &Device::Cpu)
                .unwrap();
        let (a, b) = (trained.embed(&tokens, 2).unwrap(), lookup.embed(&tokens, 2).unwrap());
        assert_eq!(a.dims(), &[2, 2, 12]);
        assert_eq!(a.to_vec3::<f32>().unwrap(), b.to_vec3::<f32>().unwrap());

        // d(sum of squares)/d(row) = 2 x row x (times the row is looked up).
        let grads = a.sqr().unwrap().sum_all().unwrap().backward().unwrap();
        let grad = grads.get(table.as_tensor()).unwrap().to_vec2::<f32>().unwrap();
        let rows = table.as_tensor().to_vec2::<f32>().unwrap();
        let mut uses = vec![0f32; rows.len()];
        for (i, &t) in tokens.flatten_all().unwrap().to_vec1::<u32>().unwrap().iter().enumerate() {
            uses[(2 + i % 3) * 16 + t as usize] += 1.0;
        }
        for (r, row) in rows.iter().enumerate() {
            for (g, v) in grad[r].iter().zip(row) {
                assert!((g - 2.0 * v * uses[r]).abs() < 1e-5, "row {r}");
            }
        }
    }
}
