//! The FACE model: shape encoder, face embedding, decoder stack and CausalMLP head, with the
//! stateless API the engine drives (encode -> start_sequence -> step / head) and the
//! teacher-forced path training uses.

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{Init, VarBuilder};

use super::attention::Dense;
use super::cache::DecoderCache;
use super::config::{COORDS_PER_FACE, FaceConfig};
use super::decoder::DecoderStack;
use super::embedding::{CoordEmbedding, FacePooling};
use super::encoder::{EncoderOutput, ShapeEncoder};
use super::head::{CausalHead, FoldedHead};
use super::{FaceToken, ModelError, Result};

/// One sequence being decoded: its decoder cache (self-attention keys/values per layer and the
/// latents its cross-attention attends to) and the faces decoded so far. The engine owns
/// it; the model only reads and extends it.
#[derive(Debug, Clone)]
pub struct SequenceState {
    cache: DecoderCache,
    faces: Vec<FaceToken>,
    quant_levels: usize,
}

impl SequenceState {
    pub fn faces(&self) -> &[FaceToken] {
        &self.faces
    }

    pub fn cache(&self) -> &DecoderCache {
        &self.cache
    }

    /// True when the last step's hidden state has not been turned into a face yet.
    pub fn awaits_face(&self) -> bool {
        self.cache.len() == self.faces.len() + 1
    }

    /// Records the face decoded from the last step's hidden state.
    pub fn push_face(&mut self, face: FaceToken) -> Result<()> {
        if !self.awaits_face() {
            return Err(ModelError::bad_input(format!(
                "push_face after {} steps and {} faces: step first",
                self.cache.len(),
                self.faces.len()
            )));
        }
        if let Some(c) = face.iter().find(|&&c| usize::from(c) >= self.quant_levels) {
            return Err(ModelError::bad_input(format!(
                "coordinate {c} out of 0..{}",
                self.quant_levels
            )));
        }
        self.faces.push(face);
        Ok(())
    }
}

/// The scope of the shape encoder's weights: their names start with it and a dot.
pub const ENCODER_SCOPE: &str = "encoder";

/// Whether a training pass updates the encoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum EncoderTraining {
    /// Gradients flow through the latents into the encoder.
    #[default]
    Trained,
    /// The latents are constants: only the decoder and head learn, so the latent space (and an
    /// image model trained to produce it) stays valid, and the encoder's backward pass is saved.
    Frozen,
}

/// What one teacher-forced training pass produced.
#[derive(Debug, Clone)]
pub struct TrainLoss {
    /// The objective: `coords + kl_weight * kl`.
    pub total: Tensor,
    /// Summed cross-entropy over the 9 coordinates, averaged over face positions (EOS included).
    pub coords: Tensor,
    /// KL term of the bottleneck (zero without one).
    pub kl: Tensor,
}

#[derive(Debug, Clone)]
pub struct FaceModel {
    cfg: FaceConfig,
    encoder: ShapeEncoder,
    coords: CoordEmbedding,
    pooling: FacePooling,
    start: Tensor,
    stack: DecoderStack,
    head: CausalHead,
}

impl FaceModel {
    /// Builds the model with weights from `vb`: a `VarMap`-backed builder for training, a
    /// checkpoint for inference (see `checkpoint::load`).
    pub fn new(cfg: &FaceConfig, vb: VarBuilder) -> Result<Self> {
        cfg.validate()?;
        let dec = vb.pp("decoder");
        Ok(Self {
            cfg: cfg.clone(),
            encoder: ShapeEncoder::new(cfg, vb.pp(ENCODER_SCOPE))?,
            coords: CoordEmbedding::new(cfg, dec.pp("coord_embed"))?,
            pooling: FacePooling::new(cfg, dec.pp("face_pooling"))?,
            start: dec.get_with_hints(
                cfg.decoder.width,
                "start",
                Init::Randn { mean: 0.0, stdev: 0.02 },
            )?,
            stack: DecoderStack::new(cfg, cfg.max_faces + 1, dec.clone())?,
            head: CausalHead::new(cfg, vb.pp("head"))?,
        })
    }

    pub fn config(&self) -> &FaceConfig {
        &self.cfg
    }

