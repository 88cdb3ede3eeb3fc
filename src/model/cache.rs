//! Per-sequence decoder state: data the caller (the engine) owns and passes to each step, so the
//! model itself stays stateless and sequences of different lengths can share one batched step.

use candle_core::Tensor;
use candle_nn::kv_cache::KvCache;

/// Self-attention cache capacity grows in chunks of this many positions, so a short mesh holds
/// little memory and a long one is not copied at every step.
pub const KV_CHUNK: usize = 128;

/// One sequence's state in one decoder layer.
#[derive(Debug, Clone)]
pub struct LayerCache {
    /// Keys and values of the positions seen so far, (1, H, len, hd) each.
    pub(crate) self_kv: KvCache,
}

/// The decoder's state for one sequence.
#[derive(Debug, Clone)]
pub struct DecoderCache {
    /// The latents the sequence is conditioned on, (1, K, latent_dim): what every layer's
    /// cross-attention attends to.
    pub(crate) latents: Tensor,
    pub(crate) layers: Vec<LayerCache>,
    len: usize,
}

impl DecoderCache {
    pub(crate) fn new(latents: Tensor, layers: usize) -> Self {
        let layers =
            (0..layers).map(|_| LayerCache { self_kv: KvCache::new(2, KV_CHUNK) }).collect();
        Self { latents, layers, len: 0 }
    }

    /// Positions processed so far.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub(crate) fn advance(&mut self) {
        self.len += 1;
    }

    /// Bytes held by the self-attention caches (allocated capacity, not just the used part).
    pub fn self_attention_bytes(&self) -> usize {
        let bytes = |t: &Option<Tensor>| {
            t.as_ref().map_or(0, |t| t.elem_count() * t.dtype().size_in_bytes())
        };
        self.layers
            .iter()
            .map(|l| bytes(l.self_kv.k_cache().all_data()) + bytes(l.self_kv.v_cache().all_data()))
            .sum()
    }

    /// Bytes held for cross-attention: the latents.
    pub fn cross_attention_bytes(&self) -> usize {
        self.latents.elem_count() * self.latents.dtype().size_in_bytes()
    }
}
