//! Generation: per-sequence sampling and constraints on top of the stateless network, one
//! batched iteration at a time (what the engine's continuous batching calls), plus a
//! streaming iterator and a callback API for a single request.

use std::ops::ControlFlow;

use candle_core::Tensor;

use super::face_search::{Choice, RowSearch, choose_faces};
use super::sampling::{Sampler, SamplingParams};
use super::{FaceModel, FaceToken, ModelError, Result, SequenceState};

/// Partial faces kept by greedy decoding; see `face_search`.
pub const DEFAULT_FACE_BEAM: usize = 4;

/// The sampling temperature of a request that does not give one (the CLI's and the server's):
/// 0, greedy decoding with the face beam, the paper's default. Why: the shipped model's samples
/// are a soup of overlapping slivers. Fitted, four samples end closer to the input (dev CD
/// 0.031 against 0.046 for four greedy candidates), but 78% of their edges are open and a mesh
/// falls into 43 parts, against 37% and 4 (the truth: 5% and 9; `docs/decisions.md`,
/// "Decoding").
pub const DEFAULT_TEMPERATURE: f32 = 0.0;

/// The widest face beam a request may ask for: the head runs once per kept partial face.
pub const MAX_FACE_BEAM: usize = 32;

#[derive(Debug, Clone, PartialEq)]
pub struct GenerateOptions {
    pub sampling: SamplingParams,
    /// Face budget; capped by the model's `max_faces`.
    pub max_faces: usize,
    /// End of mesh is not allowed before this many faces.
    pub min_faces: usize,
    /// Mask logits so that every face is canonical and after the previous one.
    pub constrained: bool,
    /// Greedy decoding keeps this many partial faces while it picks a face's 9 coordinates,
    /// and takes the most likely whole face (see `face_search`); 1 is per-coordinate greedy.
    pub face_beam: usize,
}

