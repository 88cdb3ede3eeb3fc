//! Choosing each row's next face from the CausalMLP head, coordinate by coordinate under the
//! constraint masks.
//!
//! A sampled row draws each coordinate in turn, which is exact ancestral sampling of the face.
//! A greedy row ends the mesh when end of mesh is more likely than any first coordinate (as
//! per-coordinate greedy decides it). Otherwise it wants the most likely face: it keeps the
//! `beam` most likely partial faces at every coordinate and takes the most likely complete
//! one. Per-coordinate greedy (a beam of one) commits to a face's first vertices before it
//! sees its last: when the constraints then forbid the value the model wanted (a repeat of
//! the previous face), it takes the neighbouring grid value instead, and the mesh crawls on
//! in slivers one grid step apart although the whole face was unlikely.
//!
//! End of mesh is not weighed against whole faces: a model unsure of the next face spreads
//! its probability over many faces, so the most likely one can be less likely than ending
//! even when ending is improbable. Tried on the step-1500 model, that rule ended most
//! primitives before their first face.

use candle_core::Tensor;

use super::config::COORDS_PER_FACE;
use super::constraints::{NextValues, allowed_values};
use super::head::FoldedHead;
use super::sampling::Sampler;
use super::{FaceModel, FaceToken, Result};

/// One row's search: what decides its coordinates and what its face must follow.
pub(super) struct RowSearch<'a> {
    pub sampler: &'a mut Sampler,
    /// The row's faces so far (the constraints' context).
    pub earlier: &'a [FaceToken],
    pub constrained: bool,
    /// End of mesh may be chosen.
    pub eos_ok: bool,
    /// Partial faces kept by a greedy row.
    pub beam: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Choice {
    Face(FaceToken),
    EndOfMesh,
    /// No face can follow the row's sequence.
    DeadEnd,
}

/// A face decided up to some coordinate, with its log-probability so far.
#[derive(Debug, Clone, Copy)]
struct Partial {
    row: usize,
    coords: FaceToken,
    log_prob: f32,
}

/// The next face (or end) of every row, from the decoder's hidden states (rows, d).
pub(super) fn choose_faces(
    model: &FaceModel,
    hidden: Tensor,
    rows: &mut [RowSearch],
) -> Result<Vec<Choice>> {
    let q = model.config().quant_levels;
    let mut choices = vec![Choice::DeadEnd; rows.len()];
    let mut partials: Vec<Partial> = (0..rows.len())
        .map(|row| Partial { row, coords: [0; COORDS_PER_FACE], log_prob: 0.0 })
        .collect();
    let mut input = match model.folded_head()? {
        Some(head) => HeadInput::Folded { head, on_states: head.on_states(&hidden)? },
        None => HeadInput::Context(hidden),
    };
    let mut allowed = Vec::with_capacity(q + 1);
    for j in 0..COORDS_PER_FACE {
        let logits = input.logits(model, j, &partials)?;
        // Partials stay grouped by row, in row order.
        let mut next: Vec<(usize, Partial)> = Vec::with_capacity(partials.len());
        let mut start = 0;
        while start < partials.len() {
            let row = partials[start].row;
            let end = start + partials[start..].iter().take_while(|p| p.row == row).count();
            let step = Step { j, q, eos_ok: j == 0 && rows[row].eos_ok, logits: &logits };
            let search = &mut rows[row];
            let extended = if search.sampler.is_greedy() {
                extend_by_beam(search, &partials, start..end, &step)
            } else {
                extend_by_sampling(search, &partials[start], start, &step, &mut allowed)
            };
            match extended {
                Ok(candidates) => next.extend(candidates),
                Err(choice) => choices[row] = choice,
            }
            start = end;
        }
        if next.is_empty() {
            return Ok(choices);
        }
        if let (HeadInput::Context(context), true) = (&mut input, j + 1 < COORDS_PER_FACE) {
            *context = extended_context(model, context, j, partials.len(), &next)?;
        }
        partials = next.into_iter().map(|(_, p)| p).collect();
    }
    // Each row's first partial is its best (sampled rows have just one).
    for p in partials.iter().rev() {
        choices[p.row] = Choice::Face(p.coords);
    }
    Ok(choices)
}