    /// Every linear layer: the encoder's, the face pooling's, the decoder's and the head's.
    pub(crate) fn dense_mut(&mut self) -> Vec<&mut Dense> {
        let (mut layers, decoding) = self.dense_mut_by_stage();
        layers.extend(decoding);
        layers
    }

    /// The linear layers that run once per decoded face: face pooling, decoder, head.
    pub(crate) fn decoding_dense_mut(&mut self) -> Vec<&mut Dense> {
        self.dense_mut_by_stage().1
    }

    /// The encoder's linear layers, which run once per request on every point.
    pub(crate) fn encoder_dense_mut(&mut self) -> Vec<&mut Dense> {
        self.encoder.dense_mut()
    }

    /// The linear layers of the encoder, and those of the decoding.
    fn dense_mut_by_stage(&mut self) -> (Vec<&mut Dense>, Vec<&mut Dense>) {
        let mut decoding = self.pooling.dense_mut();
        decoding.extend(self.stack.dense_mut());
        decoding.extend(self.head.dense_mut());
        (self.encoder.dense_mut(), decoding)
    }

    pub fn device(&self) -> &Device {
        self.start.device()
    }

    /// Latent sets C (B, K, latent_dim) of point clouds: points, normals (B, M, 3) f32 and the
    /// FPS query indices (B, K) u32. A KL bottleneck yields its mean.
    pub fn encode(
        &self,
        points: &Tensor,
        normals: &Tensor,
        query_indices: &Tensor,
    ) -> Result<Tensor> {
        Ok(self.encoder.forward(points, normals, query_indices)?.mean)
    }

    /// The latent set (1, K, latent_dim) of one point cloud with normals, in the normalized
    /// frame.
    pub fn encode_point_cloud(&self, cloud: &crate::mesh::Mesh) -> Result<Tensor> {
        let input = super::PointCloudInput::new(cloud, self.cfg.num_latents, self.device())?;
        self.encode(&input.points, &input.normals, &input.query_indices)
    }

    /// The encoder's full output (mean and log-variance), for training.
    pub fn encode_train(
        &self,
        points: &Tensor,
        normals: &Tensor,
        query_indices: &Tensor,
    ) -> Result<EncoderOutput> {
        self.encoder.forward(points, normals, query_indices)
    }

    /// A new sequence conditioned on one latent set, (K, latent_dim) or (1, K, latent_dim).
    pub fn start_sequence(&self, latents: &Tensor) -> Result<SequenceState> {
        let latents = if latents.rank() == 2 { latents.unsqueeze(0)? } else { latents.clone() };
        Ok(SequenceState {
            cache: self.stack.start(&latents)?,
            faces: Vec::new(),
            quant_levels: self.cfg.quant_levels,
        })
    }

    /// Face tokens (..., 9) u32 -> decoder inputs (..., d_model).
    fn embed_faces(&self, faces: &Tensor) -> Result<Tensor> {
        self.pooling.forward(&self.coords.embed(faces, 0)?)
    }

    /// One decoder step for every sequence in `states`, whatever their lengths: each feeds its
    /// last face (or the start token) and gets the hidden state (B, d_model) from which the
    /// head decodes its next face. Every state must have received the face of its previous step.
    /// After an error the states may be partly advanced: drop them.
    pub fn step(&self, states: &mut [&mut SequenceState]) -> Result<Tensor> {
        if states.is_empty() {
            return Err(ModelError::bad_input("step needs at least one sequence"));
        }
        if let Some(s) = states.iter().find(|s| s.cache.len() != s.faces.len()) {
            return Err(ModelError::bad_input(format!(
                "a sequence has {} steps but {} faces: push the face of its last step first",
                s.cache.len(),
                s.faces.len()
            )));
        }
        let dev = self.device();
        let last: Vec<u32> = states
            .iter()
            .flat_map(|s| s.faces.last().copied().unwrap_or_default().map(u32::from))
            .collect();
        let last = Tensor::from_vec(last, (states.len(), COORDS_PER_FACE), dev)?;
        let mut x = self.embed_faces(&last)?;
        if states.iter().any(|s| s.faces.is_empty()) {
            let fresh: Vec<u8> = states.iter().map(|s| u8::from(s.faces.is_empty())).collect();
            let fresh = Tensor::from_vec(fresh, (states.len(), 1), dev)?;
            let start = self.start.unsqueeze(0)?.broadcast_as(x.shape())?;
            x = fresh.broadcast_as(x.shape())?.where_cond(&start, &x)?;
        }
        let mut caches: Vec<&mut DecoderCache> = states.iter_mut().map(|s| &mut s.cache).collect();
        self.stack.step(&x.unsqueeze(1)?, &mut caches)
    }