impl Default for GenerateOptions {
    fn default() -> Self {
        Self {
            sampling: SamplingParams::greedy(),
            max_faces: usize::MAX,
            min_faces: 0,
            constrained: true,
            face_beam: DEFAULT_FACE_BEAM,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FinishReason {
    /// The model chose end of mesh.
    EndOfMesh,
    /// The face budget is used up.
    MaxFaces,
    /// No canonical face can follow the last one (constrained decoding only).
    DeadEnd,
    /// The caller stopped the stream.
    Cancelled,
    /// Not the model's: a reconstruction answered with the convex hull of its input points, which
    /// ended at least 10% closer to them than every decoded candidate
    /// ([`crate::candidates::hull_candidate`]).
    ConvexHull,
}

impl FinishReason {
    /// snake_case, as in metrics labels and API responses.
    pub fn name(self) -> &'static str {
        match self {
            Self::EndOfMesh => "end_of_mesh",
            Self::MaxFaces => "max_faces",
            Self::DeadEnd => "dead_end",
            Self::Cancelled => "cancelled",
            Self::ConvexHull => "convex_hull",
        }
    }
}

/// One request being generated: its decoder state, sampler and options.
#[derive(Debug, Clone)]
pub struct Generation {
    state: SequenceState,
    sampler: Sampler,
    options: GenerateOptions,
    finish: Option<FinishReason>,
}

impl Generation {
    /// Starts a generation from one latent set ((K, latent_dim) or (1, K, latent_dim)).
    pub fn new(model: &FaceModel, latents: &Tensor, mut options: GenerateOptions) -> Result<Self> {
        options.sampling.validate()?;
        options.max_faces = options.max_faces.min(model.config().max_faces);
        if options.min_faces > options.max_faces {
            return Err(ModelError::bad_input(format!(
                "min_faces {} exceeds max_faces {}",
                options.min_faces, options.max_faces
            )));
        }
        if !(1..=MAX_FACE_BEAM).contains(&options.face_beam) {
            return Err(ModelError::bad_input(format!(
                "face_beam {} must be in 1..={MAX_FACE_BEAM}",
                options.face_beam
            )));
        }
        let finish = (options.max_faces == 0).then_some(FinishReason::MaxFaces);
        Ok(Self {
            state: model.start_sequence(latents)?,
            sampler: Sampler::new(options.sampling.clone()),
            options,
            finish,
        })
    }

    pub fn faces(&self) -> &[FaceToken] {
        self.state.faces()
    }

    pub fn state(&self) -> &SequenceState {
        &self.state
    }

    pub fn finish_reason(&self) -> Option<FinishReason> {
        self.finish
    }

    pub fn is_finished(&self) -> bool {
        self.finish.is_some()
    }

    /// Marks the generation finished (a closed client stream, say).
    pub fn cancel(&mut self) {
        self.finish.get_or_insert(FinishReason::Cancelled);
    }
}

/// What one iteration did to one generation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepEvent {
    pub face: Option<FaceToken>,
    pub finished: Option<FinishReason>,
}

/// One iteration for a batch of generations of any lengths: one batched decoder step for the
/// unfinished ones, then each row's next face, coordinate by coordinate, under its own sampling
/// parameters and constraints. Returns one event per input row (finished rows only repeat
/// their reason).
pub fn step_generations(model: &FaceModel, gens: &mut [&mut Generation]) -> Result<Vec<StepEvent>> {
    let mut events: Vec<StepEvent> =
        gens.iter().map(|g| StepEvent { face: None, finished: g.finish }).collect();
    let active: Vec<usize> = (0..gens.len()).filter(|&i| gens[i].finish.is_none()).collect();
    if active.is_empty() {
        return Ok(events);
    }
    let hidden = {
        let mut states: Vec<&mut SequenceState> = Vec::with_capacity(active.len());
        for (i, g) in gens.iter_mut().enumerate() {
            if events[i].finished.is_none() {
                states.push(&mut g.state);
            }
        }
        model.step(&mut states)?
    };
    let choices = {
        let mut searches: Vec<RowSearch> = gens
            .iter_mut()
            .filter(|g| g.finish.is_none())
            .map(|g| RowSearch {
                sampler: &mut g.sampler,
                earlier: g.state.faces(),
                constrained: g.options.constrained,
                eos_ok: g.state.faces().len() >= g.options.min_faces,
                beam: g.options.face_beam,
            })
            .collect();
        choose_faces(model, hidden, &mut searches)?
    };
    for (choice, &i) in choices.into_iter().zip(&active) {
        let g = &mut *gens[i];
        match choice {
            Choice::Face(face) => {
                g.state.push_face(face)?;
                events[i].face = Some(face);
                if g.state.faces().len() >= g.options.max_faces {
                    g.finish = Some(FinishReason::MaxFaces);
                }
            }
            Choice::EndOfMesh => g.finish = Some(FinishReason::EndOfMesh),
            Choice::DeadEnd => g.finish = Some(FinishReason::DeadEnd),
        }
        events[i].finished = g.finish;
    }
    Ok(events)
}

/// Yields the faces of one generation as soon as each is decoded.
pub struct FaceStream<'m> {
    model: &'m FaceModel,
    generation: Generation,
}

impl<'m> FaceStream<'m> {
    pub fn new(model: &'m FaceModel, generation: Generation) -> Self {
        Self { model, generation }
    }

    pub fn generation(&self) -> &Generation {
        &self.generation
    }
}

impl Iterator for FaceStream<'_> {
    type Item = Result<FaceToken>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.generation.is_finished() {
            return None;
        }
        match step_generations(self.model, &mut [&mut self.generation]) {
            Ok(events) => events.first().and_then(|e| e.face).map(Ok),
            Err(e) => {
                self.generation.cancel();
                Some(Err(e))
            }
        }
    }
}

