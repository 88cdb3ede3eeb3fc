//! Image requests against the real binary: `POST /generate` (raw and multipart, mesh and
//! streams) and gRPC `GenerateFromImage`, with an image model of random weights (the
//! plumbing, not the quality, is under test), and a server without an image model.

mod common;

use std::path::Path;

use common::Server;
use common::models::{model_that_ends_at_once, random_image_model};
use futures_util::StreamExt;
use meshstream::mesh::{Format, ReadLimits, read_mesh};
use meshstream::server::proto::mesh_generator_client::MeshGeneratorClient;
use meshstream::server::proto::{GenerateOptions, GenerateRequest, reconstruct_response};
use serde_json::Value;
use tonic::Code;

fn image_server(dir: &tempfile::TempDir) -> Server {
    random_image_model(dir.path());
    Server::start(&["--image-model", dir.path().to_str().unwrap(), "--max-image-side", "1024"])
}

fn png(width: u32, height: u32) -> Vec<u8> {
    let img = image::RgbaImage::from_fn(width, height, |x, y| {
        image::Rgba([(x % 256) as u8, (y % 256) as u8, 128, if x < 4 { 0 } else { 255 }])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// A `width` x `height` PNG of one colour: nothing on it to make a mesh of.
fn blank_png(width: u32, height: u32, colour: [u8; 4]) -> Vec<u8> {
    let img = image::RgbaImage::from_pixel(width, height, image::Rgba(colour));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// A valid 1 x 1 PNG whose header claims `width` x `height` (its CRC patched to match).
fn png_claiming(width: u32, height: u32) -> Vec<u8> {
    let mut png = png(1, 1);
    // Signature (8), IHDR length (4), "IHDR" (4), width, height, 5 more bytes, CRC.
    png[16..20].copy_from_slice(&width.to_be_bytes());
    png[20..24].copy_from_slice(&height.to_be_bytes());
    let mut crc = !0u32;
    for &b in &png[12..29] {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
        }
    }
    png[29..33].copy_from_slice(&(!crc).to_be_bytes());
    png
}

fn form(image: &[u8], fields: &[(&str, &str)]) -> reqwest::multipart::Form {
    let mut form = reqwest::multipart::Form::new().part(
        "image",
        reqwest::multipart::Part::bytes(image.to_vec())
            .file_name("a.png")
            .mime_str("image/png")
            .unwrap(),
    );
    for (name, value) in fields {
        form = form.text(name.to_string(), value.to_string());
    }
    form
}

/// The JSON events of an SSE or NDJSON response, in order.
async fn events(response: reqwest::Response, sse: bool) -> Vec<Value> {
    assert_eq!(response.status(), 200);
    let mut body = response.bytes_stream();
    let (mut buffer, mut out) = (String::new(), Vec::new());
    while let Some(chunk) = body.next().await {
        buffer.push_str(std::str::from_utf8(&chunk.unwrap()).unwrap());
        while let Some(end) = buffer.find('\n') {
            let line: String = buffer.drain(..=end).collect();
            let data =
                if sse { line.strip_prefix("data: ").map(str::trim) } else { Some(line.trim()) };
            if let Some(data) = data.filter(|d| !d.is_empty()) {
                out.push(serde_json::from_str(data).unwrap());
            }
        }
    }
    out
}

/// Progress events 1..=steps, then faces, then one final `done`.
fn check_order(events: &[Value], steps: u64) -> Vec<Value> {
    let progress: Vec<u64> = events
        .iter()
        .take_while(|e| e.get("step").is_some())
        .map(|e| e["step"].as_u64().unwrap())
        .collect();
    assert_eq!(progress, (1..=steps).collect::<Vec<_>>(), "{events:?}");
    assert!(events.iter().all(|e| e.get("steps").is_none_or(|s| s.as_u64() == Some(steps))));
    let rest = &events[progress.len()..];
    let (done, faces) = rest.split_last().unwrap();
    assert!(done.get("finish_reason").is_some(), "{done}");
    assert!(faces.iter().all(|f| f.get("vertices").is_some()));
    assert_eq!(done["faces"].as_u64().unwrap() as usize, faces.len());
    faces.to_vec()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_png_becomes_a_mesh_and_streams_progress_then_faces() {
    let dir = tempfile::tempdir().unwrap();
    let server = image_server(&dir);
    let client = reqwest::Client::new();
    let image = png(96, 64);
    let url = server.url("/generate?steps=3&max_faces=30&seed=5");
    let r = client
        .post(&url)
        .header("content-type", "image/png")
        .body(image.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let faces: usize = r.headers()["x-meshstream-faces"].to_str().unwrap().parse().unwrap();
    let mesh = read_mesh(&r.bytes().await.unwrap(), Format::Gltf, &ReadLimits::default()).unwrap();
    assert_eq!(mesh.faces.len(), faces);
    assert!(faces > 0 && faces <= 30);
    assert!(mesh.vertices.iter().flatten().all(|c| c.abs() <= 1.0 + 1e-4), "not in [-1, 1]");

    let sse = client.post(&url).header("accept", "text/event-stream").body(image.clone());
    let sse_faces = check_order(&events(sse.send().await.unwrap(), true).await, 3);
    // The same request as a multipart form, streamed as NDJSON: the same faces.
    let fields = [("steps", "3"), ("max_faces", "30"), ("seed", "5")];
    let nd = client
        .post(server.url("/generate"))
        .header("accept", "application/x-ndjson")
        .multipart(form(&image, &fields));
    let nd_events = events(nd.send().await.unwrap(), false).await;
    assert!(nd_events.iter().all(|e| e.get("type").is_some()));
    assert_eq!(check_order(&nd_events, 3).len(), sse_faces.len());
    assert_eq!(sse_faces.len(), faces);
    for (a, b) in sse_faces.iter().zip(&check_order(&nd_events, 3)) {
        assert_eq!(a["vertices"], b["vertices"]);
    }
    let info: Value =
        client.get(server.url("/v1/info")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["image_model"]["config"]["num_latents"], 128);
    assert_eq!(info["image_model"]["default_framing"], "object");
    let api: Value =
        client.get(server.url("/openapi.json")).send().await.unwrap().json().await.unwrap();
    assert!(api["paths"]["/generate"]["post"].is_object(), "{}", api["paths"]);
    let parameters = api["paths"]["/generate"]["post"]["parameters"].as_array().unwrap();
    assert!(parameters.iter().any(|p| p["name"] == "framing"), "{parameters:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_empty_mesh_is_sampled_again_then_answered_as_no_faces() {
    let (faces, images) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    model_that_ends_at_once(faces.path());
    random_image_model(images.path());
    let model = faces.path().to_str().unwrap();
    let image_model = images.path().to_str().unwrap();
    let server =
        Server::start_with_model(model, &["--image-model", image_model, "--image-attempts", "2"]);
    let client = reqwest::Client::new();
    let url = |format: &str| server.url(&format!("/generate?steps=2&format={format}"));
    // A whole mesh: no format holds an empty one usefully (glTF cannot), so a 422 that says so.
    for format in ["glb", "obj", "ply", "stl"] {
        let r = client.post(url(format)).header("content-type", "image/png").body(png(32, 32));
        let r = r.send().await.unwrap();
        assert_eq!(r.status(), 422, "{format}");
        let body: Value = r.json().await.unwrap();
        assert_eq!(body["error"]["code"], "no_faces", "{format}: {body}");
        assert!(body["error"]["message"].as_str().unwrap().contains("no faces"), "{body}");
    }
    // A stream shows both attempts' diffusion, then a done event with no faces.
    let sse = client.post(url("glb")).header("accept", "text/event-stream").body(png(32, 32));
    let events = events(sse.send().await.unwrap(), true).await;
    let steps: Vec<u64> = events.iter().filter_map(|e| e.get("step")?.as_u64()).collect();
    assert_eq!(steps, [1, 2, 1, 2], "{events:?}");
    let done = events.last().unwrap();
    assert_eq!(
        (done["faces"].as_u64(), done["finish_reason"].as_str()),
        (Some(0), Some("end_of_mesh"))
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_images_and_options_get_4xx_and_the_server_survives() {
    let dir = tempfile::tempdir().unwrap();
    let server = image_server(&dir);
    let client = reqwest::Client::new();
    let mut truncated = png(64, 64);
    truncated.truncate(truncated.len() / 2);
    let raw: [(&str, Vec<u8>, u16, &str); 7] = [
        ("not an image", b"hello, world".to_vec(), 400, "invalid_image"),
        ("empty", Vec::new(), 400, "invalid_image"),
        ("zero size", png_claiming(0, 64), 400, "invalid_image"),
        ("huge", png_claiming(100_000, 100_000), 400, "image_too_large"),
        ("over the side limit", png(1100, 8), 400, "image_too_large"),
        ("truncated", truncated, 400, "invalid_image"),
        ("a mesh", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".to_vec(), 400, "invalid_image"),
    ];
    for (what, body, status, code) in raw {
        let r = client.post(server.url("/generate")).body(body).send().await.unwrap();
        assert_eq!(r.status(), status, "{what}");
        let v: Value = r.json().await.unwrap();
        assert_eq!(v["error"]["code"], code, "{what}: {v}");
    }
    // Pictures with nothing on them: refused as having no object, unless the client asks for
    // the picture as it is.
    for (what, colour) in [("white", [255, 255, 255, 255]), ("transparent", [9, 9, 9, 0])] {
        let blank = blank_png(300, 200, colour);
        let r = client.post(server.url("/generate")).body(blank.clone()).send().await.unwrap();
        assert_eq!(r.status(), 422, "{what}");
        let v: Value = r.json().await.unwrap();
        assert_eq!(v["error"]["code"], "no_object", "{what}: {v}");
        assert!(v["error"]["message"].as_str().unwrap().contains("centre_crop"), "{v}");
        let as_given = "/generate?framing=centre_crop&steps=2&max_faces=5";
        let r = client.post(server.url(as_given)).body(blank).send().await.unwrap();
        assert_eq!(r.status(), 200, "{what} as given");
    }
    let image = png(32, 32);
    let cases = [
        ("/generate?steps=0", 422),
        ("/generate?steps=100000", 422),
        ("/generate?guidance=-1", 422),
        ("/generate?stepz=3", 422),
        ("/generate?format=fbx", 422),
        ("/generate?max_faces=0", 422),
        ("/generate?framing=tight", 422),
    ];
    for (url, status) in cases {
        let r = client.post(server.url(url)).body(image.clone()).send().await.unwrap();
        assert_eq!(r.status(), status, "{url}");
    }
    let text = client.post(server.url("/generate")).header("content-type", "text/plain");
    assert_eq!(text.body(image.clone()).send().await.unwrap().status(), 400);
    let no_image = reqwest::multipart::Form::new().text("steps", "2");
    let r = client.post(server.url("/generate")).multipart(no_image).send().await.unwrap();
    assert_eq!(r.status(), 422);
    // Random bytes of every length never take the server down.
    for n in 0..40usize {
        let body: Vec<u8> = (0..n * 7).map(|i| (i * 31 + n) as u8).collect();
        let r = client.post(server.url("/generate")).body(body).send().await.unwrap();
        assert!(r.status().is_client_error(), "{n}: {}", r.status());
    }
    assert_eq!(client.get(server.url("/healthz")).send().await.unwrap().status(), 200);
    let r =
        client.post(server.url("/generate?steps=2&max_faces=5")).body(image).send().await.unwrap();
    assert_eq!(r.status(), 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_streams_progress_then_faces_and_refuses_bad_images() {
    let dir = tempfile::tempdir().unwrap();
    let server = image_server(&dir);
    let mut grpc = MeshGeneratorClient::connect(server.grpc.clone()).await.unwrap();
    let request = |image: Vec<u8>| GenerateRequest {
        image,
        options: Some(GenerateOptions {
            steps: Some(4),
            max_faces: Some(20),
            ..Default::default()
        }),
    };
    let mut stream = grpc.generate_from_image(request(png(40, 40))).await.unwrap().into_inner();
    let (mut steps, mut faces, mut done) = (Vec::new(), 0, None);
    while let Some(message) = stream.message().await.unwrap() {
        match message.event.unwrap() {
            reconstruct_response::Event::Progress(p) => {
                assert_eq!((faces, p.steps), (0, 4), "progress after faces");
                steps.push(p.step);
            }
            reconstruct_response::Event::Faces(chunk) => faces += chunk.faces.len(),
            reconstruct_response::Event::Done(stats) => done = Some(stats),
            reconstruct_response::Event::Drafts(d) => panic!("drafts {d:?} of an image request"),
        }
    }
    assert!(steps.windows(2).all(|w| w[0] < w[1]) && steps.last() == Some(&4), "{steps:?}");
    assert_eq!(done.unwrap().faces as usize, faces);
    for bad in [b"garbage".to_vec(), Vec::new(), png_claiming(0, 5), png_claiming(70_000, 70_000)] {
        let status = grpc.generate_from_image(request(bad)).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    }
    let blank = grpc.generate_from_image(request(blank_png(40, 40, [255; 4]))).await.unwrap_err();
    assert_eq!(blank.code(), Code::InvalidArgument, "{blank:?}");
    assert!(blank.message().contains("no object"), "{blank:?}");
    let mut framed = request(png(40, 40));
    framed.options.as_mut().unwrap().framing = Some("tight".into());
    let status = grpc.generate_from_image(framed).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(status.message().contains("centre_crop"), "{status:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_without_an_image_model_says_so() {
    // The face model alone, without the shipped dit/ folder.
    let dir = tempfile::tempdir().unwrap();
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default");
    for file in ["config.json", "model.safetensors"] {
        std::fs::copy(model.join(file), dir.path().join(file)).unwrap();
    }
    let server = Server::start_with_model(dir.path().to_str().unwrap(), &[]);
    let r =
        reqwest::Client::new().post(server.url("/generate")).body(png(8, 8)).send().await.unwrap();
    assert_eq!(r.status(), 501);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["error"]["code"], "unsupported");
    let mut grpc = MeshGeneratorClient::connect(server.grpc.clone()).await.unwrap();
    let status = grpc
        .generate_from_image(GenerateRequest { image: png(8, 8), options: None })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::Unimplemented);
}