/// What the head reads for the partial faces.
enum HeadInput<'m> {
    /// The head folded (an inference model): every row's part on its decoder state.
    Folded { head: &'m FoldedHead, on_states: Vec<f32> },
    /// Each partial face's context (a model in training): its decoder state and the
    /// embeddings of its coordinates so far.
    Context(Tensor),
}

impl HeadInput<'_> {
    /// One row of sub-head `j`'s logits per partial face.
    fn logits(&self, model: &FaceModel, j: usize, partials: &[Partial]) -> Result<Vec<Vec<f32>>> {
        let logits = match self {
            Self::Folded { head, on_states } => {
                head.logits(j, on_states, partials.iter().map(|p| (p.row, &p.coords[..])))?
            }
            Self::Context(context) => model.head_logits(j, context)?,
        };
        Ok(logits.to_vec2::<f32>()?)
    }
}

/// The contexts of the partial faces `next` (each with its parent among `parents` partial
/// faces, whose contexts are `context`), extended by coordinate `j`.
fn extended_context(
    model: &FaceModel,
    context: &Tensor,
    j: usize,
    parents: usize,
    next: &[(usize, Partial)],
) -> Result<Tensor> {
    let order: Vec<u32> = next.iter().map(|(i, _)| *i as u32).collect();
    let context =
        if order.len() != parents || order.iter().enumerate().any(|(i, &p)| p as usize != i) {
            let n = order.len();
            context.index_select(&Tensor::from_vec(order, n, context.device())?, 0)?
        } else {
            context.clone()
        };
    let column: Vec<u16> = next.iter().map(|(_, p)| p.coords[j]).collect();
    model.extend_context(&context, j, &column)
}

/// What every row's choice at coordinate `j` reads.
struct Step<'a> {
    j: usize,
    q: usize,
    /// End of mesh may be chosen now (first coordinate, and the row allows it).
    eos_ok: bool,
    /// One row of logits per partial face.
    logits: &'a [Vec<f32>],
}

/// A greedy row's `beam` most likely extensions (parent index, partial) of its partial faces
/// `mine` by coordinate `j`; an empty list is a dead end, `Err` is end of mesh.
///
/// The masks are asked only about values that could change the outcome: those that would
/// enter the beam as it stands, and at the first coordinate those at least as likely as end
/// of mesh. Most of the q values of a partial cannot, and asking costs more than scoring.
fn extend_by_beam(
    search: &RowSearch,
    partials: &[Partial],
    mine: std::ops::Range<usize>,
    step: &Step,
) -> std::result::Result<Vec<(usize, Partial)>, Choice> {
    let (j, q) = (step.j, step.q);
    let beam = search.beam.max(1);
    let mut kept: Vec<(usize, Partial)> = Vec::with_capacity(beam + 1);
    for index in mine {
        let p = partials[index];
        let log_probs = log_softmax(&step.logits[index]);
        let mask = search.constrained.then(|| NextValues::new(&p.coords[..j], search.earlier, q));
        let allowed = |c: usize| mask.as_ref().is_none_or(|mask| mask.allows(c));
        // At the first coordinate (one partial) end of mesh competes with each value; ties
        // go to the value, as in per-coordinate greedy.
        if step.eos_ok && !(0..q).any(|c| log_probs[c] >= log_probs[q] && allowed(c)) {
            return Err(Choice::EndOfMesh);
        }
        for (c, value_log_prob) in log_probs.iter().enumerate().take(q) {
            let log_prob = p.log_prob + value_log_prob;
            // What `keep_best` would turn away whether allowed or not.
            let full_and_no_better =
                kept.len() == beam && kept[beam - 1].1.log_prob.total_cmp(&log_prob).is_ge();
            if full_and_no_better || !allowed(c) {
                continue;
            }
            let mut coords = p.coords;
            coords[j] = c as u16;
            keep_best(&mut kept, (index, Partial { coords, log_prob, ..p }), beam);
        }
    }
    Ok(kept)
}

