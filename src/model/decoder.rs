//! The decoder transformer shared by FACE and the per-coordinate baseline: pre-norm layers of
//! causal self-attention (RoPE), cross-attention to the latents, and an MLP. Only the token
//! embedding and the output head differ between the two models.

use std::borrow::Cow;
use std::sync::OnceLock;

use candle_core::Tensor;
use candle_nn::VarBuilder;
use candle_nn::kv_cache::KvCache;

use super::attention::{
    CrossAttention, Dense, LatentCrossAttention, Mlp, Norm, Rope, SelfAttention, causal_mask,
};
use super::cache::DecoderCache;
use super::config::FaceConfig;
use super::{ModelError, Result};

#[derive(Debug, Clone)]
struct DecoderLayer {
    self_norm: Norm,
    self_attn: SelfAttention,
    cross_norm: Norm,
    cross_attn: CrossAttention,
    mlp_norm: Norm,
    mlp: Mlp,
}

impl DecoderLayer {
    fn new(cfg: &FaceConfig, vb: VarBuilder) -> Result<Self> {
        let d = &cfg.decoder;
        Ok(Self {
            self_norm: Norm::new(d.width, cfg.norm_eps, vb.pp("self_norm"))?,
            self_attn: SelfAttention::new(d.width, d.heads, vb.pp("self_attn"))?,
            cross_norm: Norm::new(d.width, cfg.norm_eps, vb.pp("cross_norm"))?,
            cross_attn: CrossAttention::new(d.width, d.heads, vb.pp("cross_attn"))?,
            mlp_norm: Norm::new(d.width, cfg.norm_eps, vb.pp("mlp_norm"))?,
            mlp: Mlp::new(d.width, d.mlp_hidden, d.width, vb.pp("mlp"))?,
        })
    }

    fn dense_mut(&mut self) -> Vec<&mut Dense> {
        let mut layers = self.self_attn.dense_mut();
        layers.extend(self.cross_attn.dense_mut());
        layers.extend(self.mlp.dense_mut());
        layers
    }
}

#[derive(Debug, Clone)]
pub struct DecoderStack {
    latent_up: Dense,
    layers: Vec<DecoderLayer>,
    norm: Norm,
    rope: Rope,
    latent_dim: usize,
    width: usize,
    /// Every layer's cross-attention folded onto the latents, for [`Self::step`]: made from the
    /// weights on first use.
    on_latents: OnceLock<Vec<LatentCrossAttention>>,
}

impl DecoderStack {
    /// `max_positions`: the longest token sequence (start token included) this stack serves.
    pub fn new(cfg: &FaceConfig, max_positions: usize, vb: VarBuilder) -> Result<Self> {
        let d = &cfg.decoder;
        Ok(Self {
            latent_up: Dense::new(cfg.latent_dim, d.width, true, vb.pp("latent_up"))?,
            layers: (0..d.layers)
                .map(|i| DecoderLayer::new(cfg, vb.pp(format!("layers.{i}"))))
                .collect::<Result<_>>()?,
            norm: Norm::new(d.width, cfg.norm_eps, vb.pp("norm"))?,
            rope: Rope::new(d.head_dim(), max_positions, cfg.rope_theta, vb.device())?,
            latent_dim: cfg.latent_dim,
            width: d.width,
            on_latents: OnceLock::new(),
        })
    }

    /// Every linear layer, in checkpoint order.
    pub fn dense_mut(&mut self) -> Vec<&mut Dense> {
        // The caller may change them (quantize them): fold them again when next used.
        self.on_latents = OnceLock::new();
        let mut layers = vec![&mut self.latent_up];
        layers.extend(self.layers.iter_mut().flat_map(DecoderLayer::dense_mut));
        layers
    }

    pub fn max_positions(&self) -> usize {
        self.rope.max_positions()
    }

    fn check_latents(&self, latents: &Tensor) -> Result<()> {
        match latents.dims() {
            [_, k, c] if *k > 0 && *c == self.latent_dim => Ok(()),
            dims => Err(ModelError::bad_input(format!(
                "latents {dims:?} must be (B, K, {})",
                self.latent_dim
            ))),
        }
    }

