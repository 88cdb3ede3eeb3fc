use std::time::{Duration, Instant};

use super::*;
use crate::mesh::primitives::uv_sphere;
use crate::model::testing::random_model;
use crate::model::{GenerateOptions, Generation, SamplingParams, step_generations};
use crate::tokenize::FaceToken;

fn engine(config: EngineConfig) -> (Engine, FaceModel) {
    // The engine's quantizer needs a real level count; the network stays tiny.
    let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
    let (_, model) = random_model(&cfg);
    let engine = Engine::start(model.clone(), None, config, Arc::new(Metrics::default())).unwrap();
    (engine, model)
}

fn request(model: &FaceModel, id: usize, max_faces: usize) -> Request {
    // Spheres of different sizes and places: different latents, so different sequences.
    let r = 0.5 + id as f32 * 0.3;
    let shape = uv_sphere(r, 6 + id as u32 % 3, 4).translated([id as f32, -2.0, 0.5]);
    Request {
        id: format!("r{id}"),
        conditioning: Conditioning::Points(
            PreparedPoints::from_mesh(&shape, model.config(), id as u64).unwrap(),
        ),
        options: DecodeOptions { max_faces: Some(max_faces), sampling: SamplingParams::greedy() },
        deadline: None,
    }
}

/// What one request decodes alone, without the engine.
fn reference_faces(model: &FaceModel, request: &Request, max_faces: usize) -> Vec<FaceToken> {
    let Conditioning::Points(p) = &request.conditioning;
    let latents = scheduler_encode(model, p);
    let opts = GenerateOptions { max_faces, ..GenerateOptions::default() };
    let mut g = Generation::new(model, &latents, opts).unwrap();
    while !g.is_finished() {
        step_generations(model, &mut [&mut g]).unwrap();
    }
    g.faces().to_vec()
}

fn scheduler_encode(model: &FaceModel, p: &PreparedPoints) -> candle_core::Tensor {
    scheduler::encode_batch(model, &[p]).unwrap()
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap()
}

#[test]
fn concurrent_requests_decode_in_batches_exactly_as_alone() {
    let (engine, model) = engine(EngineConfig { decode_threads: 2, ..EngineConfig::default() });
    let requests: Vec<Request> = (0..9).map(|i| request(&model, i, 12 + i)).collect();
    let expected: Vec<_> =
        requests.iter().enumerate().map(|(i, r)| reference_faces(&model, r, 12 + i)).collect();
    let streams: Vec<_> = requests.into_iter().map(|r| engine.submit(r).unwrap()).collect();
    let done = runtime().block_on(async {
        let mut out = Vec::new();
        for s in streams {
            out.push(s.collect().await.unwrap());
        }
        out
    });
    for (i, (d, want)) in done.iter().zip(&expected).enumerate() {
        assert_eq!(&d.tokens, want, "request {i}");
        assert_eq!(d.summary.faces, want.len());
        assert!(d.tokens.len() <= 12 + i);
    }
    // Nine requests admitted at once were decoded together: some batches held more than one.
    let text = engine.metrics().render();
    let value = |prefix: &str| -> f64 {
        let line = text.lines().find(|l| l.starts_with(prefix)).unwrap();
        line.rsplit(' ').next().unwrap().parse().unwrap()
    };
    let singles = value("meshstream_batch_size_bucket{le=\"1.0\"}");
    assert!(value("meshstream_batch_size_count") > singles, "{text}");
    engine.shutdown(Duration::ZERO);
    engine.join();
    assert!(!engine.status().alive);
}

#[test]
fn faces_arrive_in_the_callers_coordinates() {
    let (engine, model) = engine(EngineConfig::default());
    let r = request(&model, 4, 20);
    let Conditioning::Points(p) = &r.conditioning;
    let normalization = p.normalization;
    let mut stream = engine.submit(r).unwrap();
    runtime().block_on(async {
        let q = engine.quantizer;
        let mut tokens = Vec::new();
        while let Some(event) = stream.next().await {
            match event {
                Event::Face(f) => {
                    assert_eq!(f.index, tokens.len());
                    let expected = crate::tokenize::face_positions(&f.token, q)
                        .map(|v| normalization.invert(v));
                    assert_eq!(f.vertices, expected);
                    tokens.push(f.token);
                }
                Event::Finished(s) => {
                    assert_eq!(s.faces, tokens.len());
                    break;
                }
                Event::Failed(e) => panic!("{e}"),
            }
        }
        // The sphere was shifted to x = 4: so are the faces.
        let mesh = stream.assemble(&tokens);
        let mean_x: f32 =
            mesh.vertices.iter().map(|v| v[0]).sum::<f32>() / mesh.vertices.len().max(1) as f32;
        assert!(tokens.is_empty() || (2.0..6.0).contains(&mean_x), "mean x {mean_x}");
    });
}