/// Generates one mesh, calling `on_face` with each face as it is decoded; `on_face` may stop
/// the generation with `ControlFlow::Break`.
pub fn generate(
    model: &FaceModel,
    latents: &Tensor,
    options: GenerateOptions,
    mut on_face: impl FnMut(&FaceToken) -> ControlFlow<()>,
) -> Result<(Vec<FaceToken>, FinishReason)> {
    let mut stream = FaceStream::new(model, Generation::new(model, latents, options)?);
    while let Some(face) = stream.next() {
        if on_face(&face?).is_break() {
            stream.generation.cancel();
        }
    }
    let g = stream.generation;
    Ok((g.faces().to_vec(), g.finish.unwrap_or(FinishReason::Cancelled)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::FaceConfig;
    use crate::model::constraints::is_valid_next;
    use crate::model::testing::{random_latents, random_model};
    use crate::tokenize::is_canonical_sequence;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(12))]

        /// Random weights, random sampling: every face canonical, strictly increasing, so no
        /// duplicates and no degenerate faces.
        #[test]
        fn constrained_decoding_only_emits_canonical_increasing_faces(
            seed in any::<u64>(),
            temperature in prop_oneof![Just(0.0f32), 0.5f32..3.0],
            q in prop_oneof![Just(3usize), Just(4), Just(16)],
            face_beam in prop_oneof![Just(1usize), Just(4)],
        ) {
            let mut cfg = FaceConfig::micro();
            cfg.quant_levels = q;
            let (_, model) = random_model(&cfg);
            let latents = random_latents(&cfg, 1, seed);
            let options = GenerateOptions {
                sampling: SamplingParams { temperature, top_k: None, top_p: None, seed },
                max_faces: 30,
                min_faces: 30, // no early EOS: push the sequences to their limits
                constrained: true,
                face_beam,
            };
            let (faces, reason) = generate(&model, &latents, options, |_| ControlFlow::Continue(())).unwrap();
            for (i, f) in faces.iter().enumerate() {
                prop_assert!(is_valid_next(f, &faces[..i], q), "face {i} {f:?}");
            }
            prop_assert!(is_canonical_sequence(&faces));
            prop_assert!(faces.len() == 30 || reason == FinishReason::DeadEnd);
        }
    }

    #[test]
    fn batched_generations_match_single_ones_and_respect_budgets() {
        let cfg = FaceConfig::micro();
        let (_, model) = random_model(&cfg);
        let latents = random_latents(&cfg, 3, 11);
        // Row 1 decodes greedily with a face beam, next to two sampled rows.
        let options = |max_faces, seed| GenerateOptions {
            sampling: if seed == 1 {
                SamplingParams::greedy()
            } else {
                SamplingParams { temperature: 1.0, top_k: Some(5), top_p: Some(0.9), seed }
            },
            max_faces,
            ..GenerateOptions::default()
        };
        let budgets = [4usize, 9, 6];
        let single: Vec<Vec<FaceToken>> = (0..3)
            .map(|r| {
                let l = latents.get(r).unwrap();
                generate(&model, &l, options(budgets[r], r as u64), |_| ControlFlow::Continue(()))
                    .unwrap()
                    .0
            })
            .collect();
        let mut gens: Vec<Generation> = (0..3)
            .map(|r| {
                Generation::new(&model, &latents.get(r).unwrap(), options(budgets[r], r as u64))
                    .unwrap()
            })
            .collect();
        // Row 2 joins late, as in continuous batching.
        for _ in 0..2 {
            let (a, b) = gens.split_at_mut(1);
            step_generations(&model, &mut [&mut a[0], &mut b[0]]).unwrap();
        }
        while gens.iter().any(|g| !g.is_finished()) {
            let mut refs: Vec<&mut Generation> = gens.iter_mut().collect();
            step_generations(&model, &mut refs).unwrap();
        }
        for r in 0..3 {
            assert_eq!(gens[r].faces(), &single[r][..], "row {r}");
            assert!(gens[r].faces().len() <= budgets[r]);
        }
    }

    #[test]
    fn face_beams_outside_the_limit_are_refused() {
        let cfg = FaceConfig::micro();
        let (_, model) = random_model(&cfg);
        let latents = random_latents(&cfg, 1, 0);
        for (face_beam, ok) in
            [(0, false), (1, true), (MAX_FACE_BEAM, true), (MAX_FACE_BEAM + 1, false)]
        {
            let options = GenerateOptions { face_beam, ..GenerateOptions::default() };
            assert_eq!(Generation::new(&model, &latents, options).is_ok(), ok, "{face_beam}");
        }
    }

    #[test]
    fn the_callback_can_stop_the_stream() {
        let cfg = FaceConfig::micro();
        let (_, model) = random_model(&cfg);
        let latents = random_latents(&cfg, 1, 3);
        let opts = GenerateOptions { min_faces: 10, max_faces: 10, ..GenerateOptions::default() };
        let mut seen = 0;
        let (faces, reason) = generate(&model, &latents, opts, |_| {
            seen += 1;
            if seen == 3 { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
        })
        .unwrap();
        assert!(faces.len() == 3 || reason == FinishReason::DeadEnd);
        if faces.len() == 3 {
            assert_eq!(reason, FinishReason::Cancelled);
        }
    }
}