    /// Logits of coordinate `j` from its context (B, d_model + j * coord_embed_dim): Q classes,
    /// plus end of mesh (the last class) for j = 0.
    pub fn head_logits(&self, j: usize, context: &Tensor) -> Result<Tensor> {
        self.head.logits(j, context)
    }

    /// The head folded with the coordinate embeddings, for decoding (see [`FoldedHead`]);
    /// `None` for a model in training.
    pub(crate) fn folded_head(&self) -> Result<Option<&FoldedHead>> {
        self.head.folded(&self.coords)
    }

    /// Appends the chosen values of coordinate `j` (one per row) to a head context.
    pub fn extend_context(&self, context: &Tensor, j: usize, values: &[u16]) -> Result<Tensor> {
        if j >= COORDS_PER_FACE || values.len() != context.dim(0)? {
            return Err(ModelError::bad_input(format!(
                "{} values for coordinate {j} of {} rows",
                values.len(),
                context.dim(0)?
            )));
        }
        let ids: Vec<u32> = values.iter().map(|&v| u32::from(v)).collect();
        let ids = Tensor::from_vec(ids, (values.len(), 1), context.device())?;
        Ok(Tensor::cat(&[context, &self.coords.embed(&ids, j)?], 1)?)
    }

    /// Teacher forcing: hidden states (B, N + 1, d_model) for latents (B, K, latent_dim) and
    /// faces (B, N, 9) u32. Position i holds the state from which face i is decoded; position N
    /// the one that should say end of mesh.
    pub fn hidden_states(&self, latents: &Tensor, faces: &Tensor) -> Result<Tensor> {
        let max = if faces.elem_count() > 0 {
            faces.max_all()?.to_dtype(DType::U32)?.to_scalar::<u32>()?
        } else {
            0
        };
        self.check_coordinates(max as usize)?;
        self.hidden_states_of_checked(latents, faces)
    }

    fn check_coordinates(&self, max: usize) -> Result<()> {
        if max >= self.cfg.quant_levels {
            return Err(ModelError::bad_input(format!(
                "face coordinates must be below Q = {}",
                self.cfg.quant_levels
            )));
        }
        Ok(())
    }

    /// [`Self::hidden_states`] for faces whose coordinates are known to be below Q.
    fn hidden_states_of_checked(&self, latents: &Tensor, faces: &Tensor) -> Result<Tensor> {
        let (b, _n, c) = faces.dims3()?;
        if c != COORDS_PER_FACE {
            return Err(ModelError::bad_input(format!(
                "faces {:?} must be (B, N, 9)",
                faces.dims()
            )));
        }
        let start = self.start.reshape((1, 1, ()))?.broadcast_as((b, 1, self.cfg.decoder.width))?;
        let x = Tensor::cat(&[&start, &self.embed_faces(faces)?], 1)?;
        self.stack.forward(&x, latents)
    }

    /// The 9 sub-heads' logits with the ground-truth coordinates as the already-chosen prefix:
    /// entry 0 is (B, N + 1, Q + 1) over all positions, entry j >= 1 is (B, N, Q).
    pub fn teacher_forced_logits(&self, hidden: &Tensor, faces: &Tensor) -> Result<Vec<Tensor>> {
        let n = faces.dim(1)?;
        let embedded = self.coords.embed(faces, 0)?;
        let h = hidden.narrow(1, 0, n)?;
        let dc = self.coords.dim();
        let mut out = vec![self.head.logits(0, hidden)?];
        for j in 1..COORDS_PER_FACE {
            let context = Tensor::cat(&[&h, &embedded.narrow(D::Minus1, 0, j * dc)?], D::Minus1)?;
            out.push(self.head.logits(j, &context)?);
        }
        Ok(out)
    }

