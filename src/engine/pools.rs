//! Where model work runs: a batch is stepped in parts, one per decode thread, and a batch too
//! small to split runs on a single thread. `meshstream` keeps candle's own kernels on the
//! thread of their part (`src/kernel_threads.rs`), so the parts are the only parallelism.

use rayon::prelude::*;

use crate::model::{FaceModel, Generation, ModelError, StepEvent, step_generations};

use super::EngineError;

/// Rows below which a part of the batch is not worth a thread of its own. Why 2: a whole mesh
/// alone on the server steps its 4 candidates as 2 parts of 2, on both cores. A step of few
/// rows mostly reads the weights, so each part costs about what the whole did: a whole mesh
/// whose candidates all ran to the 300-face budget answered in 0.84-0.92 s against 1.06-1.09 s
/// with parts of at least 4, for 1.4x the CPU, and 16 clients (parts of 10 rows and more)
/// stayed within noise (`docs/decisions.md`, "Serving").
const MIN_ROWS_PER_THREAD: usize = 2;

pub struct DecodePools {
    /// One thread per core (or `decode_threads`): parts of the batch in parallel, and
    /// diffusion.
    wide: rayon::ThreadPool,
    single: rayon::ThreadPool,
}

/// One part of a stepped batch: its rows' events in order, or the error that failed them all.
pub type PartResult = Result<Vec<StepEvent>, ModelError>;

impl DecodePools {
    /// Pools for `threads` threads (at least 1).
    pub fn new(threads: usize) -> Result<Self, EngineError> {
        let pool = |threads: usize, name: &'static str| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .thread_name(move |i| format!("{name}-{i}"))
                .build()
                .map_err(|e| EngineError::Model(format!("cannot start the decode threads: {e}")))
        };
        Ok(Self {
            wide: pool(threads.max(1), "engine-decode")?,
            single: pool(1, "engine-decode-single")?,
        })
    }

    /// The pool for work that uses every thread (diffusion).
    pub fn wide(&self) -> &rayon::ThreadPool {
        &self.wide
    }

    /// Rows per part when `rows` rows are stepped together.
    pub fn part_size(&self, rows: usize) -> usize {
        rows.div_ceil(self.wide.current_num_threads()).max(MIN_ROWS_PER_THREAD)
    }

    /// The pool that steps `rows` rows together: the single thread when they make one part.
    pub fn pool_for(&self, rows: usize) -> &rayon::ThreadPool {
        if rows <= self.part_size(rows) { &self.single } else { &self.wide }
    }

    /// Steps every row's generation by one face, in parts of [`Self::part_size`] rows on
    /// threads of their own (one part on the single thread): one result per part, in order.
    pub fn step<R: Send>(
        &self,
        model: &FaceModel,
        rows: &mut [R],
        generation: impl Fn(&mut R) -> &mut Generation + Sync,
    ) -> Vec<PartResult> {
        let part = self.part_size(rows.len());
        self.pool_for(rows.len()).install(|| {
            rows.par_chunks_mut(part)
                .map(|part| {
                    let mut gens: Vec<&mut Generation> = part.iter_mut().map(&generation).collect();
                    step_generations(model, &mut gens)
                })
                .collect()
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::testing::{random_latents, random_model};
    use crate::model::{FaceConfig, GenerateOptions};

    #[test]
    fn a_batch_steps_in_parts_as_its_rows_would_alone() {
        let pools = DecodePools::new(2).unwrap();
        assert_eq!([1, 3, 4, 8, 9, 64].map(|rows| pools.part_size(rows)), [2, 2, 2, 4, 5, 32]);
        // Two rows make one part, on the single thread; from three they split.
        assert!(std::ptr::eq(pools.pool_for(2), &pools.single));
        assert!(std::ptr::eq(pools.pool_for(3), &pools.wide));
        let cfg = FaceConfig::micro();
        let (_, model) = random_model(&cfg);
        let options = GenerateOptions { max_faces: 6, ..GenerateOptions::default() };
        let start = |seed| Generation::new(&model, &random_latents(&cfg, 1, seed), options.clone());
        let mut batch: Vec<Generation> = (0..9).map(|seed| start(seed).unwrap()).collect();
        let mut alone: Vec<Generation> = (0..9).map(|seed| start(seed).unwrap()).collect();
        for _ in 0..3 {
            let parts = pools.step(&model, &mut batch, |g| g);
            assert_eq!(parts.iter().map(|p| p.as_ref().unwrap().len()).collect::<Vec<_>>(), [5, 4]);
            for g in &mut alone {
                step_generations(&model, &mut [g]).unwrap();
            }
        }
        for (b, a) in batch.iter().zip(&alone) {
            assert_eq!(b.faces(), a.faces());
        }
    }
}
