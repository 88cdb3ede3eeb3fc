//! The CausalMLP head: the hidden state of a face is decoded into its 9 coordinates one after
//! another. Sub-head j sees [h ; embeddings of coordinates 0..j-1] and outputs Q logits;
//! sub-head 0 has one extra class, end of mesh.

use std::sync::OnceLock;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use super::attention::{Dense, Mlp};
use super::config::{COORDS_PER_FACE, FaceConfig};
use super::embedding::CoordEmbedding;
use super::{ModelError, Result};

#[derive(Debug, Clone)]
pub struct CausalHead {
    sub_heads: Vec<Mlp>,
    width: usize,
    coord_dim: usize,
    /// The first layers folded for decoding: made from the weights on first use.
    folded: OnceLock<FoldedHead>,
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
        Ok(Self { sub_heads, width: d, coord_dim: dc, folded: OnceLock::new() })
    }

    pub fn dense_mut(&mut self) -> Vec<&mut Dense> {
        // The caller may change them (quantize them): fold them again when next used.
        self.folded = OnceLock::new();
        self.sub_heads.iter_mut().flat_map(Mlp::dense_mut).collect()
    }

    /// context (..., d + j * coord_dim) -> logits (..., Q), or (..., Q + 1) for j = 0 where the
    /// last class is end of mesh.
    pub fn logits(&self, j: usize, context: &Tensor) -> Result<Tensor> {
        let head = self.sub_head(j)?;
        let expected = self.width + j * self.coord_dim;
        let found = context.dim(candle_core::D::Minus1)?;
        if found != expected {
            return Err(ModelError::bad_input(format!(
                "sub-head {j} takes a context of width {expected}, got {found}"
            )));
        }
        head.forward(context)
    }

    fn sub_head(&self, j: usize) -> Result<&Mlp> {
        self.sub_heads.get(j).ok_or_else(|| no_coordinate(j))
    }

    /// The head folded with the coordinate embeddings `coords` for decoding; `None` while its
    /// weights are training variables (they change as they train, and training never decodes
    /// enough faces for a fold to pay).
    pub fn folded(&self, coords: &CoordEmbedding) -> Result<Option<&FoldedHead>> {
        if let Some(folded) = self.folded.get() {
            return Ok(Some(folded));
        }
        if self.sub_heads.iter().any(|m| m.layers().0.is_training()) {
            return Ok(None);
        }
        let folded = FoldedHead::new(self, coords)?;
        Ok(Some(self.folded.get_or_init(|| folded)))
    }
}

/// The head with its first layers folded, for decoding. Sub-head j's first layer on
/// [h ; e_0(c_0) ; ... ; e_{j-1}(c_{j-1})] is A_j h + b_j + sum over i of B_ji e_i(c_i), and
/// B_ji e_i(c) is one of Q rows of a table. So the part on h is one matmul per row for all 9
/// sub-heads at once, not one per partial face and coordinate, and the part on the coordinates
/// is a sum of table rows, not a matmul over a context that grows by a concatenation per
/// coordinate. The same logits as [`CausalHead::logits`], up to rounding.
#[derive(Debug, Clone)]
pub struct FoldedHead {
    /// Every sub-head's first layer on h, stacked: (9 * hidden) outputs, biases included.
    on_state: Dense,
    /// B_ji e_i(c) for i < j, `hidden` values, at row [`table_row`]`(j, i) * Q + c`.
    tables: Vec<f32>,
    /// Every sub-head's second layer.
    second: Vec<Dense>,
    hidden: usize,
    quant_levels: usize,
    device: Device,
}

impl FoldedHead {
    fn new(head: &CausalHead, coords: &CoordEmbedding) -> Result<Self> {
        let (d, dc) = (head.width, head.coord_dim);
        let embeddings = coords.tables().to_dtype(DType::F64)?;
        let quant_levels = embeddings.dim(0)? / COORDS_PER_FACE;
        let (mut on_state, mut biases, mut tables) = (Vec::new(), Vec::new(), Vec::new());
        let mut hidden = 0;
        for (j, sub_head) in head.sub_heads.iter().enumerate() {
            let (weight, bias) = sub_head.layers().0.values()?;
            hidden = weight.dim(0)?;
            on_state.push(weight.narrow(1, 0, d)?);
            biases.push(bias.ok_or_else(|| {
                ModelError::bad_input(format!("sub-head {j}'s first layer has no bias"))
            })?);
            // In f64, so that each table row rounds once.
            let weight = weight.to_dtype(DType::F64)?;
            for i in 0..j {
                let e = embeddings.narrow(0, i * quant_levels, quant_levels)?;
                // Contiguous: CUDA's matmul takes no column slice (the CPU takes any layout).
                let b = weight.narrow(1, d + i * dc, dc)?.contiguous()?;
                let rows = e.matmul(&b.t()?)?.to_dtype(DType::F32)?;
                tables.extend(rows.flatten_all()?.to_vec1::<f32>()?);
            }
        }
        let name = format!("{} folded", head.sub_heads[0].layers().0.name().unwrap_or("head"));
        let on_state =
            Dense::inference(name, &Tensor::cat(&on_state, 0)?, Some(Tensor::cat(&biases, 0)?))?;
        let second = head.sub_heads.iter().map(|m| m.layers().1.clone()).collect();
        let device = embeddings.device().clone();
        Ok(Self { on_state, tables, second, hidden, quant_levels, device })
    }

