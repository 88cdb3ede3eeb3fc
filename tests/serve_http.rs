//! `meshstream serve` over HTTP, as a client sees it: the real binary on an ephemeral port.

mod common;

use std::time::{Duration, Instant};

use common::{Server, points_json, shape, stream_through};
use futures_util::StreamExt;
use meshstream::mesh::primitives::uv_sphere;
use meshstream::mesh::{Format, Mesh, ReadLimits, read_mesh, sample_surface, write_mesh};
use meshstream::metrics::{point_set_distances, topology};
use serde_json::{Value, json};

fn client() -> reqwest::Client {
    reqwest::Client::new()
}

async fn reconstruct_glb(server: &Server, body: &Value) -> (reqwest::header::HeaderMap, Vec<u8>) {
    let r = client().post(server.url("/reconstruct")).json(body).send().await.unwrap();
    assert_eq!(r.status(), 200, "{:?}", r.text().await);
    let headers = r.headers().clone();
    (headers, r.bytes().await.unwrap().to_vec())
}

/// Face events of an SSE or NDJSON stream with their arrival times, and the final event.
async fn stream_events(
    server: &Server,
    body: &Value,
    accept: &str,
) -> (Vec<(Instant, Value)>, Value) {
    let r = client()
        .post(server.url("/reconstruct"))
        .header("accept", accept)
        .json(body)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let mut chunks = r.bytes_stream();
    let (mut buffer, mut faces) = (String::new(), Vec::new());
    while let Some(chunk) = chunks.next().await {
        buffer.push_str(std::str::from_utf8(&chunk.unwrap()).unwrap());
        while let Some(end) = buffer.find('\n') {
            let line: String = buffer.drain(..=end).collect();
            let data = if accept == "text/event-stream" {
                match line.strip_prefix("data: ") {
                    Some(d) => d.trim().to_string(),
                    None => continue,
                }
            } else {
                line.trim().to_string()
            };
            if data.is_empty() {
                continue;
            }
            let v: Value = serde_json::from_str(&data).unwrap();
            if v.get("vertices").is_some() {
                faces.push((Instant::now(), v));
            } else {
                return (faces, v);
            }
        }
    }
    panic!("the stream ended without a final event");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_glb_comes_back_in_the_callers_coordinates() {
    let server = Server::start(&[]);
    let cloud = shape();
    let (h, base) = reconstruct_glb(&server, &points_json(&cloud, json!({"max_faces": 60}))).await;
    assert_eq!(h["content-type"], "model/gltf-binary");
    assert!(h.contains_key("x-request-id"));
    let faces: usize = h["x-meshstream-faces"].to_str().unwrap().parse().unwrap();
    let base = read_mesh(&base, Format::Gltf, &ReadLimits::default()).unwrap();
    assert_eq!(base.faces.len(), faces);
    assert!(faces > 0 && faces <= 60);

    // The same shape scaled by 10 and moved: the same faces, scaled and moved the same way.
    // As decoded, the corners too. Fitted (the default), only as close to the points: the
    // moved points round differently in the normalized frame, the fit's nearest-neighbour
    // matches break near ties the other way, and over its rounds corners can settle where the
    // base answer's did not (up to a few grid steps on this soup of 60 faces).
    let shift = |v: [f32; 3]| [v[0] * 10.0 + 5.0, v[1] * 10.0 - 20.0, v[2] * 10.0 + 1.0];
    let unshift = |v: &[f32; 3]| [(v[0] - 5.0) / 10.0, (v[1] + 20.0) / 10.0, (v[2] - 1.0) / 10.0];
    let mut moved = cloud.clone();
    moved.vertices.iter_mut().for_each(|v| *v = shift(*v));
    let (lo, hi) = cloud.bounds().unwrap();
    let step = (0..3).map(|k| hi[k] - lo[k]).fold(0.0f32, f32::max) / 128.0;
    // Mean distance from a mesh's corners to their nearest input point, in grid steps.
    let off_the_points = |corners: &[[f32; 3]]| {
        point_set_distances(corners, &cloud.vertices).accuracy / f64::from(step)
    };
    for fit_rounds in [0, 40] {
        let options = json!({"max_faces": 60, "fit_rounds": fit_rounds});
        let (_, base) = reconstruct_glb(&server, &points_json(&cloud, options.clone())).await;
        let (_, out) = reconstruct_glb(&server, &points_json(&moved, options)).await;
        let base = read_mesh(&base, Format::Gltf, &ReadLimits::default()).unwrap();
        let out = read_mesh(&out, Format::Gltf, &ReadLimits::default()).unwrap();
        assert_eq!(out.faces, base.faces);
        let back: Vec<[f32; 3]> = out.vertices.iter().map(unshift).collect();
        if fit_rounds == 0 {
            for (a, b) in base.vertices.iter().zip(&back) {
                assert!((0..3).all(|k| (a[k] - b[k]).abs() < 1e-4), "{b:?} vs {a:?}");
            }
        } else {
            let (a, b) = (off_the_points(&base.vertices), off_the_points(&back));
            assert!(a < 8.0 && (a - b).abs() < 0.25, "{a} vs {b} grid steps off the points");
        }
    }

    // The same shape lying with +z up, sent with `up: "z"` (as a raw upload's query
    // parameter too): the same answer, lying as sent. A turn between axes is exact, so are
    // the answers, fitted or not.
    let lie = |v: [f32; 3]| [v[0], -v[2], v[1]];
    let mut lying = cloud.clone();
    lying.vertices.iter_mut().for_each(|v| *v = lie(*v));
    if let Some(normals) = lying.normals.as_mut() {
        normals.iter_mut().for_each(|n| *n = lie(*n));
    }
    let read = |glb: &[u8]| read_mesh(glb, Format::Gltf, &ReadLimits::default()).unwrap();
    let options = json!({"max_faces": 60});
    let base = read(&reconstruct_glb(&server, &points_json(&cloud, options)).await.1);
    let options = json!({"max_faces": 60, "up": "z"});
    let out = read(&reconstruct_glb(&server, &points_json(&lying, options)).await.1);
    assert_eq!(out.faces, base.faces);
    assert_eq!(out.vertices, base.vertices.iter().map(|&v| lie(v)).collect::<Vec<_>>());
    let upload = |query: &str| {
        let ply = write_mesh(&lying, Format::Ply).unwrap();
        let url = server.url(&format!("/reconstruct?{query}"));
        client().post(url).header("content-type", "application/ply").body(ply).send()
    };
    let r = upload("max_faces=60&up=z").await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(read(&r.bytes().await.unwrap()).faces, base.faces);
    let bad = upload("up=w").await.unwrap();
    assert_eq!(bad.status(), 422);
    assert!(bad.text().await.unwrap().contains("x, -x, y, -y, z, -z"));

    // Other formats by option, and a raw upload of a mesh file with options in the query.
    let (h, obj) =
        reconstruct_glb(&server, &points_json(&cloud, json!({"max_faces": 30, "format": "obj"})))
            .await;
    assert_eq!(h["content-type"], "model/obj");
    assert!(read_mesh(&obj, Format::Obj, &ReadLimits::default()).is_ok());
    let upload =
        write_mesh(&meshstream::mesh::primitives::cuboid([2.0, 1.0, 1.0]), Format::Ply).unwrap();
    let r = client()
        .post(server.url("/reconstruct?max_faces=20&format=stl&face_beam=2&candidates=3"))
        .header("content-type", "application/ply")
        .body(upload)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "model/stl");
    // A GLB made small for the web (Draco-compressed by Google's encoder) is an upload as any.
    let draco = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/web-gltf/pine-tree-draco.glb");
    let r = client()
        .post(server.url("/reconstruct?max_faces=20"))
        .header("content-type", "model/gltf-binary")
        .body(std::fs::read(draco).unwrap())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert!(read_mesh(&r.bytes().await.unwrap(), Format::Gltf, &ReadLimits::default()).is_ok());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streams_deliver_faces_as_they_are_decoded_and_equal_the_mesh() {
    let server = Server::start(&[]);
    // One candidate, no weld and no fitting for both: a whole mesh otherwise defaults to the
    // best of several, welded and fitted to the points.
    let as_decoded = json!({"max_faces": 200, "candidates": 1, "weld_radius": 0, "fit_rounds": 0});
    let body = points_json(&shape(), as_decoded);
    let (headers, glb) = reconstruct_glb(&server, &body).await;
    let mesh = read_mesh(&glb, Format::Gltf, &ReadLimits::default()).unwrap();
    // The answer says how it is built, as counted on the file here, and how far it lies from
    // the points.
    let header = |name: &str| headers[name].to_str().unwrap().to_string();
    let built = topology(&mesh);
    assert_eq!(header("x-meshstream-edges"), built.edges.to_string());
    assert_eq!(header("x-meshstream-boundary-edges"), built.boundary_edges.to_string());
    assert_eq!(header("x-meshstream-non-manifold-edges"), built.non_manifold_edges.to_string());
    assert_eq!(header("x-meshstream-parts"), built.parts.to_string());
    let watertight = built.boundary_edges == 0 && built.non_manifold_edges == 0;
    assert_eq!(header("x-meshstream-watertight"), watertight.to_string());
    let input_chamfer: f64 = header("x-meshstream-input-chamfer").parse().unwrap();
    assert!(input_chamfer > 0.0 && input_chamfer < 2.0, "{input_chamfer}");
    for accept in ["text/event-stream", "application/x-ndjson"] {
        let (faces, done) = stream_events(&server, &body, accept).await;
        assert_eq!(done["faces"].as_u64().unwrap() as usize, faces.len(), "{done}");
        let q = &done["quality"];
        assert_eq!(q["edges"], built.edges, "{done}");
        assert_eq!(q["boundary_edges"], built.boundary_edges, "{done}");
        assert_eq!(q["non_manifold_edges"], built.non_manifold_edges, "{done}");
        assert_eq!((&q["parts"], &q["watertight"]), (&json!(built.parts), &json!(watertight)));
        assert!((q["input_chamfer"].as_f64().unwrap() - input_chamfer).abs() < 1e-5, "{done}");
        assert_eq!(faces.len(), mesh.faces.len(), "{accept}");
        for (i, (_, f)) in faces.iter().enumerate() {
            assert_eq!(f["index"], i);
            let streamed: Vec<[f32; 3]> = serde_json::from_value(f["vertices"].clone()).unwrap();
            let face = mesh.faces[i].map(|v| mesh.vertices[v as usize]);
            for (a, b) in streamed.iter().zip(&face) {
                assert!((0..3).all(|k| (a[k] - b[k]).abs() < 1e-5), "{a:?} vs {b:?}");
            }
        }
        if faces.len() >= 20 {
            let span = faces[faces.len() - 1].0 - faces[0].0;
            assert!(span > Duration::from_millis(5), "all faces arrived at once ({span:?})");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_of_a_whole_answer_sends_drafts_first_when_asked() {
    let server = Server::start(&[]);
    let options = json!({"max_faces": 120, "candidates": 3, "fit_rounds": 20, "drafts": true});
    let r = client()
        .post(server.url("/reconstruct"))
        .header("accept", "text/event-stream")
        .json(&points_json(&shape(), options))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let text = r.text().await.unwrap();
    let kinds: Vec<&str> = text.lines().filter_map(|l| l.strip_prefix("event: ")).collect();
    let (drafts, faces) = kinds.iter().fold((0, 0), |(d, f), k| match *k {
        "draft" => (d + 1, f),
        "face" => (d, f + 1),
        _ => (d, f),
    });
    assert!(drafts > 0 && faces > 0, "{kinds:?}");
    // Every draft first, then the answer's faces, then done.
    let first_face = kinds.iter().position(|k| *k == "face").unwrap();
    assert!(kinds[..first_face].iter().all(|k| *k == "draft"), "{kinds:?}");
    assert_eq!(kinds.last(), Some(&"done"));
    assert_eq!(kinds.len(), drafts + faces + 1);
    // A whole mesh has no one to show drafts to: the option changes nothing there.
    let body = json!({"max_faces": 120, "candidates": 3, "fit_rounds": 20});
    let (_, plain) = reconstruct_glb(&server, &points_json(&shape(), body.clone())).await;
    let mut asked = body;
    asked["drafts"] = json!(true);
    let (_, drafted) = reconstruct_glb(&server, &points_json(&shape(), asked)).await;
    assert_eq!(plain, drafted);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn whole_meshes_default_to_the_servers_candidates_and_streams_to_one() {
    let server = Server::start(&["--candidates", "3"]);
    let c = client();
    let info: Value = c.get(server.url("/v1/info")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["defaults"]["candidates"], json!({"whole_mesh": 3, "stream": 1}));
    let temperature = info["defaults"]["temperature"].as_f64().unwrap() as f32;
    assert_eq!(temperature, meshstream::model::DEFAULT_TEMPERATURE);
    // Every candidate is an engine request of its own.
    let finished = || server.metric(&c, "meshstream_requests_finished_total{");
    let body = points_json(&shape(), json!({"max_faces": 40}));
    reconstruct_glb(&server, &body).await;
    assert_eq!(finished().await, 3.0);
    stream_events(&server, &body, "application/x-ndjson").await;
    assert_eq!(finished().await, 4.0);
    let asked = points_json(&shape(), json!({"max_faces": 40, "candidates": 2}));
    stream_events(&server, &asked, "application/x-ndjson").await;
    assert_eq!(finished().await, 6.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn whole_meshes_are_fitted_to_their_points_and_streams_when_they_ask() {
    // The decoded faces alone: the convex hull of these points would win against them.
    let args = ["--candidates", "1", "--fit-rounds", "7", "--reference-points", "500"];
    let server = Server::start(&[&args[..], &["--hull-faces", "0"]].concat());
    let c = client();
    let info: Value = c.get(server.url("/v1/info")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["defaults"]["fit_rounds"], json!({"whole_mesh": 7, "stream": 0}));
    assert_eq!(info["defaults"]["weld_radius"], json!({"whole_mesh": 1, "stream": 0}));
    assert_eq!(info["defaults"]["reference_points"], 500);
    let read = |glb: &[u8]| read_mesh(glb, Format::Gltf, &ReadLimits::default()).unwrap();
    // Holes left open, so that the faces are the decoded ones (closing them adds faces).
    let fitted = json!({"max_hole_edges": 0});
    let fitted = read(&reconstruct_glb(&server, &points_json(&shape(), fitted)).await.1);
    let as_decoded = json!({"fit_rounds": 0});
    let decoded = read(&reconstruct_glb(&server, &points_json(&shape(), as_decoded)).await.1);
    // The same faces, their corners moved (a flat polygon may come split the other way for
    // its moved corners, so as many faces, not the same triples).
    assert_eq!(fitted.faces.len(), decoded.faces.len());
    assert_ne!(fitted.vertices, decoded.vertices);
    // A stream that asks is welded and fitted alike; its faces come together at the end.
    let asked = json!({"fit_rounds": 7, "weld_radius": 1, "max_hole_edges": 0});
    let asked = points_json(&shape(), asked);
    let (faces, _) = stream_events(&server, &asked, "application/x-ndjson").await;
    assert_eq!(faces.len(), fitted.faces.len());
    for (i, (_, f)) in faces.iter().enumerate() {
        let streamed: Vec<[f32; 3]> = serde_json::from_value(f["vertices"].clone()).unwrap();
        let face = fitted.faces[i].map(|v| fitted.vertices[v as usize]);
        for (a, b) in streamed.iter().zip(&face) {
            assert!((0..3).all(|k| (a[k] - b[k]).abs() < 1e-5), "{a:?} vs {b:?}");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fitted_answer_has_its_small_holes_closed_unless_it_asks_not_to() {
    // The decoded faces alone: the convex hull of these points would win against them.
    let server =
        Server::start(&["--candidates", "1", "--reference-points", "2000", "--hull-faces", "0"]);
    let c = client();
    let info: Value = c.get(server.url("/v1/info")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["defaults"]["max_hole_edges"], 8);
    let read = |glb: &[u8]| read_mesh(glb, Format::Gltf, &ReadLimits::default()).unwrap();
    let answer = |extra: Value| {
        let body = points_json(&shape(), extra);
        let server = &server;
        async move {
            let (headers, glb) = reconstruct_glb(server, &body).await;
            let count = |name: &str| -> usize { headers[name].to_str().unwrap().parse().unwrap() };
            (read(&glb), count("x-meshstream-boundary-edges"))
        }
    };
    let (closed, closed_open_edges) = answer(json!({})).await;
    let (open, open_edges) = answer(json!({"max_hole_edges": 0})).await;
    // The same answer, with faces added over some of its holes and none taken away.
    assert!(closed.faces.len() > open.faces.len(), "no hole was closed: {open_edges} open edges");
    assert!(closed_open_edges < open_edges, "{closed_open_edges} against {open_edges}");
    let corners = |m: &Mesh| -> Vec<[[u32; 3]; 3]> {
        let mut faces: Vec<_> =
            m.faces.iter().map(|f| f.map(|v| m.vertices[v as usize].map(f32::to_bits))).collect();
        faces.sort_unstable();
        faces
    };
    let (all, kept) = (corners(&closed), corners(&open));
    assert!(kept.iter().all(|f| all.binary_search(f).is_ok()), "a face of the open answer is gone");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fitted_answer_is_the_convex_hull_where_that_ends_closer_and_says_so() {
    let server = Server::start(&["--candidates", "1", "--reference-points", "2000"]);
    let c = client();
    let info: Value = c.get(server.url("/v1/info")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["engine"]["hull_faces"], 100);
    // A ball: the shipped model's decode ends further from its points than their hull does.
    let ball = sample_surface(&uv_sphere(1.0, 24, 16), 3000, 7).unwrap();
    let (headers, glb) = reconstruct_glb(&server, &points_json(&ball, json!({}))).await;
    let header = |headers: &reqwest::header::HeaderMap, name: &str| {
        headers[name].to_str().unwrap().to_string()
    };
    assert_eq!(header(&headers, "x-meshstream-finish-reason"), "convex_hull");
    assert_eq!(header(&headers, "x-meshstream-watertight"), "true");
    let hull = read_mesh(&glb, Format::Gltf, &ReadLimits::default()).unwrap();
    assert!(hull.faces.len() <= 100, "{}", hull.faces.len());
    // Not fitted, or asked for no hull: the model's faces only.
    for options in [json!({"fit_rounds": 0}), json!({"hull_faces": 0})] {
        let as_decoded = points_json(&ball, options.clone());
        let (headers, _) = reconstruct_glb(&server, &as_decoded).await;
        assert_ne!(header(&headers, "x-meshstream-finish-reason"), "convex_hull", "{options}");
    }
    // A hull of fewer faces, asked in the query of a raw mesh body.
    let r = client()
        .post(server.url("/reconstruct?hull_faces=40"))
        .header("content-type", "application/ply")
        .body(write_mesh(&uv_sphere(1.0, 24, 16), Format::Ply).unwrap())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(header(r.headers(), "x-meshstream-finish-reason"), "convex_hull");
    let hull = read_mesh(&r.bytes().await.unwrap(), Format::Gltf, &ReadLimits::default()).unwrap();
    assert!(hull.faces.len() <= 40, "{}", hull.faces.len());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sixteen_concurrent_clients_are_batched() {
    let server = Server::start(&[]);
    let cloud = shape();
    let tasks: Vec<_> = (0..16)
        .map(|i| {
            let body = points_json(&cloud, json!({"max_faces": 80, "seed": i, "temperature": 0.7}));
            let url = server.url("/reconstruct");
            tokio::spawn(async move {
                let r = client().post(url).json(&body).send().await.unwrap();
                (r.status(), r.bytes().await.unwrap())
            })
        })
        .collect();
    for t in tasks {
        let (status, body) = t.await.unwrap();
        assert_eq!(status, 200);
        assert!(read_mesh(&body, Format::Gltf, &ReadLimits::default()).is_ok());
    }
    let c = client();
    let count = server.metric(&c, "meshstream_batch_size_count").await;
    let singles = server.metric(&c, "meshstream_batch_size_bucket{le=\"1.0\"}").await;
    assert!(count > singles, "no batch held more than one sequence ({singles} of {count})");
    // Whole meshes with the defaults: every stage of their work was counted.
    for stage in ["prepare", "encode", "decode", "end"] {
        let metric = format!("meshstream_work_seconds_total{{stage=\"{stage}\"}}");
        assert!(server.metric(&c, &metric).await > 0.0, "no {stage} work counted");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_goes_away_frees_its_slot() {
    let server = Server::start(&["--stream-buffer", "4"]);
    let body = points_json(&shape(), json!({"max_faces": 400}));
    let r = client()
        .post(server.url("/reconstruct"))
        .header("accept", "text/event-stream")
        .json(&body)
        .send()
        .await
        .unwrap();
    let mut chunks = r.bytes_stream();
    let _first = chunks.next().await;
    let c = client();
    assert_eq!(server.metric(&c, "meshstream_running_sequences").await, 1.0);
    drop(chunks);
    let t0 = Instant::now();
    loop {
        if server.metric(&c, "meshstream_running_sequences").await == 0.0 {
            break;
        }
        // Loose: shared test machines are slow; the counter below says why it ended.
        assert!(t0.elapsed() < Duration::from_secs(10), "the slot is still taken");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // Cancelled, not decoded to its end.
    let cancelled = "meshstream_requests_finished_total{reason=\"cancelled\"}";
    assert_eq!(server.metric(&c, cancelled).await, 1.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_gets_its_code_and_the_server_survives_garbage() {
    let server = Server::start(&["--max-points", "5000", "--max-body-bytes", "200000"]);
    let c = client();
    let post = |ct: &'static str, body: Vec<u8>, query: &'static str| {
        let c = c.clone();
        let url = server.url(&format!("/reconstruct{query}"));
        async move {
            let r = c.post(url).header("content-type", ct).body(body).send().await.unwrap();
            let status = r.status().as_u16();
            let v: Value = r.json().await.unwrap_or(Value::Null);
            (status, v["error"]["code"].as_str().unwrap_or("").to_string(), v)
        }
    };
    let json = "application/json";
    let three = r#"[[0,0,0],[1,0,0],[0,1,0]]"#;
    let cases: Vec<(&str, Vec<u8>, &str, u16, &str)> = vec![
        (json, b"".to_vec(), "", 400, "malformed_body"),
        (json, b"{\"points\": [".to_vec(), "", 400, "malformed_body"),
        (json, br#"{"points": []}"#.to_vec(), "", 422, "invalid_input"),
        (json, br#"{"points": [[1e39,0,0],[1,0,0],[0,1,0]]}"#.to_vec(), "", 422, "invalid_input"),
        (
            json,
            format!(r#"{{"points": {three}, "max_faces": 0}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "max_faces": 100000}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "top_p": 2}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "face_beam": 0}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "face_beam": 33}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "candidates": 0}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "candidates": 17}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "fit_rounds": 201}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "weld_radius": 5}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "max_hole_edges": 33}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "hull_faces": 100000}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "format": "fbx"}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        (
            json,
            format!(r#"{{"points": {three}, "colour": 1}}"#).into_bytes(),
            "",
            422,
            "invalid_input",
        ),
        ("image/png", b"\x89PNG".to_vec(), "", 400, "unsupported_format"),
        ("application/octet-stream", b"\x00garbage\x01".to_vec(), "", 400, "unsupported_format"),
        (
            "application/ply",
            b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999\nend_header\n".to_vec(),
            "",
            400,
            "malformed_body",
        ),
        (
            "model/obj",
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\n".to_vec(),
            "?max_faces=abc",
            422,
            "invalid_input",
        ),
        ("model/obj", vec![b'v'; 300_000], "", 413, "too_large"),
    ];
    for (ct, body, query, status, code) in cases {
        let (got, got_code, v) = post(ct, body.clone(), query).await;
        assert_eq!(
            (got, got_code.as_str()),
            (status, code),
            "{ct} {:?}: {v}",
            String::from_utf8_lossy(&body[..body.len().min(60)])
        );
        assert!(!v["error"]["message"].as_str().unwrap_or("").is_empty());
    }
    let many: Vec<[f32; 3]> = (0..5001).map(|i| [i as f32, (i % 7) as f32, 0.5]).collect();
    let (status, code, _) =
        post(json, serde_json::to_vec(&json!({"points": many})).unwrap(), "").await;
    assert_eq!((status, code.as_str()), (422, "invalid_input"));

    // Garbage of every kind: never a crash, never a 5xx.
    let mut seed = 12345u64;
    for round in 0..200 {
        let len = (round * 37) % 3000;
        let bytes: Vec<u8> = (0..len)
            .map(|_| {
                seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (seed >> 56) as u8
            })
            .collect();
        let ct = [
            "application/json",
            "application/ply",
            "model/obj",
            "model/stl",
            "model/gltf-binary",
            "application/octet-stream",
            "text/plain",
        ][round % 7];
        let (status, _, _) = post(ct, bytes, "").await;
        assert!((400..500).contains(&status), "{ct}: {status}");
    }
    let r = c.get(server.url("/healthz")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert!(
        server.metric(&c, "meshstream_requests_rejected_total{reason=\"invalid_input\"}").await
            >= 1.0
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overload_gets_429_with_retry_after() {
    let server = Server::start(&["--max-running", "1", "--max-queue", "1", "--stream-buffer", "2"]);
    let body = points_json(&shape(), json!({"max_faces": 400}));
    // Two streams nobody reads on: one runs (stalled), one waits; the third is refused.
    let stream = || {
        client()
            .post(server.url("/reconstruct"))
            .header("accept", "application/x-ndjson")
            .json(&body)
            .send()
    };
    let mut running = stream().await.unwrap();
    assert_eq!(running.status(), 200);
    // Its first face shows it was admitted: without it, a loaded machine may still have it in
    // the queue when the next request arrives, and refuse that one instead.
    assert!(running.chunk().await.unwrap().is_some());
    let waiting = stream().await.unwrap();
    assert_eq!(waiting.status(), 200);
    let r = client().post(server.url("/reconstruct")).json(&body).send().await.unwrap();
    assert_eq!(r.status(), 429);
    assert!(r.headers().contains_key("retry-after"));
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["error"]["code"], "queue_full");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_lets_a_stream_finish_then_exits_0() {
    let mut server = Server::start(&["--shutdown-grace", "20"]);
    let last = stream_through(&server.http, || server.terminate()).await;
    assert_eq!(last["type"], "done", "{last}");
    // New requests are refused meanwhile or the port is closed; the process exits 0.
    assert_eq!(server.wait_exit(Duration::from_secs(10)), Some(0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_readiness_info_and_openapi() {
    let server = Server::start(&[]);
    let c = client();
    assert_eq!(c.get(server.url("/healthz")).send().await.unwrap().status(), 200);
    assert_eq!(c.get(server.url("/readyz")).send().await.unwrap().status(), 200);
    let info: Value = c.get(server.url("/v1/info")).send().await.unwrap().json().await.unwrap();
    assert!(info["model"]["parameters"].as_u64().unwrap() > 0);
    assert!(info["limits"]["max_faces"].as_u64().unwrap() > 0);
    let api: Value = c.get(server.url("/openapi.json")).send().await.unwrap().json().await.unwrap();
    assert!(api["paths"]["/reconstruct"]["post"].is_object());
    assert!(api["components"]["schemas"]["ErrorBody"].is_object());
    let r = c.get(server.url("/nope")).send().await.unwrap();
    assert_eq!(r.status(), 404);
}
