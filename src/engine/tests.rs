use std::ops::ControlFlow;
use std::time::{Duration, Instant};

use super::*;
use crate::candidates::{MAX_CANDIDATES, candidate_options, input_distance};
use crate::mesh::primitives::uv_sphere;
use crate::mesh::{Mesh, REFERENCE_POINTS, UpAxis};
use crate::metrics::MeshQuality;
use crate::model::testing::random_model;
use crate::model::{FinishReason, GenerateOptions, Generation, generate, step_generations};
use crate::tokenize::{FaceToken, detokenize};

fn engine(config: EngineConfig) -> (Engine, FaceModel) {
    // The engine's quantizer needs a real level count; the network stays tiny.
    let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
    let (_, model) = random_model(&cfg);
    let engine = Engine::start(model.clone(), None, config, Arc::new(Metrics::default())).unwrap();
    (engine, model)
}

fn request(model: &FaceModel, id: usize, max_faces: usize) -> Request {
    request_with_draws(model, id, max_faces, 1)
}

/// A request whose input points are drawn `draws` times, one draw per candidate.
fn request_with_draws(model: &FaceModel, id: usize, max_faces: usize, draws: usize) -> Request {
    // Spheres of different sizes and places: different latents, so different sequences.
    let r = 0.5 + id as f32 * 0.3;
    let shape = uv_sphere(r, 6 + id as u32 % 3, 4).translated([id as f32, -2.0, 0.5]);
    Request {
        id: format!("r{id}"),
        conditioning: Conditioning::Points(
            PreparedPoints::from_mesh(
                &shape,
                model.config(),
                REFERENCE_POINTS,
                id as u64,
                draws,
                UpAxis::Y,
            )
            .unwrap(),
        ),
        options: DecodeOptions { max_faces: Some(max_faces), ..Default::default() },
        deadline: None,
    }
}

/// What one request decodes alone, without the engine.
fn reference_faces(model: &FaceModel, request: &Request, max_faces: usize) -> Vec<FaceToken> {
    let Conditioning::Points(p) = &request.conditioning else { unreachable!() };
    let latents = engine_encode(model, p);
    let opts = GenerateOptions { max_faces, ..GenerateOptions::default() };
    let mut g = Generation::new(model, &latents, opts).unwrap();
    while !g.is_finished() {
        step_generations(model, &mut [&mut g]).unwrap();
    }
    g.faces().to_vec()
}