    /// Every row's first-layer part on its decoder state (rows, d), for every sub-head: row r's
    /// values for sub-head j at `(r * 9 + j) * hidden`.
    pub fn on_states(&self, states: &Tensor) -> Result<Vec<f32>> {
        Ok(self.on_state.forward(states)?.flatten_all()?.to_vec1::<f32>()?)
    }

    /// Sub-head j's logits (one row per partial face, as [`CausalHead::logits`]) for partial
    /// faces given as (row of `on_states`, coordinates decided so far).
    pub fn logits<'a>(
        &self,
        j: usize,
        on_states: &[f32],
        partials: impl ExactSizeIterator<Item = (usize, &'a [u16])>,
    ) -> Result<Tensor> {
        let (h, q) = (self.hidden, self.quant_levels);
        let second = self.second.get(j).ok_or_else(|| no_coordinate(j))?;
        let n = partials.len();
        let mut first = Vec::with_capacity(n * h);
        for (row, coords) in partials {
            let at = (row * COORDS_PER_FACE + j) * h;
            let start = first.len();
            first.extend_from_slice(
                on_states.get(at..at + h).ok_or_else(|| {
                    ModelError::bad_input(format!("no decoder state for row {row}"))
                })?,
            );
            let sum = &mut first[start..];
            for (i, &c) in coords.iter().enumerate().take(j) {
                let c = usize::from(c);
                if c >= q {
                    return Err(ModelError::bad_input(format!("coordinate value {c} of {q}")));
                }
                let at = (table_row(j, i) * q + c) * h;
                for (s, t) in sum.iter_mut().zip(&self.tables[at..at + h]) {
                    *s += t;
                }
            }
            // SiLU, as `Mlp::forward` applies it.
            for s in sum.iter_mut() {
                *s /= 1.0 + (-*s).exp();
            }
        }
        second.forward(&Tensor::from_vec(first, (n, h), &self.device)?)
    }
}

fn no_coordinate(j: usize) -> ModelError {
    ModelError::bad_input(format!("coordinate {j} out of 0..{COORDS_PER_FACE}"))
}

/// Where the table of sub-head j's coordinate i < j starts, in tables: those of sub-head 1,
/// then the two of sub-head 2, and so on.
fn table_row(j: usize, i: usize) -> usize {
    j * (j - 1) / 2 + i
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::testing::{max_abs_diff, random_model};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Folded, every sub-head gives the logits of the context it would have read, for partial
    /// faces of several rows in any order.
    #[test]
    fn the_folded_head_gives_the_context_logits() {
        let cfg = FaceConfig::micro();
        let model = random_model(&cfg).1;
        let (d, q) = (cfg.decoder.width, cfg.quant_levels);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let states: Vec<f32> = (0..3 * d).map(|_| rng.random_range(-2.0..2.0)).collect();
        let states = Tensor::from_vec(states, (3, d), &Device::Cpu).unwrap();
        let folded = model.folded_head().unwrap().expect("an inference model folds its head");
        let on_states = folded.on_states(&states).unwrap();
        let partials: Vec<(usize, [u16; COORDS_PER_FACE])> = (0..7)
            .map(|p| (p % 3, std::array::from_fn(|_| rng.random_range(0..q as u16))))
            .collect();
        for j in 0..COORDS_PER_FACE {
            let rows: Vec<u32> = partials.iter().map(|(r, _)| *r as u32).collect();
            let ids = Tensor::from_vec(rows, partials.len(), &Device::Cpu).unwrap();
            let mut context = states.index_select(&ids, 0).unwrap();
            for i in 0..j {
                let column: Vec<u16> = partials.iter().map(|(_, c)| c[i]).collect();
                context = model.extend_context(&context, i, &column).unwrap();
            }
            let expected = model.head_logits(j, &context).unwrap();
            let found =
                folded.logits(j, &on_states, partials.iter().map(|(r, c)| (*r, &c[..]))).unwrap();
            assert_eq!(found.dims(), expected.dims());
            let diff = max_abs_diff(&found, &expected);
            assert!(diff < 1e-4, "sub-head {j}: {diff}");
        }
    }
}
