//! The per-coordinate baseline: the same decoder transformer run on the 9N-token sequence (one
//! token per coordinate), for the efficiency comparison with FACE. Only the token embedding
//! (one table per coordinate slot, the slot given by the position) and the head (a linear
//! layer over Q coordinate classes plus end of mesh) differ.

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{Embedding, Init, VarBuilder};

use super::attention::Dense;
use super::cache::DecoderCache;
use super::config::{COORDS_PER_FACE, FaceConfig};
use super::decoder::DecoderStack;
use super::{ModelError, Result};

/// One baseline sequence: decoder cache and the coordinate tokens so far.
#[derive(Debug, Clone)]
pub struct BaselineState {
    cache: DecoderCache,
    tokens: Vec<u16>,
}

impl BaselineState {
    pub fn tokens(&self) -> &[u16] {
        &self.tokens
    }

    pub fn cache(&self) -> &DecoderCache {
        &self.cache
    }
}

#[derive(Debug, Clone)]
pub struct CoordinateBaseline {
    embed: Embedding,
    start: Tensor,
    stack: DecoderStack,
    head: Dense,
    quant_levels: usize,
}

impl CoordinateBaseline {
    pub fn new(cfg: &FaceConfig, vb: VarBuilder) -> Result<Self> {
        cfg.validate()?;
        let (q, d) = (cfg.quant_levels, cfg.decoder.width);
        Ok(Self {
            embed: candle_nn::embedding(COORDS_PER_FACE * q, d, vb.pp("token_embed"))?,
            start: vb.get_with_hints(d, "start", Init::Randn { mean: 0.0, stdev: 0.02 })?,
            stack: DecoderStack::new(cfg, COORDS_PER_FACE * cfg.max_faces + 1, vb.pp("decoder"))?,
            head: Dense::new(d, q + 1, true, vb.pp("head"))?,
            quant_levels: q,
        })
    }

    pub fn start_sequence(&self, latents: &Tensor) -> Result<BaselineState> {
        let latents = if latents.rank() == 2 { latents.unsqueeze(0)? } else { latents.clone() };
        Ok(BaselineState { cache: self.stack.start(&latents)?, tokens: Vec::new() })
    }

    /// Embedding ids: token i of a sequence fills coordinate slot i mod 9.
    fn ids(&self, tokens: impl Iterator<Item = (usize, u16)>) -> Vec<u32> {
        tokens
            .map(|(i, t)| ((i % COORDS_PER_FACE) * self.quant_levels + usize::from(t)) as u32)
            .collect()
    }

    /// One step for every sequence: logits (B, Q + 1) of each one's next coordinate.
    pub fn step(&self, states: &mut [&mut BaselineState]) -> Result<Tensor> {
        if states.is_empty() || states.iter().any(|s| s.cache.len() != s.tokens.len()) {
            return Err(ModelError::bad_input("every sequence needs its last token pushed"));
        }
        let dev = self.start.device();
        let last = self.ids(states.iter().map(|s| match s.tokens.last() {
            Some(&t) => (s.tokens.len() - 1, t),
            None => (0, 0),
        }));
        let mut x = Tensor::from_vec(last, states.len(), dev)?.apply(&self.embed)?;
        if states.iter().any(|s| s.tokens.is_empty()) {
            let fresh: Vec<u8> = states.iter().map(|s| u8::from(s.tokens.is_empty())).collect();
            let fresh = Tensor::from_vec(fresh, (states.len(), 1), dev)?.broadcast_as(x.shape())?;
            x = fresh.where_cond(&self.start.unsqueeze(0)?.broadcast_as(x.shape())?, &x)?;
        }
        let mut caches: Vec<&mut DecoderCache> = states.iter_mut().map(|s| &mut s.cache).collect();
        self.head.forward(&self.stack.step(&x.unsqueeze(1)?, &mut caches)?)
    }

    /// Greedy decoding without end of mesh, for benchmarks: one step, then each sequence's most
    /// likely coordinate is appended.
    pub fn step_greedy(&self, states: &mut [&mut BaselineState]) -> Result<()> {
        let logits = self.step(states)?.narrow(1, 0, self.quant_levels)?;
        let best = logits.argmax(D::Minus1)?.to_dtype(DType::U32)?.to_vec1::<u32>()?;
        for (s, b) in states.iter_mut().zip(best) {
            s.tokens.push(b as u16);
        }
        Ok(())
    }

    /// Appends a coordinate token decoded from the last step.
    pub fn push_token(&self, state: &mut BaselineState, token: u16) -> Result<()> {
        if state.cache.len() != state.tokens.len() + 1 || usize::from(token) >= self.quant_levels {
            return Err(ModelError::bad_input(format!("cannot push token {token} now")));
        }
        state.tokens.push(token);
        Ok(())
    }

    /// Teacher forcing: tokens (B, T) u32 -> logits (B, T + 1, Q + 1).
    pub fn logits(&self, latents: &Tensor, tokens: &Tensor) -> Result<Tensor> {
        let (b, t) = tokens.dims2()?;
        let dev: &Device = tokens.device();
        let flat = tokens.to_dtype(DType::U32)?.to_vec2::<u32>()?;
        let ids: Vec<u32> = flat
            .iter()
            .flat_map(|row| self.ids(row.iter().enumerate().map(|(i, &v)| (i, v as u16))))
            .collect();
        let x = Tensor::from_vec(ids, (b, t), dev)?.apply(&self.embed)?;
        let d = self.start.dim(0)?;
        let start = self.start.reshape((1, 1, d))?.broadcast_as((b, 1, d))?;
        let x = Tensor::cat(&[&start, &x], 1)?;
        self.head.forward(&self.stack.forward(&x, latents)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::checkpoint::detached_weights;
    use crate::model::testing::{max_abs_diff, random_latents};
    use candle_nn::VarMap;

    #[test]
    fn cached_steps_match_teacher_forcing() {
        let cfg = FaceConfig::micro();
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        CoordinateBaseline::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &dev)).unwrap();
        let model = CoordinateBaseline::new(
            &cfg,
            VarBuilder::from_tensors(detached_weights(&varmap), DType::F32, &dev),
        )
        .unwrap();
        let latents = random_latents(&cfg, 1, 2);
        let mut s = model.start_sequence(&latents).unwrap();
        let mut cached = Vec::new();
        for _ in 0..20 {
            cached.push(model.step(&mut [&mut s]).unwrap());
            let t = (cached.len() * 7 % cfg.quant_levels) as u16;
            model.push_token(&mut s, t).unwrap();
        }
        let tokens: Vec<u32> = s.tokens().iter().map(|&t| u32::from(t)).collect();
        let tokens = Tensor::from_vec(tokens, (1, 20), &dev).unwrap();
        let full = model.logits(&latents, &tokens).unwrap().get(0).unwrap();
        for (i, c) in cached.iter().enumerate() {
            let d = max_abs_diff(c, &full.narrow(0, i, 1).unwrap());
            assert!(d < 1e-4, "position {i}: {d}");
        }
    }
}
