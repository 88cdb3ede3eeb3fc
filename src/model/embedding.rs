//! Coordinate embeddings (one table per slot of the 9) and the face-pooling MLP that turns a
//! whole face into one token. The CausalMLP head reuses the same coordinate tables for the
//! coordinates it has already chosen.

use candle_core::{DType, Tensor};
use candle_nn::{Embedding, VarBuilder};

use super::Result;
use super::attention::Mlp;
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

    /// tokens (..., n) u32 holding the coordinates of slots `first_slot..first_slot + n`
    /// -> (..., n * dim), the per-slot embeddings concatenated.
    pub fn embed(&self, tokens: &Tensor, first_slot: usize) -> Result<Tensor> {
        let n = tokens.dim(candle_core::D::Minus1)?;
        let offsets: Vec<u32> =
            (first_slot..first_slot + n).map(|s| (s * self.quant_levels) as u32).collect();
        let offsets = Tensor::from_vec(offsets, n, tokens.device())?;
        let ids = tokens.to_dtype(DType::U32)?.broadcast_add(&offsets)?;
        let e = ids.apply(&self.table)?;
        Ok(e.flatten_from(e.rank() - 2)?)
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

    /// embedded faces (..., 9 * dim) -> (..., d_model).
    pub fn forward(&self, embedded: &Tensor) -> Result<Tensor> {
        self.mlp.forward(embedded)
    }
}
