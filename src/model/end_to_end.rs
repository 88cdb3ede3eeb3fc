//! The whole path, trained in a test: points -> latents -> faces -> mesh. A tiny model learns a
//! handful of fixed meshes and must then reproduce each exactly, by greedy constrained
//! decoding from its point cloud alone.

use std::ops::ControlFlow;
use std::time::Instant;

use candle_core::{DType, Device};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarBuilder, VarMap};

use super::*;
use crate::mesh::{Mesh, sample_surface};
use crate::tokenize::{Quantizer, detokenize, tokenize_mesh};

fn shapes() -> Vec<Mesh> {
    let tetra = Mesh::new(
        vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
    );
    let c = |x: f32, y: f32, z: f32| [x, y, z];
    let cube = Mesh::new(
        vec![
            c(0., 0., 0.),
            c(1., 0., 0.),
            c(1., 1., 0.),
            c(0., 1., 0.),
            c(0., 0., 1.),
            c(1., 0., 1.),
            c(1., 1., 1.),
            c(0., 1., 1.),
        ],
        vec![
            [0, 2, 1],
            [0, 3, 2],
            [4, 5, 6],
            [4, 6, 7],
            [0, 1, 5],
            [0, 5, 4],
            [2, 3, 7],
            [2, 7, 6],
            [1, 2, 6],
            [1, 6, 5],
            [0, 4, 7],
            [0, 7, 3],
        ],
    );
    let pyramid = Mesh::new(
        vec![c(0., 0., 0.), c(2., 0., 0.), c(2., 2., 0.), c(0., 2., 0.), c(1., 1., 0.7)],
        vec![[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]],
    );
    let octa = Mesh::new(
        vec![
            c(1., 0., 0.),
            c(-1., 0., 0.),
            c(0., 1., 0.),
            c(0., -1., 0.),
            c(0., 0., 1.),
            c(0., 0., -1.),
        ],
        vec![
            [0, 2, 4],
            [2, 1, 4],
            [1, 3, 4],
            [3, 0, 4],
            [2, 0, 5],
            [1, 2, 5],
            [3, 1, 5],
            [0, 3, 5],
        ],
    );
    let prism = Mesh::new(
        vec![
            c(0., 0., 0.),
            c(3., 0., 0.),
            c(0., 1., 0.),
            c(0., 0., 0.5),
            c(3., 0., 0.5),
            c(0., 1., 0.5),
        ],
        vec![
            [0, 2, 1],
            [3, 4, 5],
            [0, 1, 4],
            [0, 4, 3],
            [1, 2, 5],
            [1, 5, 4],
            [2, 0, 3],
            [2, 3, 5],
        ],
    );
    vec![tetra, cube, pyramid, octa, prism]
}

fn test_config() -> FaceConfig {
    FaceConfig {
        quant_levels: 128,
        max_faces: 16,
        num_points: 256,
        point_oversampling: 1,
        num_latents: 32,
        latent_dim: 16,
        bottleneck: Bottleneck::Linear,
        fourier_frequencies: 6,
        encoder: StackConfig { width: 64, layers: 1, heads: 2, mlp_hidden: 128 },
        decoder: StackConfig { width: 128, layers: 2, heads: 4, mlp_hidden: 256 },
        coord_embed_dim: 16,
        head_hidden: 128,
        rope_theta: 10_000.0,
        norm_eps: 1e-5,
    }
}

#[test]
fn a_tiny_model_learns_fixed_meshes_and_reproduces_them_from_points() {
    let cfg = test_config();
    let dev = Device::Cpu;
    let q = Quantizer::new(cfg.quant_levels as u16).unwrap();
    struct Sample {
        cloud: Mesh,
        queries: Vec<u32>,
        faces: Vec<FaceToken>,
    }
    let samples: Vec<Sample> = shapes()
        .iter()
        .enumerate()
        .map(|(i, mesh)| {
            let (tokens, _) = tokenize_mesh(mesh, q).unwrap();
            let (normalized, _) = mesh.normalized().unwrap();
            let cloud = sample_surface(&normalized, cfg.num_points, i as u64).unwrap();
            let queries = crate::mesh::farthest_point_sampling(&cloud.vertices, cfg.num_latents, 0)
                .into_iter()
                .map(|i| i as u32)
                .collect();
            Sample { cloud, queries, faces: tokens.faces }
        })
        .collect();
    let examples: Vec<TrainExample> = samples
        .iter()
        .map(|s| TrainExample {
            points: &s.cloud.vertices,
            normals: s.cloud.normals.as_deref().unwrap(),
            query_indices: &s.queries,
            faces: &s.faces,
        })
        .collect();
    let batch = TrainBatch::new(&examples, &dev).unwrap();

    let varmap = VarMap::new();
    let model = FaceModel::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &dev)).unwrap();
    let params = ParamsAdamW { lr: 3e-3, weight_decay: 0.0, ..Default::default() };
    let mut opt = AdamW::new(varmap.all_vars(), params).unwrap();
    let started = Instant::now();
    let mut last = f32::MAX;
    for step in 0..300 {
        let loss = model.loss(&batch, EncoderTraining::Trained).unwrap();
        opt.backward_step(&loss.total).unwrap();
        last = loss.coords.to_scalar::<f32>().unwrap();
        if step % 50 == 0 {
            eprintln!("step {step}: loss {last:.4}");
        }
        // Well below the loss at which greedy decoding of every coordinate is right.
        if last < 5e-3 {
            break;
        }
    }
    eprintln!("trained to loss {last:.5} in {:.1} s", started.elapsed().as_secs_f64());

    let model = checkpoint::inference_model(&cfg, &varmap, &dev).unwrap();
    for (i, s) in samples.iter().enumerate() {
        let latents = model.encode_point_cloud(&s.cloud).unwrap();
        let (faces, reason) =
            generate(&model, &latents, GenerateOptions::default(), |_| ControlFlow::Continue(()))
                .unwrap();
        assert_eq!(faces, s.faces, "mesh {i}");
        assert_eq!(reason, FinishReason::EndOfMesh, "mesh {i}");
        let mesh = detokenize(&faces, q);
        assert_eq!(mesh.faces.len(), s.faces.len());
    }
}