/// Adds `candidate` to `best` (the most likely first, at most `beam` of them) if it is among
/// the `beam` most likely so far. Ties keep the earlier candidate first, as a stable sort of
/// every candidate would: the earlier partial, then the lower value. Why not sort: a beam of
/// 4 over 128 values extends 512 partials per coordinate, of which it keeps 4.
fn keep_best(best: &mut Vec<(usize, Partial)>, candidate: (usize, Partial), beam: usize) {
    let at = best.partition_point(|b| b.1.log_prob.total_cmp(&candidate.1.log_prob).is_ge());
    if at < beam {
        best.insert(at, candidate);
        best.truncate(beam);
    }
}

/// A sampled row's partial face (at `index`) extended by one drawn coordinate (a list of one,
/// as the beam's); `Err` when the row ends (end of mesh, or a dead end).
fn extend_by_sampling(
    search: &mut RowSearch,
    p: &Partial,
    index: usize,
    step: &Step,
    allowed: &mut Vec<bool>,
) -> std::result::Result<Vec<(usize, Partial)>, Choice> {
    let (j, q) = (step.j, step.q);
    allowed_for(search, &p.coords[..j], q, allowed);
    let pick =
        search.sampler.pick(&step.logits[index], |c| if c == q { step.eos_ok } else { allowed[c] });
    match pick {
        Some(c) if c == q => Err(Choice::EndOfMesh),
        Some(c) => {
            let mut coords = p.coords;
            coords[j] = c as u16;
            Ok(vec![(index, Partial { coords, ..*p })])
        }
        None => Err(Choice::DeadEnd),
    }
}

fn allowed_for(search: &RowSearch, prefix: &[u16], q: usize, allowed: &mut Vec<bool>) {
    if search.constrained {
        allowed_values(prefix, search.earlier, q, allowed);
    } else {
        allowed.clear();
        allowed.resize(q, true);
    }
}