fn engine_encode(model: &FaceModel, p: &PreparedPoints) -> candle_core::Tensor {
    encode_stage::encode_batch(model, &[&p.encoder]).unwrap()
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
    let Conditioning::Points(p) = &r.conditioning else { unreachable!() };
    let normalization = p.normalization;
    let mut stream = engine.submit(r).unwrap();
    runtime().block_on(async {
        let q = engine.quantizer;
        let (mut tokens, mut corners) = (Vec::new(), Vec::new());
        while let Some(event) = stream.next().await {
            match event {
                Event::Face(f) => {
                    assert_eq!(f.index, tokens.len());
                    let expected = crate::tokenize::face_positions(&f.token, q)
                        .map(|v| normalization.invert(v));
                    assert_eq!(f.vertices, expected);
                    tokens.push(f.token);
                    corners.push(f.vertices);
                }
                Event::Finished(s) => {
                    assert_eq!(s.faces, tokens.len());
                    break;
                }
                Event::Failed(e) => panic!("{e}"),
                Event::Progress { .. } => panic!("progress events are for image requests"),
                Event::Draft(f) => panic!("a draft without drafts asked for: {f:?}"),
            }
        }
        // The sphere was shifted to x = 4: so are the faces.
        let mesh = Mesh::from_triangles(corners);
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
        assert!(t0.elapsed() < Duration::from_secs(10), "still running");
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(engine.metrics().render().contains("requests_finished_total{reason=\"cancelled\"} 1"));
}

#[test]
fn a_stalled_reader_is_cancelled_after_the_idle_timeout_and_finds_why() {
    let idle = Duration::from_millis(300);
    let (engine, model) = engine(EngineConfig {
        max_running: 1,
        stream_buffer: 2,
        stream_idle_timeout: idle,
        ..EngineConfig::default()
    });
    let mut stalled = engine.submit(request(&model, 1, 40)).unwrap();
    let first = runtime().block_on(stalled.next());
    assert!(matches!(first, Some(Event::Face(_))), "{first:?}");
    // Nobody reads on: the slot is given back once the timeout has passed.
    let t0 = Instant::now();
    while engine.status().running > 0 {
        assert!(t0.elapsed() < Duration::from_secs(10), "the stalled stream still runs");
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(t0.elapsed() >= idle / 2, "cancelled before it stalled long: {:?}", t0.elapsed());
    assert!(engine.metrics().render().contains("requests_failed_total{reason=\"stream_idle\"} 1"));
    // The reader finds its buffered faces, then the reason.
    let rest = runtime().block_on(async {
        let mut events = Vec::new();
        while let Some(e) = stalled.next().await {
            events.push(e);
        }
        events
    });
    assert!(matches!(rest.last(), Some(Event::Failed(EngineError::StreamIdle(_)))), "{rest:?}");
    // A reader that keeps up is never cancelled, however long it takes.
    let done = runtime().block_on(engine.submit(request(&model, 2, 40)).unwrap().collect());
    assert!(done.is_ok(), "{done:?}");
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
        assert!(t0.elapsed() < Duration::from_secs(10), "never started");
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
    assert!(matches!(engine.submit(r.clone()), Err(EngineError::InvalidInput(_))));
    r.options.sampling.temperature = 0.0;
    for beam in [0, crate::model::MAX_FACE_BEAM + 1] {
        r.options.face_beam = Some(beam);
        assert!(matches!(engine.submit(r.clone()), Err(EngineError::InvalidInput(_))));
    }
    r.options.face_beam = None;
    for candidates in [0, MAX_CANDIDATES + 1] {
        r.options.candidates = Some(candidates);
        assert!(matches!(engine.submit(r.clone()), Err(EngineError::InvalidInput(_))));
    }
    r.options.candidates = None;
    r.options.fit_rounds = Some(crate::mesh::MAX_FIT_ROUNDS + 1);
    assert!(matches!(engine.submit(r.clone()), Err(EngineError::InvalidInput(_))));
    // Fitting runs on the picking task too.
    r.options.fit_rounds = Some(1);
    assert!(matches!(engine.submit(r.clone()), Err(EngineError::Unsupported(_))));
    r.options.fit_rounds = None;
    r.options.weld_radius = Some(crate::candidates::MAX_WELD_RADIUS + 1);
    assert!(matches!(engine.submit(r.clone()), Err(EngineError::InvalidInput(_))));
    // So does welding.
    r.options.weld_radius = Some(1);
    assert!(matches!(engine.submit(r.clone()), Err(EngineError::Unsupported(_))));
    r.options.weld_radius = None;
    r.options.max_hole_edges = Some(crate::mesh::MAX_HOLE_EDGES + 1);
    assert!(matches!(engine.submit(r.clone()), Err(EngineError::InvalidInput(_))));
    r.options.max_hole_edges = None;
    r.options.hull_faces = Some(engine.face_limit() + 1);
    assert!(matches!(engine.submit(r.clone()), Err(EngineError::InvalidInput(_))));
    r.options.hull_faces = None;
    // Best-of-N runs a task that picks the winner: outside a runtime it has nowhere to run.
    r.options.candidates = Some(2);
    assert!(matches!(engine.submit(r.clone()), Err(EngineError::Unsupported(_))));
    assert_eq!(engine.status().waiting, 0);
}

#[test]
fn a_best_of_request_streams_the_candidate_closest_to_its_points() {
    let (engine, model) = engine(EngineConfig::default());
    let mut r = request_with_draws(&model, 2, 15, 3);
    r.options.candidates = Some(3);
    let Conditioning::Points(p) = &r.conditioning else { unreachable!() };
    let base = GenerateOptions { max_faces: 15, ..GenerateOptions::default() };
    // Each candidate decodes from its own draw of the points.
    let alone: Vec<Vec<FaceToken>> = candidate_options(&base, 3)
        .into_iter()
        .enumerate()
        .map(|(i, o)| {
            let latents = engine_encode(&model, &p.for_candidate(i));
            generate(&model, &latents, o, |_| ControlFlow::Continue(())).unwrap().0
        })
        .collect();
    assert!(alone[0] != alone[1] || alone[1] != alone[2], "the draws decode alike");
    // Judged as the engine judges them: against the request's reference points, not the
    // encoder's (two close candidates can rank differently against the two).
    let seed = r.options.sampling.seed;
    let distances: Vec<f64> = alone
        .iter()
        .map(|f| input_distance(&detokenize(f, engine.quantizer), &p.reference.vertices, seed))
        .collect();
    let best = (0..3).min_by(|&a, &b| distances[a].total_cmp(&distances[b])).unwrap();
    let done = runtime().block_on(async { engine.submit(r).unwrap().collect().await.unwrap() });
    assert_eq!(done.tokens, alone[best], "distances {distances:?}");
    assert_eq!(done.summary.faces, done.tokens.len());
    // The candidates ran as three requests of the engine.
    let text = engine.metrics().render();
    let finished: f64 = text
        .lines()
        .filter(|l| l.starts_with("meshstream_requests_finished_total{"))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum();
    assert_eq!(finished, 3.0, "{text}");
}

#[test]
fn a_fitted_request_streams_its_faces_moved_closer_to_its_points() {
    // The decoded faces alone: the convex hull of a sphere's points would win against them.
    let (engine, model) = engine(EngineConfig { hull_faces: 0, ..EngineConfig::default() });
    let plain = request(&model, 3, 30);
    let mut fitted = plain.clone();
    fitted.options.fit_rounds = Some(20);
    let Conditioning::Points(p) = &plain.conditioning else { unreachable!() };
    let (points, normalization) = (p.encoder.points.clone(), p.normalization);
    let work = |stage| engine.metrics().work_seconds(stage);
    let (plain, fitted, measuring) = runtime().block_on(async {
        let plain = engine.submit(plain).unwrap().collect().await.unwrap();
        // Counted as work of its stages: a plain request ends by measuring its answer only.
        assert!(work(Stage::Encode) > 0.0 && work(Stage::Decode) > 0.0);
        let measuring = work(Stage::End);
        assert!(measuring > 0.0);
        (plain, engine.submit(fitted).unwrap().collect().await.unwrap(), measuring)
    });
    assert!(work(Stage::End) > 2.0 * measuring, "fitting is counted as ending the request");
    // The faces as decoded without fitting (this model's have no flat polygons to split
    // again), less the faces and parts that add nothing, some turned to face out; only their
    // corners moved.
    let corners = |t: &FaceToken| {
        let mut c = [[t[0], t[1], t[2]], [t[3], t[4], t[5]], [t[6], t[7], t[8]]];
        c.sort_unstable();
        c
    };
    let decoded: Vec<[[u16; 3]; 3]> = plain.tokens.iter().map(corners).collect();
    assert!(!fitted.tokens.is_empty());
    assert!(fitted.tokens.iter().all(|t| decoded.contains(&corners(t))), "{:?}", fitted.tokens);
    assert_eq!(fitted.mesh.faces.len(), fitted.tokens.len());
    assert_eq!(fitted.summary.faces, fitted.tokens.len());
    assert_ne!(fitted.mesh.vertices, plain.mesh.vertices);
    assert_eq!(crate::metrics::topology(&fitted.mesh).misoriented_edges, 0);
    let from_points = |mesh: &Mesh| {
        let normalized = normalization.apply_mesh(mesh);
        let on_surface = crate::mesh::sample_surface(&normalized, 4096, 0).unwrap();
        crate::metrics::point_set_distances(&on_surface.vertices, &points).chamfer
    };
    let (before, after) = (from_points(&plain.mesh), from_points(&fitted.mesh));
    assert!(after < before, "Chamfer distance to the points {before} as decoded, {after} fitted");
}

#[test]
fn a_fitted_request_answers_with_the_convex_hull_when_it_ends_closer() {
    // This test model's decodes of a sphere lie far from its points; their hull does not.
    // The engine's setting holds unless the request says otherwise.
    let settings = [(40, None, true), (0, None, false), (40, Some(0), false), (0, Some(40), true)];
    for (configured, asked, hull_wins) in settings {
        let config = EngineConfig { hull_faces: configured, ..EngineConfig::default() };
        let (engine, model) = engine(config);
        let mut fitted = request(&model, 3, 30);
        fitted.options.fit_rounds = Some(20);
        fitted.options.candidates = Some(2);
        fitted.options.hull_faces = asked;
        let done = runtime().block_on(async { engine.submit(fitted).unwrap().collect().await });
        let done = done.unwrap();
        let setting = format!("{configured} configured, {asked:?} asked");
        assert_eq!(done.summary.finish == FinishReason::ConvexHull, hull_wins, "{setting}");
        if hull_wins {
            // Within the request's face budget, closed, every face streamed with its token.
            assert!(done.mesh.faces.len() <= 30, "{}", done.mesh.faces.len());
            assert!(MeshQuality::measure(&done.mesh, None).watertight);
            assert_eq!(done.tokens.len(), done.mesh.faces.len());
        }
    }
}

#[test]
fn an_answer_is_measured_as_the_client_gets_it() {
    let (engine, model) = engine(EngineConfig::default());
    let plain = request(&model, 3, 30);
    let Conditioning::Points(p) = &plain.conditioning else { unreachable!() };
    let (reference, normalization) = (Arc::clone(&p.reference), p.normalization);
    let mut fitted = plain.clone();
    fitted.options.fit_rounds = Some(20);
    fitted.options.candidates = Some(2);
    for (name, request) in [("plain", plain), ("two candidates, fitted", fitted)] {
        let done = runtime().block_on(async { engine.submit(request).unwrap().collect().await });
        let done = done.unwrap();
        assert!(!done.mesh.faces.is_empty(), "{name}");
        let quality = done.summary.quality.expect("measured");
        // The faces handed over, in the frame of the input points they are measured against.
        let normalized = normalization.apply_mesh(&done.mesh);
        assert_eq!(quality, MeshQuality::measure(&normalized, Some(&reference.vertices)), "{name}");
        assert!(quality.input_chamfer.is_some_and(|d| d > 0.0), "{name}: {quality:?}");
    }
}

#[test]
fn drafts_are_the_first_candidate_as_decoded_then_the_answer_follows() {
    let (engine, model) = engine(EngineConfig::default());
    let plain = request_with_draws(&model, 3, 30, 3);
    let mut drafted = plain.clone();
    drafted.options.candidates = Some(3);
    drafted.options.fit_rounds = Some(20);
    drafted.options.drafts = true;
    let mut undrafted = drafted.clone();
    undrafted.options.drafts = false;
    let (drafts, faces, answer, first) = runtime().block_on(async {
        let (mut drafts, mut faces) = (Vec::new(), Vec::new());
        let mut stream = engine.submit(drafted).unwrap();
        while let Some(event) = stream.next().await {
            match event {
                Event::Draft(f) => {
                    assert!(faces.is_empty(), "a draft after the answer's first face");
                    drafts.push(f);
                }
                Event::Face(f) => faces.push(f),
                Event::Finished(_) => break,
                Event::Progress { .. } | Event::Failed(_) => panic!("{event:?}"),
            }
        }
        let answer = engine.submit(undrafted).unwrap().collect().await.unwrap();
        // The first candidate alone: the request as asked, one candidate, as decoded.
        let Conditioning::Points(p) = &plain.conditioning else { unreachable!() };
        let mut first = plain.clone();
        first.conditioning = Conditioning::Points(p.for_candidate(0));
        let first = engine.submit(first).unwrap().collect().await.unwrap();
        (drafts, faces, answer, first)
    });
    let tokens = |faces: &[StreamedFace]| faces.iter().map(|f| f.token).collect::<Vec<_>>();
    assert!(!drafts.is_empty());
    assert_eq!(tokens(&drafts), first.tokens, "drafts are the first candidate's faces");
    assert!(drafts.iter().enumerate().all(|(i, f)| f.index == i));
    // The answer is what it is without drafts.
    assert_eq!(tokens(&faces), answer.tokens);
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

/// An engine with an image model whose latents fit the micro face model.
fn image_engine(config: EngineConfig) -> (Engine, FaceModel, crate::diffusion::DiffusionModel) {
    let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
    let (_, model) = random_model(&cfg);
    image_engine_with(model, config)
}

/// A model whose first coordinate always says end of mesh: every mesh comes out empty.
fn model_that_ends_at_once() -> FaceModel {
    let cfg = FaceConfig { quant_levels: 128, ..FaceConfig::micro() };
    let (varmap, _) = random_model(&cfg);
    {
        let vars = varmap.data().lock().unwrap();
        let bias = &vars["head.sub.0.fc2.bias"];
        let mut values = bias.to_vec1::<f32>().unwrap();
        values[cfg.quant_levels] = 1e4;
        bias.set(&candle_core::Tensor::new(values, &candle_core::Device::Cpu).unwrap()).unwrap();
    }
    crate::model::checkpoint::inference_model(&cfg, &varmap, &candle_core::Device::Cpu).unwrap()
}

fn image_engine_with(
    model: FaceModel,
    config: EngineConfig,
) -> (Engine, FaceModel, crate::diffusion::DiffusionModel) {
    let cfg = model.config().clone();
    let dit_cfg = crate::diffusion::DitConfig {
        num_latents: cfg.num_latents,
        latent_dim: cfg.latent_dim,
        latent_stats: crate::diffusion::LatentStats::identity(cfg.latent_dim),
        encoder_fingerprint: None,
        ..crate::diffusion::DitConfig::micro()
    };
    let (varmap, dit) = crate::diffusion::checkpoint::random_varmap(&dit_cfg);
    let same = crate::diffusion::checkpoint::inference_model(
        &dit_cfg,
        &varmap,
        &candle_core::Device::Cpu,
        None,
    )
    .unwrap();
    let engine =
        Engine::start(model.clone(), Some(same), config, Arc::new(Metrics::default())).unwrap();
    (engine, model, dit)
}

fn image_request(id: usize, steps: usize, guidance: f32, max_faces: usize) -> Request {
    let shade = 40 + 50 * id as u8;
    let img =
        image::RgbImage::from_fn(24, 20, |x, y| image::Rgb([shade, (x * 9) as u8, (y * 11) as u8]));
    let mut png = std::io::Cursor::new(Vec::new());
    img.write_to(&mut png, image::ImageFormat::Png).unwrap();
    let image =
        crate::diffusion::decode_image(png.get_ref(), &crate::diffusion::ImageOptions::new(16))
            .unwrap();
    Request {
        id: format!("img{id}"),
        conditioning: Conditioning::Image(ImagePrompt { image, steps, guidance, seed: id as u64 }),
        options: DecodeOptions { max_faces: Some(max_faces), ..Default::default() },
        deadline: None,
    }
}

/// What an image request gives without the engine: sampled alone, decoded alone.
fn reference_image_faces(
    model: &FaceModel,
    dit: &crate::diffusion::DiffusionModel,
    request: &Request,
    max_faces: usize,
) -> Vec<FaceToken> {
    use rand::SeedableRng;
    let Conditioning::Image(p) = &request.conditioning else { unreachable!() };
    let images = crate::diffusion::images_to_tensor(
        std::slice::from_ref(&p.image),
        &candle_core::Device::Cpu,
    )
    .unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(p.seed);
    let latents = dit.generate(&images, vec![p.guidance], p.steps, &mut rng).unwrap();
    let opts = GenerateOptions { max_faces, ..GenerateOptions::default() };
    let mut g = Generation::new(model, &latents.get(0).unwrap(), opts).unwrap();
    while !g.is_finished() {
        step_generations(model, &mut [&mut g]).unwrap();
    }
    g.faces().to_vec()
}

#[test]
fn image_requests_report_progress_then_decode_as_alone_next_to_point_requests() {
    let (engine, model, dit) = image_engine(EngineConfig::default());
    let images: Vec<Request> =
        [(0, 3, 1.0), (1, 6, 2.5), (2, 4, 0.0)].map(|(i, s, g)| image_request(i, s, g, 15)).into();
    let expected: Vec<_> =
        images.iter().map(|r| reference_image_faces(&model, &dit, r, 15)).collect();
    let points = request(&model, 5, 10);
    let points_expected = reference_faces(&model, &points, 10);
    let results = runtime().block_on(async {
        // Submitted in the runtime: an image request that came out empty would be sampled
        // again (`EngineConfig::image_attempts`), by a task of its own.
        let mut streams: Vec<_> = images.into_iter().map(|r| engine.submit(r).unwrap()).collect();
        let points_stream = engine.submit(points).unwrap();
        let mut out = Vec::new();
        for s in &mut streams {
            let mut progress = Vec::new();
            let mut tokens = Vec::new();
            while let Some(event) = s.next().await {
                match event {
                    Event::Progress { step, steps } => {
                        assert!(tokens.is_empty(), "progress after a face");
                        progress.push((step, steps));
                    }
                    Event::Face(f) => tokens.push(f.token),
                    Event::Draft(f) => panic!("a draft of an image request: {f:?}"),
                    Event::Finished(_) => break,
                    Event::Failed(e) => panic!("{e}"),
                }
            }
            out.push((progress, tokens));
        }
        (out, points_stream.collect().await.unwrap())
    });
    let (image_results, points_done) = results;
    for (i, ((progress, tokens), want)) in image_results.iter().zip(&expected).enumerate() {
        let steps = [3, 6, 4][i];
        let all: Vec<_> = (1..=steps).map(|k| (k, steps)).collect();
        assert_eq!(progress, &all, "request {i}");
        assert_eq!(tokens, want, "request {i}");
    }
    assert_eq!(points_done.tokens, points_expected);
    // Submitted together, they shared diffusion steps: fewer steps than 3 + 6 + 4, and some
    // with more than one row.
    let text = engine.metrics().render();
    let value = |prefix: &str| -> f64 {
        let line = text.lines().find(|l| l.starts_with(prefix)).unwrap();
        line.rsplit(' ').next().unwrap().parse().unwrap()
    };
    let steps = value("meshstream_diffusion_steps_total");
    assert!((6.0..13.0).contains(&steps), "{text}");
    assert!(value("meshstream_diffusion_batch_size_bucket{le=\"1.0\"}") < steps, "{text}");
}

#[test]
fn image_requests_are_checked_and_refused_without_an_image_model() {
    let (plain, _) = engine(EngineConfig::default());
    assert!(matches!(plain.submit(image_request(0, 3, 1.0, 5)), Err(EngineError::Unsupported(_))));
    let (engine, _, _) =
        image_engine(EngineConfig { max_diffusion_steps: 10, ..EngineConfig::default() });
    let mut best_of_image = image_request(0, 3, 1.0, 5);
    best_of_image.options.candidates = Some(2);
    assert!(matches!(engine.submit(best_of_image), Err(EngineError::InvalidInput(_))));
    for (steps, guidance) in [(0, 1.0), (11, 1.0), (3, -0.5), (3, f32::NAN), (3, 25.0)] {
        let r = engine.submit(image_request(0, steps, guidance, 5));
        assert!(
            matches!(r, Err(EngineError::InvalidInput(_))),
            "steps {steps} guidance {guidance}"
        );
    }
    let mut wrong_size = image_request(0, 3, 1.0, 5);
    if let Conditioning::Image(p) = &mut wrong_size.conditioning {
        let png = {
            let mut c = std::io::Cursor::new(Vec::new());
            image::RgbImage::new(8, 8).write_to(&mut c, image::ImageFormat::Png).unwrap();
            c.into_inner()
        };
        let as_given = crate::diffusion::ImageOptions {
            framing: crate::diffusion::Framing::CentreCrop,
            ..crate::diffusion::ImageOptions::new(8)
        };
        p.image = crate::diffusion::decode_image(&png, &as_given).unwrap();
    }
    assert!(matches!(engine.submit(wrong_size), Err(EngineError::InvalidInput(_))));
}

#[test]
fn a_cancelled_image_request_leaves_the_diffusion_batch() {
    let (engine, _, _) =
        image_engine(EngineConfig { max_diffusion_steps: 100_000, ..EngineConfig::default() });
    // A worker thread forwards the request's events while this thread waits.
    let runtime =
        tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
    let _inside = runtime.enter();
    let stream = engine.submit(image_request(1, 100_000, 2.0, 5)).unwrap();
    let t0 = Instant::now();
    while engine.status().running == 0 {
        assert!(t0.elapsed() < Duration::from_secs(10), "never started");
        std::thread::sleep(Duration::from_millis(2));
    }
    drop(stream);
    while engine.status().running > 0 {
        assert!(t0.elapsed() < Duration::from_secs(10), "still diffusing");
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(engine.metrics().render().contains("requests_finished_total{reason=\"cancelled\"} 1"));
}

#[test]
fn an_image_request_whose_mesh_comes_out_empty_is_sampled_again_from_the_next_seeds() {
    let events_of = |attempts: usize| {
        let (engine, _, _) = image_engine_with(
            model_that_ends_at_once(),
            EngineConfig { image_attempts: attempts, ..EngineConfig::default() },
        );
        let (progress, summary) = runtime().block_on(async {
            let mut stream = engine.submit(image_request(0, 2, 1.0, 5)).unwrap();
            let mut progress = Vec::new();
            loop {
                match stream.next().await.unwrap() {
                    Event::Progress { step, .. } => progress.push(step),
                    Event::Face(f) | Event::Draft(f) => {
                        panic!("a face from a model that ends at once: {f:?}")
                    }
                    Event::Finished(summary) => return (progress, summary),
                    Event::Failed(e) => panic!("{e}"),
                }
            }
        });
        (progress, summary, engine.metrics().render())
    };
    // Every attempt is sampled in full (its progress shown again), then the empty answer.
    let (progress, summary, metrics) = events_of(3);
    assert_eq!(progress, [1, 2, 1, 2, 1, 2]);
    assert_eq!((summary.faces, summary.finish), (0, crate::model::FinishReason::EndOfMesh));
    assert!(summary.total >= summary.decode && summary.queued <= summary.total);
    // Measured, without input points to measure a distance to.
    let quality = summary.quality.expect("measured");
    assert_eq!((quality.edges, quality.parts, quality.input_chamfer), (0, 0, None));
    assert!(metrics.contains("meshstream_image_resamples_total 2"), "{metrics}");
    let (progress, _, metrics) = events_of(1);
    assert_eq!(progress, [1, 2], "one attempt: never sampled again");
    assert!(metrics.contains("meshstream_image_resamples_total 0"), "{metrics}");
}

#[test]
fn further_attempts_start_from_the_next_seeds() {
    let request = image_request(4, 2, 1.0, 5);
    let next = resample::next_attempt(&request, 2);
    assert_eq!(next.id, "img4/attempt-2");
    let Conditioning::Image(prompt) = next.conditioning else { unreachable!() };
    assert_eq!(prompt.seed, 6);
}