#[test]
fn a_dropped_stream_frees_its_slot_within_a_step() {
    let (engine, model) = engine(EngineConfig { stream_buffer: 2, ..EngineConfig::default() });
    let mut stream = engine.submit(request(&model, 1, 40)).unwrap();
    runtime().block_on(async {
        // The client reads one face, then stops reading: the buffer fills and the sequence
        // waits; then the client goes away.
        let first = stream.next().await;
        assert!(matches!(first, Some(Event::Face(_))), "{first:?}");
    });
    drop(stream);
    let t0 = Instant::now();
    while engine.status().running > 0 {
        assert!(t0.elapsed() < Duration::from_secs(2), "still running");
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(engine.metrics().render().contains("requests_finished_total{reason=\"cancelled\"} 1"));
}

#[test]
fn a_full_queue_and_a_closing_engine_refuse_requests() {
    let (engine, model) = engine(EngineConfig {
        max_running: 1,
        max_queue: 2,
        stream_buffer: 2,
        ..EngineConfig::default()
    });
    // The first runs and stalls (nobody reads); two wait; the fourth is refused.
    let mut held = vec![engine.submit(request(&model, 0, 40)).unwrap()];
    let t0 = Instant::now();
    while engine.status().running == 0 {
        assert!(t0.elapsed() < Duration::from_secs(2));
        std::thread::sleep(Duration::from_millis(2));
    }
    held.extend((1..3).map(|i| engine.submit(request(&model, i, 40)).unwrap()));
    assert!(matches!(engine.submit(request(&model, 3, 40)), Err(EngineError::QueueFull(2))));
    engine.shutdown(Duration::from_secs(5));
    assert_eq!(engine.submit(request(&model, 4, 4)).unwrap_err(), EngineError::ShuttingDown);
    // Accepted requests still finish after shutdown began.
    let done = runtime().block_on(async {
        let mut out = Vec::new();
        for s in held {
            out.push(s.collect().await);
        }
        out
    });
    assert!(done.iter().all(Result::is_ok), "{done:?}");
    engine.join();
}

#[test]
fn invalid_options_are_refused_before_queueing() {
    let (engine, model) = engine(EngineConfig::default());
    let mut r = request(&model, 0, 0);
    assert!(matches!(engine.submit(r.clone()), Err(EngineError::InvalidInput(_))));
    r.options.max_faces = Some(engine.face_limit() + 1);
    assert!(matches!(engine.submit(r.clone()), Err(EngineError::InvalidInput(_))));
    r.options.max_faces = Some(4);
    r.options.sampling.temperature = f32::NAN;
    assert!(matches!(engine.submit(r), Err(EngineError::InvalidInput(_))));
    assert_eq!(engine.status().waiting, 0);
}

#[test]
fn the_deadline_ends_a_request_with_an_error() {
    let (engine, model) = engine(EngineConfig { stream_buffer: 2, ..EngineConfig::default() });
    let mut r = request(&model, 2, 40);
    r.deadline = Some(Instant::now() + Duration::from_millis(50));
    let mut stream = engine.submit(r).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    let last = runtime().block_on(async {
        let mut last = None;
        while let Some(e) = stream.next().await {
            last = Some(e);
        }
        last
    });
    // Either it finished before the deadline or the deadline ended it; with a stalled reader
    // and a 2-event buffer it cannot have finished 40 faces.
    assert!(
        matches!(
            last,
            Some(Event::Failed(EngineError::DeadlineExceeded(_))) | Some(Event::Finished(_))
        ),
        "{last:?}"
    );
}