/// Log-probabilities of every class; a non-finite logit counts as impossible.
fn log_softmax(logits: &[f32]) -> Vec<f32> {
    let finite = |l: f32| if l.is_finite() { l } else { f32::NEG_INFINITY };
    let max = logits.iter().map(|&l| finite(l)).fold(f32::NEG_INFINITY, f32::max);
    if max == f32::NEG_INFINITY {
        return vec![f32::NEG_INFINITY; logits.len()];
    }
    let sum: f32 = logits.iter().map(|&l| (finite(l) - max).exp()).sum();
    let log_sum = max + sum.ln();
    logits.iter().map(|&l| finite(l) - log_sum).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::constraints::is_valid_next;
    use crate::model::sampling::SamplingParams;
    use crate::model::testing::random_model;
    use crate::model::{FaceConfig, FaceModel};
    use candle_core::Device;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn log_softmax_normalizes_and_ignores_non_finite_logits() {
        let lp = log_softmax(&[1.0, 2.0, f32::NAN, 3.0]);
        let total: f32 = lp.iter().map(|l| l.exp()).sum();
        assert!((total - 1.0).abs() < 1e-6);
        assert_eq!(lp[2], f32::NEG_INFINITY);
        assert!(lp[3] > lp[1] && lp[1] > lp[0]);
        assert!(log_softmax(&[f32::NAN]).iter().all(|l| *l == f32::NEG_INFINITY));
    }

    /// Three levels: 3^9 faces, few enough to score every one.
    fn small_model() -> FaceModel {
        random_model(&FaceConfig { quant_levels: 3, ..FaceConfig::micro() }).1
    }

    /// A random decoder state for the head.
    fn hidden(model: &FaceModel, seed: u64) -> Tensor {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let d = model.config().decoder.width;
        let v: Vec<f32> = (0..d).map(|_| rng.random_range(-3.0..3.0)).collect();
        Tensor::from_vec(v, (1, d), &Device::Cpu).unwrap()
    }

    /// Log-probability of the first coordinate's classes, and of each face in `faces`, by
    /// teacher forcing the head: independent of the search.
    fn score(model: &FaceModel, hidden: &Tensor, faces: &[FaceToken]) -> (Vec<f32>, Vec<f32>) {
        let first =
            log_softmax(&model.head_logits(0, hidden).unwrap().to_vec2::<f32>().unwrap()[0]);
        let mut context = hidden.repeat((faces.len(), 1)).unwrap();
        let mut total = vec![0f32; faces.len()];
        for j in 0..COORDS_PER_FACE {
            let logits = model.head_logits(j, &context).unwrap().to_vec2::<f32>().unwrap();
            for (t, (row, f)) in total.iter_mut().zip(logits.iter().zip(faces)) {
                *t += log_softmax(row)[usize::from(f[j])];
            }
            let column: Vec<u16> = faces.iter().map(|f| f[j]).collect();
            if j + 1 < COORDS_PER_FACE {
                context = model.extend_context(&context, j, &column).unwrap();
            }
        }
        (first, total)
    }

    fn choose(
        model: &FaceModel,
        hidden: &Tensor,
        earlier: &[FaceToken],
        beam: usize,
        eos_ok: bool,
    ) -> Choice {
        let mut sampler = Sampler::new(SamplingParams::greedy());
        let mut rows =
            [RowSearch { sampler: &mut sampler, earlier, constrained: true, eos_ok, beam }];
        choose_faces(model, hidden.clone(), &mut rows).unwrap()[0]
    }

    /// A model in training (its head read through contexts that grow a coordinate at a
    /// time) and the same weights loaded for inference (its head folded) choose the same faces.
    #[test]
    fn a_training_and_an_inference_model_choose_the_same_faces() {
        let cfg = FaceConfig::micro();
        let (varmap, inference) = random_model(&cfg);
        let vb = candle_nn::VarBuilder::from_varmap(&varmap, candle_core::DType::F32, &Device::Cpu);
        let training = FaceModel::new(&cfg, vb).unwrap();
        assert!(training.folded_head().unwrap().is_none());
        let earlier = [[0, 0, 0, 0, 1, 0, 0, 1, 1]];
        for seed in 0..8 {
            let h = hidden(&inference, seed);
            for beam in [1, 4] {
                let (a, b) = (
                    choose(&training, &h, &earlier, beam, false),
                    choose(&inference, &h, &earlier, beam, false),
                );
                assert!(matches!(a, Choice::Face(_)), "seed {seed}, beam {beam}: {a:?}");
                assert_eq!(a, b, "seed {seed}, beam {beam}");
            }
        }
    }

    /// The beam as it was before the masks were asked lazily: every value's mask, then every
    /// allowed value offered to the beam. What [`extend_by_beam`] must keep exactly.
    fn extend_with_full_masks(
        search: &RowSearch,
        partials: &[Partial],
        step: &Step,
    ) -> std::result::Result<Vec<(usize, Partial)>, Choice> {
        let (j, q) = (step.j, step.q);
        let mut kept = Vec::new();
        let mut allowed = Vec::new();
        for (index, p) in partials.iter().enumerate() {
            let log_probs = log_softmax(&step.logits[index]);
            allowed_for(search, &p.coords[..j], q, &mut allowed);
            let best = (0..q).filter(|&c| allowed[c]).map(|c| log_probs[c]).reduce(f32::max);
            if step.eos_ok && best.is_none_or(|best| log_probs[q] > best) {
                return Err(Choice::EndOfMesh);
            }
            for c in (0..q).filter(|&c| allowed[c]) {
                let mut coords = p.coords;
                coords[j] = c as u16;
                let log_prob = p.log_prob + log_probs[c];
                keep_best(&mut kept, (index, Partial { coords, log_prob, ..*p }), search.beam);
            }
        }
        Ok(kept)
    }

    proptest! {
        /// Asking the masks only about values that could enter the beam keeps what asking about
        /// every value keeps, ties included (small grids, so that the masks bite; whole-number
        /// logits, so that values tie; the first coordinate, where end of mesh competes, half
        /// the time).
        #[test]
        fn lazy_masks_keep_what_full_masks_keep(
            q in 2usize..=5,
            j in prop_oneof![Just(0usize), 0usize..9],
            faces in proptest::collection::vec(proptest::array::uniform9(0u16..5), 0..12),
            prefixes in proptest::collection::vec(
                (proptest::array::uniform9(0u16..5), -4i8..=0),
                1..4,
            ),
            logits in proptest::collection::vec(-3i8..=3, 4 * 6),
            beam in 1usize..6,
            eos_ok in any::<bool>(),
        ) {
            let mut faces: Vec<FaceToken> =
                faces.into_iter().map(|f| f.map(|c| c % q as u16)).collect();
            faces.sort_unstable();
            let mut earlier: Vec<FaceToken> = Vec::new();
            for f in faces {
                if is_valid_next(&f, &earlier, q) {
                    earlier.push(f);
                }
            }
            let partials: Vec<Partial> = prefixes
                .iter()
                .map(|(coords, log_prob)| {
                    let mut coords = coords.map(|c| c % q as u16);
                    coords[j..].fill(0);
                    Partial { row: 0, coords, log_prob: f32::from(*log_prob) }
                })
                .collect();
            let width = if j == 0 { q + 1 } else { q };
            let logits: Vec<Vec<f32>> = logits
                .chunks(6)
                .take(partials.len())
                .map(|l| l[..width].iter().map(|&v| f32::from(v)).collect())
                .collect();
            let step = Step { j, q, eos_ok: eos_ok && j == 0, logits: &logits };
            let mut sampler = Sampler::new(SamplingParams::greedy());
            let search = RowSearch {
                sampler: &mut sampler,
                earlier: &earlier,
                constrained: true,
                eos_ok,
                beam,
            };
            let key = |r: std::result::Result<Vec<(usize, Partial)>, Choice>| {
                r.map(|v| v.iter().map(|(i, p)| (*i, p.coords, p.log_prob)).collect::<Vec<_>>())
            };
            prop_assert_eq!(
                key(extend_by_beam(&search, &partials, 0..partials.len(), &step)),
                key(extend_with_full_masks(&search, &partials, &step))
            );
        }
    }

    proptest! {
        /// Keeping the best as they come is the stable sort of all of them, truncated.
        #[test]
        fn keeping_the_best_is_a_stable_sort_truncated(
            log_probs in proptest::collection::vec(-4i8..=0, 0..40),
            beam in 1usize..6,
        ) {
            let all: Vec<(usize, Partial)> = log_probs
                .iter()
                .enumerate()
                .map(|(i, &l)| {
                    (i, Partial { row: 0, coords: [i as u16; 9], log_prob: f32::from(l) })
                })
                .collect();
            let mut best = Vec::new();
            for &candidate in &all {
                keep_best(&mut best, candidate, beam);
            }
            let mut sorted = all.clone();
            sorted.sort_by(|a, b| b.1.log_prob.total_cmp(&a.1.log_prob));
            sorted.truncate(beam);
            let key = |v: &[(usize, Partial)]| {
                v.iter().map(|(i, p)| (*i, p.coords, p.log_prob)).collect::<Vec<_>>()
            };
            prop_assert_eq!(key(&best), key(&sorted));
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(6))]

        /// A beam as wide as the face space finds the most likely valid face; end of mesh wins
        /// exactly when it beats every allowed first coordinate.
        #[test]
        fn a_full_beam_finds_the_most_likely_valid_face(seed in 0u64..1000, after in any::<bool>()) {
            let model = small_model();
            let q = 3usize;
            let h = hidden(&model, seed);
            let earlier: Vec<FaceToken> = if after { vec![[0, 0, 0, 0, 1, 0, 0, 1, 1]] } else { vec![] };
            let all: Vec<FaceToken> = (0..q.pow(9))
                .map(|n| std::array::from_fn(|j| ((n / q.pow(8 - j as u32)) % q) as u16))
                .filter(|f| is_valid_next(f, &earlier, q))
                .collect();
            let (first, scores) = score(&model, &h, &all);
            let best = (0..all.len()).max_by(|&a, &b| scores[a].total_cmp(&scores[b])).unwrap();
            prop_assert_eq!(choose(&model, &h, &earlier, q.pow(8), false), Choice::Face(all[best]));

            let first_allowed = all.iter().map(|f| first[usize::from(f[0])]).fold(f32::MIN, f32::max);
            let expected = if first[q] > first_allowed { Choice::EndOfMesh } else { Choice::Face(all[best]) };
            prop_assert_eq!(choose(&model, &h, &earlier, q.pow(8), true), expected);
        }
    }
}
