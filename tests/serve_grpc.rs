//! `meshstream serve` over gRPC: the real binary, a tonic client.

mod common;

use std::time::{Duration, Instant};

use common::{Server, points_json, points_request, shape};
use meshstream::mesh::{Format, ReadLimits, read_mesh, write_mesh};
use meshstream::metrics::topology;
use meshstream::server::proto::mesh_generator_client::MeshGeneratorClient;
use meshstream::server::proto::{
    MeshFile, Options, PointCloud, ReconstructRequest, reconstruct_request, reconstruct_response,
};
use serde_json::json;
use tonic::Code;

async fn client(server: &Server) -> MeshGeneratorClient<tonic::transport::Channel> {
    MeshGeneratorClient::connect(server.grpc.clone()).await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_stream_delivers_faces_incrementally_equal_to_the_http_mesh() {
    let server = Server::start(&[]);
    let mut grpc = client(&server).await;
    let mut stream = grpc.reconstruct(points_request(200)).await.unwrap().into_inner();
    let (mut faces, mut arrivals, mut stats) = (Vec::new(), Vec::new(), None);
    while let Some(message) = stream.message().await.unwrap() {
        match message.event.unwrap() {
            reconstruct_response::Event::Faces(chunk) => {
                arrivals.push(Instant::now());
                faces.extend(chunk.faces);
            }
            reconstruct_response::Event::Done(s) => stats = Some(s),
            reconstruct_response::Event::Progress(p) => panic!("progress {p:?} for points"),
            reconstruct_response::Event::Drafts(d) => panic!("drafts {d:?} not asked for"),
        }
    }
    let stats = stats.expect("a final stats message");
    assert_eq!(stats.faces as usize, faces.len());
    assert!(!stats.request_id.is_empty());

    // A whole mesh over HTTP defaults to several candidates, welded and fitted to the points;
    // the stream decoded one, as the model placed it.
    let as_decoded = json!({"max_faces": 200, "candidates": 1, "weld_radius": 0, "fit_rounds": 0});
    let body = points_json(&shape(), as_decoded);
    let r =
        reqwest::Client::new().post(server.url("/reconstruct")).json(&body).send().await.unwrap();
    let mesh = read_mesh(&r.bytes().await.unwrap(), Format::Gltf, &ReadLimits::default()).unwrap();
    assert_eq!(faces.len(), mesh.faces.len());
    // The stream's answer says how it is built, as counted on the same mesh here.
    let quality = stats.quality.expect("the answer measured");
    let built = topology(&mesh);
    assert_eq!(
        [quality.edges, quality.boundary_edges, quality.non_manifold_edges, quality.parts],
        [built.edges, built.boundary_edges, built.non_manifold_edges, built.parts]
            .map(|n| n as u32)
    );
    assert!(quality.input_chamfer.is_some_and(|d| d > 0.0 && d < 2.0), "{quality:?}");
    for (i, f) in faces.iter().enumerate() {
        assert_eq!(f.index as usize, i);
        let corners = mesh.faces[i].map(|v| mesh.vertices[v as usize]);
        for (a, b) in f.vertices.iter().zip(corners.iter().flatten()) {
            assert!((a - b).abs() < 1e-5);
        }
    }
    if faces.len() >= 20 {
        assert!(arrivals.len() > 1, "all faces came in one message");
        assert!(arrivals[arrivals.len() - 1] - arrivals[0] > Duration::from_millis(5));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn files_are_accepted_and_bad_input_is_invalid_argument() {
    let server = Server::start(&["--max-points", "5000"]);
    let mut grpc = client(&server).await;
    let ply =
        write_mesh(&meshstream::mesh::primitives::cuboid([1.0, 2.0, 1.0]), Format::Ply).unwrap();
    let file = |data: Vec<u8>, format: &str| ReconstructRequest {
        input: Some(reconstruct_request::Input::File(MeshFile { data, format: format.into() })),
        options: Some(Options { max_faces: Some(20), ..Options::default() }),
    };
    let mut ok = grpc.reconstruct(file(ply.clone(), "")).await.unwrap().into_inner();
    while ok.message().await.unwrap().is_some() {}
    // A file lying with +z up, said so.
    let z_up = ReconstructRequest {
        options: Some(Options { max_faces: Some(20), up: Some("z".into()), ..Options::default() }),
        ..file(ply.clone(), "ply")
    };
    let mut ok = grpc.reconstruct(z_up).await.unwrap().into_inner();
    while ok.message().await.unwrap().is_some() {}

    let bad = [
        file(b"garbage".to_vec(), ""),
        file(ply.clone(), "fbx"),
        file(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n".to_vec(), "ply"),
        ReconstructRequest { input: None, options: None },
        ReconstructRequest {
            input: Some(reconstruct_request::Input::Points(PointCloud {
                positions: vec![0.0, f32::NAN, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
                normals: vec![],
            })),
            options: None,
        },
        ReconstructRequest {
            input: Some(reconstruct_request::Input::Points(PointCloud {
                positions: vec![0.0; 7],
                normals: vec![],
            })),
            options: None,
        },
        ReconstructRequest {
            options: Some(Options { top_p: Some(3.0), ..Options::default() }),
            ..points_request(10)
        },
        ReconstructRequest {
            options: Some(Options { max_faces: Some(1_000_000), ..Options::default() }),
            ..points_request(10)
        },
        ReconstructRequest {
            options: Some(Options { face_beam: Some(0), ..Options::default() }),
            ..points_request(10)
        },
        ReconstructRequest {
            options: Some(Options { candidates: Some(17), ..Options::default() }),
            ..points_request(10)
        },
        ReconstructRequest {
            options: Some(Options { up: Some("sideways".into()), ..Options::default() }),
            ..points_request(10)
        },
        ReconstructRequest {
            options: Some(Options { max_hole_edges: Some(33), ..Options::default() }),
            ..points_request(10)
        },
        ReconstructRequest {
            options: Some(Options { hull_faces: Some(100_000), ..Options::default() }),
            ..points_request(10)
        },
    ];
    for (i, request) in bad.into_iter().enumerate() {
        let status = grpc.reconstruct(request).await.map(|_| ()).unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "case {i}: {status:?}");
        assert!(!status.message().is_empty());
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overload_is_resource_exhausted() {
    let server = Server::start(&["--max-running", "1", "--max-queue", "1", "--stream-buffer", "2"]);
    let mut grpc = client(&server).await;
    // Two streams nobody reads on: one runs (stalled), one waits; the third is refused.
    let mut a = grpc.reconstruct(points_request(400)).await.unwrap().into_inner();
    // Its first faces show it was admitted: without them, a loaded machine may still have it
    // in the queue when the next request arrives, and refuse that one instead.
    let first = a.message().await.unwrap().and_then(|m| m.event);
    assert!(matches!(first, Some(reconstruct_response::Event::Faces(_))), "{first:?}");
    let _b = grpc.reconstruct(points_request(400)).await.unwrap();
    let status = grpc.reconstruct(points_request(400)).await.map(|_| ()).unwrap_err();
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_and_reflection_answer() {
    use tonic_health::pb::HealthCheckRequest;
    use tonic_health::pb::health_client::HealthClient;
    use tonic_reflection::pb::v1::ServerReflectionRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;

    let server = Server::start(&[]);
    let channel = tonic::transport::Endpoint::from_shared(server.grpc.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = HealthClient::new(channel.clone());
    let service = "meshstream.v1.MeshGenerator".to_string();
    let r = health.check(HealthCheckRequest { service }).await.unwrap().into_inner();
    assert_eq!(r.status, 1, "SERVING");

    let mut reflection = ServerReflectionClient::new(channel);
    let request = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut responses = reflection
        .server_reflection_info(tokio_stream::iter([request]))
        .await
        .unwrap()
        .into_inner();
    let response = responses.message().await.unwrap().unwrap();
    let Some(MessageResponse::ListServicesResponse(list)) = response.message_response else {
        panic!("{response:?}");
    };
    let names: Vec<_> = list.service.iter().map(|s| s.name.as_str()).collect();
    assert!(names.contains(&"meshstream.v1.MeshGenerator"), "{names:?}");
    assert!(names.contains(&"grpc.health.v1.Health"), "{names:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drafts_come_before_a_whole_answer_that_they_leave_as_it_is() {
    let server = Server::start(&[]);
    let mut grpc = client(&server).await;
    // Faces and drafts of one request, in the order they came.
    async fn events(
        grpc: &mut MeshGeneratorClient<tonic::transport::Channel>,
        drafts: bool,
    ) -> (Vec<Vec<f32>>, Vec<Vec<f32>>) {
        let mut request = points_request(120);
        let options = request.options.as_mut().unwrap();
        (options.candidates, options.fit_rounds, options.drafts) =
            (Some(3), Some(20), Some(drafts));
        let mut stream = grpc.reconstruct(request).await.unwrap().into_inner();
        let (mut drafted, mut faces) = (Vec::new(), Vec::new());
        while let Some(message) = stream.message().await.unwrap() {
            match message.event.unwrap() {
                reconstruct_response::Event::Drafts(chunk) => {
                    assert!(faces.is_empty(), "a draft after the answer's faces");
                    drafted.extend(chunk.faces.into_iter().map(|f| f.vertices));
                }
                reconstruct_response::Event::Faces(chunk) => {
                    faces.extend(chunk.faces.into_iter().map(|f| f.vertices));
                }
                reconstruct_response::Event::Done(stats) => {
                    assert_eq!(stats.faces as usize, faces.len());
                }
                reconstruct_response::Event::Progress(p) => panic!("progress {p:?} for points"),
            }
        }
        (drafted, faces)
    }
    let (drafted, faces) = events(&mut grpc, true).await;
    let (none, answer) = events(&mut grpc, false).await;
    assert!(!drafted.is_empty() && none.is_empty());
    assert_eq!(faces, answer, "drafts leave the answer as it is");
}
