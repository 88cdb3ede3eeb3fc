//! The CausalMLP head: the hidden state of a face is decoded into its 9 coordinates one after
//! another. Sub-head j sees [h ; embeddings of coordinates 0..j-1] and outputs Q logits;
//! sub-head 0 has one extra class, end of mesh.

use candle_core::Tensor;
use candle_nn::VarBuilder;

use super::attention::{Dense, Mlp};
use super::config::{COORDS_PER_FACE, FaceConfig};
use super::{ModelError, Result};

#[derive(Debug, Clone)]
pub struct CausalHead {
    sub_heads: Vec<Mlp>,
    width: usize,
    coord_dim: usize,
}

impl CausalHead {
    pub fn new(cfg: &FaceConfig, vb: VarBuilder) -> Result<Self> {
        let (d, dc, q) = (cfg.decoder.width, cfg.coord_embed_dim, cfg.quant_levels);
        let sub_heads = (0..COORDS_PER_FACE)
            .map(|j| {
                let classes = q + usize::from(j == 0);
                Mlp::new(d + j * dc, cfg.head_hidden, classes, vb.pp(format!("sub.{j}")))
            })
            .collect::<Result<_>>()?;
        Ok(Self { sub_heads, width: d, coord_dim: dc })
    }

    pub fn dense_mut(&mut self) -> Vec<&mut Dense> {
        self.sub_heads.iter_mut().flat_map(Mlp::dense_mut).collect()
    }

    /// context (..., d + j * coord_dim) -> logits (..., Q), or (..., Q + 1) for j = 0 where the
    /// last class is end of mesh.
    pub fn logits(&self, j: usize, context: &Tensor) -> Result<Tensor> {
        let head = self.sub_heads.get(j).ok_or_else(|| {
            ModelError::bad_input(format!("coordinate {j} out of 0..{COORDS_PER_FACE}"))
        })?;
        let expected = self.width + j * self.coord_dim;
        let found = context.dim(candle_core::D::Minus1)?;
        if found != expected {
            return Err(ModelError::bad_input(format!(
                "sub-head {j} takes a context of width {expected}, got {found}"
            )));
        }
        head.forward(context)
    }
}