    /// Every layer's cross-attention folded onto the latents; made again on every call while
    /// the weights are training variables, which change as they train.
    fn on_latents(&self) -> Result<Cow<'_, [LatentCrossAttention]>> {
        if let Some(folded) = self.on_latents.get() {
            return Ok(Cow::Borrowed(folded));
        }
        let folded = self
            .layers
            .iter()
            .map(|l| l.cross_attn.on_latents(&self.latent_up))
            .collect::<Result<Vec<_>>>()?;
        if self.latent_up.is_training() {
            return Ok(Cow::Owned(folded));
        }
        Ok(Cow::Borrowed(self.on_latents.get_or_init(|| folded)))
    }

    /// A fresh cache for one sequence conditioned on `latents` (1, K, latent_dim).
    pub fn start(&self, latents: &Tensor) -> Result<DecoderCache> {
        self.check_latents(latents)?;
        if latents.dim(0)? != 1 {
            return Err(ModelError::bad_input(format!(
                "one sequence starts from one latent set, got {:?}",
                latents.dims()
            )));
        }
        Ok(DecoderCache::new(latents.detach(), self.layers.len()))
    }

    /// Whole sequences at once (teacher forcing, or the reference for cached decoding):
    /// x (B, T, d) at positions 0..T, latents (B, K, latent_dim) -> final hidden (B, T, d).
    pub fn forward(&self, x: &Tensor, latents: &Tensor) -> Result<Tensor> {
        self.check_latents(latents)?;
        let (b, t, d) = x.dims3()?;
        if d != self.width || latents.dim(0)? != b {
            return Err(ModelError::bad_input(format!(
                "inputs {:?} do not fit latents {:?} and width {}",
                x.dims(),
                latents.dims(),
                self.width
            )));
        }
        if t > self.max_positions() {
            return Err(ModelError::SequenceTooLong {
                position: t - 1,
                limit: self.max_positions(),
            });
        }
        let memory = self.latent_up.forward(latents)?;
        let mask = causal_mask(t, x.device())?;
        let mut x = x.clone();
        for l in &self.layers {
            let h = l.self_norm.forward(&x)?;
            x = (&x + l.self_attn.forward(&h, Some(&self.rope), Some(&mask))?)?;
            let (k, v) = l.cross_attn.memory_kv(&memory)?;
            x = (&x + l.cross_attn.forward(&l.cross_norm.forward(&x)?, &k, &v)?)?;
            x = (&x + l.mlp.forward(&l.mlp_norm.forward(&x)?)?)?;
        }
        self.norm.forward(&x)
    }

    /// One position for each sequence: x (B, 1, d) holds each row's next input token; row `r`
    /// sits at position `caches[r].len()`, whatever the others' lengths. Returns the final
    /// hidden states (B, d) and advances every cache by one.
    pub fn step(&self, x: &Tensor, caches: &mut [&mut DecoderCache]) -> Result<Tensor> {
        let (b, t, d) = x.dims3()?;
        if b != caches.len() || t != 1 || d != self.width {
            return Err(ModelError::bad_input(format!(
                "step input {:?} must be ({}, 1, {})",
                x.dims(),
                caches.len(),
                self.width
            )));
        }
        if let Some(c) = caches.iter().find(|c| c.layers.len() != self.layers.len()) {
            return Err(ModelError::bad_input(format!(
                "a cache has {} layers, the decoder {}",
                c.layers.len(),
                self.layers.len()
            )));
        }
        let positions: Vec<usize> = caches.iter().map(|c| c.len()).collect();
        if let Some(&p) = positions.iter().find(|&&p| p >= self.max_positions()) {
            return Err(ModelError::SequenceTooLong { position: p, limit: self.max_positions() });
        }
        let rope = self.rope.rows(&positions)?;
        let on_latents = self.on_latents()?;
        // Cheap handles (reference-counted storage), not copies.
        let latents: Vec<Tensor> = caches.iter().map(|c| c.latents.clone()).collect();
        let mut x = x.clone();
        for ((i, l), cross) in self.layers.iter().enumerate().zip(on_latents.iter()) {
            let h = l.self_norm.forward(&x)?;
            let mut kv: Vec<&mut KvCache> =
                caches.iter_mut().map(|c| &mut c.layers[i].self_kv).collect();
            x = (&x + l.self_attn.step(&h, &rope, &mut kv)?)?;
            x = (&x + cross.step(&l.cross_norm.forward(&x)?, &latents)?)?;
            x = (&x + l.mlp.forward(&l.mlp_norm.forward(&x)?)?)?;
        }
        for c in caches.iter_mut() {
            c.advance();
        }
        Ok(self.norm.forward(&x)?.squeeze(1)?.contiguous()?.reshape((b, d))?)
    }
}