    /// The training objective on a padded batch (see [`super::TrainBatch`]).
    pub fn loss(&self, batch: &super::TrainBatch, encoder: EncoderTraining) -> Result<TrainLoss> {
        let (logits, enc) = self.batch_logits(batch, encoder)?;
        let coords = batch.cross_entropy(&logits, self.cfg.quant_levels)?;
        let kl = enc.kl()?;
        let total = match self.cfg.bottleneck {
            super::Bottleneck::Kl { weight } => (&coords + (&kl * weight)?)?,
            super::Bottleneck::Linear => coords.clone(),
        };
        Ok(TrainLoss { total, coords, kl })
    }

    /// Each row's teacher-forced loss by coordinate (see [`super::TrainBatch::coordinate_nll`]).
    pub fn coordinate_nll(&self, batch: &super::TrainBatch) -> Result<Vec<super::CoordinateNll>> {
        let (logits, _) = self.batch_logits(batch, EncoderTraining::Frozen)?;
        batch.coordinate_nll(&logits, self.cfg.quant_levels)
    }

    /// The 9 sub-heads' teacher-forced logits for a batch, and the encoder's output they came
    /// from (for its KL term).
    fn batch_logits(
        &self,
        batch: &super::TrainBatch,
        encoder: EncoderTraining,
    ) -> Result<(Vec<Tensor>, EncoderOutput)> {
        let enc = self.encoder.forward_with_max_index(
            &batch.points,
            &batch.normals,
            &batch.query_indices,
            Some(batch.max_query_index),
        )?;
        let latents = match encoder {
            EncoderTraining::Trained => enc.sample()?,
            EncoderTraining::Frozen => enc.sample()?.detach(),
        };
        self.check_coordinates(batch.max_coordinate as usize)?;
        let hidden = self.hidden_states_of_checked(&latents, &batch.faces)?;
        Ok((self.teacher_forced_logits(&hidden, &batch.faces)?, enc))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::testing::{
        faces_tensor, max_abs_diff, random_faces, random_latents, random_model,
    };
    use candle_core::DType;

    /// Hidden state and all 9 teacher-forced logits at `pos` of one row, from the cached path.
    fn cached_outputs(
        model: &FaceModel,
        hidden_row: &Tensor,
        face: Option<&FaceToken>,
    ) -> Vec<Tensor> {
        let mut out = vec![model.head_logits(0, hidden_row).unwrap()];
        if let Some(face) = face {
            let mut ctx = hidden_row.clone();
            for j in 1..COORDS_PER_FACE {
                ctx = model.extend_context(&ctx, j - 1, &[face[j - 1]]).unwrap();
                out.push(model.head_logits(j, &ctx).unwrap());
            }
        }
        out
    }

    #[test]
    fn cached_batched_steps_match_full_forward_for_rows_of_different_lengths() {
        let cfg = FaceConfig::micro();
        let (_, model) = random_model(&cfg);
        let latents = random_latents(&cfg, 2, 1);
        let faces = [random_faces(&cfg, 6, 2), random_faces(&cfg, 3, 3)];
        // Reference: each row's full forward pass.
        let reference: Vec<(Tensor, Vec<Tensor>)> = (0..2)
            .map(|r| {
                let f = faces_tensor(&faces[r]);
                let h = model.hidden_states(&latents.narrow(0, r, 1).unwrap(), &f).unwrap();
                let l = model.teacher_forced_logits(&h, &f).unwrap();
                (h, l)
            })
            .collect();
        let mut a = model.start_sequence(&latents.get(0).unwrap()).unwrap();
        let mut b = model.start_sequence(&latents.narrow(0, 1, 1).unwrap()).unwrap();
        let mut worst = 0f32;
        let mut check = |r: usize, state: &mut SequenceState, hidden: &Tensor| {
            let pos = state.faces().len();
            let face = faces[r].get(pos);
            let (ref_h, ref_l) = &reference[r];
            worst =
                worst.max(max_abs_diff(hidden, &ref_h.get(0).unwrap().narrow(0, pos, 1).unwrap()));
            for (j, got) in cached_outputs(&model, hidden, face).iter().enumerate() {
                let want = ref_l[j].get(0).unwrap().narrow(0, pos, 1).unwrap();
                worst = worst.max(max_abs_diff(got, &want));
            }
            if let Some(f) = face {
                state.push_face(*f).unwrap();
            }
        };
        // Row a runs alone for 3 steps, then b joins and both step together: different lengths
        // in one batch.
        for _ in 0..3 {
            let h = model.step(&mut [&mut a]).unwrap();
            check(0, &mut a, &h);
        }
        for _ in 0..4 {
            let h = model.step(&mut [&mut a, &mut b]).unwrap();
            check(0, &mut a, &h.narrow(0, 0, 1).unwrap());
            check(1, &mut b, &h.narrow(0, 1, 1).unwrap());
        }
        assert_eq!(a.cache().len(), 7);
        assert_eq!(b.cache().len(), 4);
        assert!(worst < 1e-4, "max abs diff {worst}");
    }

    #[test]
    fn padded_batch_matches_single_rows() {
        let cfg = FaceConfig::micro();
        let (_, model) = random_model(&cfg);
        let latents = random_latents(&cfg, 2, 4);
        let long = random_faces(&cfg, 5, 5);
        let mut short = random_faces(&cfg, 2, 6);
        let single =
            model.hidden_states(&latents.narrow(0, 1, 1).unwrap(), &faces_tensor(&short)).unwrap();
        short.extend(random_faces(&cfg, 3, 7)); // padding content must not matter
        let batch = Tensor::cat(&[faces_tensor(&long), faces_tensor(&short)], 0).unwrap();
        let h = model.hidden_states(&latents, &batch).unwrap();
        let diff = max_abs_diff(&h.narrow(0, 1, 1).unwrap().narrow(1, 0, 3).unwrap(), &single);
        assert!(diff < 1e-5, "{diff}");
    }

    #[test]
    fn changing_face_k_changes_nothing_at_or_before_k() {
        let cfg = FaceConfig::micro();
        let (_, model) = random_model(&cfg);
        let latents = random_latents(&cfg, 1, 8);
        let faces = random_faces(&cfg, 8, 9);
        let k = 4;
        let first_changed = 3;
        let mut changed = faces.clone();
        for c in &mut changed[k][first_changed..] {
            *c = (*c + 1) % cfg.quant_levels as u16;
        }
        let run = |f: &[FaceToken]| {
            let f = faces_tensor(f);
            let h = model.hidden_states(&latents, &f).unwrap();
            let l = model.teacher_forced_logits(&h, &f).unwrap();
            (h, l)
        };
        let (h1, l1) = run(&faces);
        let (h2, l2) = run(&changed);
        // Hidden states at positions <= k see only faces < k.
        assert_eq!(
            max_abs_diff(&h1.narrow(1, 0, k + 1).unwrap(), &h2.narrow(1, 0, k + 1).unwrap()),
            0.0
        );
        for j in 0..COORDS_PER_FACE {
            // Positions < k: every sub-head unchanged. Position k: the sub-heads that have not
            // yet seen a changed coordinate (j <= first_changed) unchanged.
            let upto = if j <= first_changed { k + 1 } else { k };
            let same = max_abs_diff(
                &l1[j].narrow(1, 0, upto).unwrap(),
                &l2[j].narrow(1, 0, upto).unwrap(),
            );
            assert_eq!(same, 0.0, "sub-head {j}");
        }
        // And the change does reach later positions.
        assert!(
            max_abs_diff(&h1.narrow(1, k + 1, 1).unwrap(), &h2.narrow(1, k + 1, 1).unwrap()) > 0.0
        );
    }

    #[test]
    fn parameter_count_matches_an_instantiated_model() {
        for cfg in [FaceConfig::micro(), FaceConfig::tiny(), {
            let mut c = FaceConfig::micro();
            c.bottleneck = crate::model::Bottleneck::Kl { weight: 1e-3 };
            c
        }] {
            let (varmap, _) = random_model(&cfg);
            let n: usize = varmap.all_vars().iter().map(|v| v.elem_count()).sum();
            assert_eq!(n, cfg.parameter_count());
        }
    }

    #[test]
    fn api_misuse_is_an_error_not_a_panic() {
        let cfg = FaceConfig::micro();
        let (_, model) = random_model(&cfg);
        let mut s = model.start_sequence(&random_latents(&cfg, 1, 1)).unwrap();
        assert!(s.push_face([0; 9]).is_err()); // no step yet
        model.step(&mut [&mut s]).unwrap();
        assert!(model.step(&mut [&mut s]).is_err()); // face of the last step missing
        assert!(s.push_face([99; 9]).is_err()); // out of range
        assert!(
            model
                .start_sequence(&Tensor::zeros((1, 3, 5), DType::F32, &Device::Cpu).unwrap())
                .is_err()
        );
        let bad_idx =
            Tensor::from_vec(vec![999u32; cfg.num_latents], (1, cfg.num_latents), &Device::Cpu)
                .unwrap();
        let pts = Tensor::zeros((1, cfg.num_points, 3), DType::F32, &Device::Cpu).unwrap();
        assert!(model.encode(&pts, &pts, &bad_idx).is_err());
        let bad_faces = faces_tensor(&[[cfg.quant_levels as u16; 9]]);
        assert!(model.hidden_states(&random_latents(&cfg, 1, 1), &bad_faces).is_err());
    }

    #[test]
    fn a_frozen_encoder_gets_no_gradient_and_the_decoder_still_does() {
        let cfg = FaceConfig::micro();
        let dev = Device::Cpu;
        let varmap = candle_nn::VarMap::new();
        let model =
            FaceModel::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &dev)).unwrap();
        let pts: Vec<[f32; 3]> =
            (0..cfg.num_points).map(|i| [(i as f32).sin(), (i as f32).cos(), 0.5]).collect();
        let queries: Vec<u32> = (0..cfg.num_latents as u32).collect();
        let faces = random_faces(&cfg, 4, 1);
        let example = crate::model::TrainExample {
            points: &pts,
            normals: &pts,
            query_indices: &queries,
            faces: &faces,
        };
        let batch = crate::model::TrainBatch::new(&[example], &dev).unwrap();
        for (mode, encoder_learns) in
            [(EncoderTraining::Trained, true), (EncoderTraining::Frozen, false)]
        {
            let grads = model.loss(&batch, mode).unwrap().total.backward().unwrap();
            let vars = varmap.data().lock().unwrap();
            let has_grad = |prefix: &str| {
                vars.iter()
                    .filter(|(name, _)| name.starts_with(prefix))
                    .map(|(_, v)| grads.get(v.as_tensor()).is_some())
                    .collect::<Vec<_>>()
            };
            let encoder = has_grad("encoder.");
            assert!(!encoder.is_empty());
            assert!(encoder.iter().all(|&g| g == encoder_learns), "{mode:?}: {encoder:?}");
            assert!(has_grad("decoder.").into_iter().all(|g| g), "{mode:?}");
            assert!(has_grad("head.").into_iter().all(|g| g), "{mode:?}");
        }
    }

    #[test]
    fn a_training_models_steps_follow_its_weights_as_they_change() {
        let cfg = FaceConfig::micro();
        let dev = Device::Cpu;
        let (varmap, _) = random_model(&cfg);
        let training =
            FaceModel::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &dev)).unwrap();
        let latents = random_latents(&cfg, 1, 7);
        let first_step = |model: &FaceModel| {
            let mut state = model.start_sequence(&latents).unwrap();
            model.step(&mut [&mut state]).unwrap()
        };
        let before = first_step(&training);
        // As an optimizer step does: a cross-attention weight changes in place.
        {
            let vars = varmap.data().lock().unwrap();
            let q = &vars["decoder.layers.0.cross_attn.q.weight"];
            q.set(&(q.as_tensor() * 2.0).unwrap()).unwrap();
        }
        let after = first_step(&training);
        let changed = crate::model::checkpoint::inference_model(&cfg, &varmap, &dev).unwrap();
        assert!(max_abs_diff(&after, &before) > 1e-3, "the step did not see the new weight");
        assert!(max_abs_diff(&after, &first_step(&changed)) < 1e-5);
    }
}
