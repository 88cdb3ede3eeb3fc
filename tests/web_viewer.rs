//! The viewer page of `meshstream serve`: served (or not, with `--no-ui`), and used in a real
//! browser by web/tests/viewer.spec.mjs (Debian's chromium, driven by playwright-core from
//! web/node_modules). Without those, the browser test says so and passes, except where
//! MESHSTREAM_REQUIRE_BROWSER=1 (CI), where it fails.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::Server;
use meshstream::mesh::{Format, ReadLimits, read_mesh};

fn client() -> reqwest::Client {
    reqwest::Client::new()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_and_its_files_are_served_and_no_ui_turns_them_off() {
    let server = Server::start(&[]);
    let c = client();
    let get = |path: &str| c.get(server.url(path)).send();
    let page = get("/").await.unwrap();
    assert_eq!(page.status(), 200);
    assert_eq!(page.headers()["content-type"], "text/html; charset=utf-8");
    assert!(page.text().await.unwrap().contains("/ui/app.js"));
    let script = get("/ui/app.js").await.unwrap();
    assert_eq!(script.status(), 200);
    assert!(script.headers()["content-type"].to_str().unwrap().starts_with("text/javascript"));
    let example = get("/ui/examples/mug-points.ply").await.unwrap().bytes().await.unwrap();
    let points = read_mesh(&example, Format::Ply, &ReadLimits::default()).unwrap();
    assert_eq!(points.vertices.len(), 2048);
    assert_eq!(get("/ui/nothing.js").await.unwrap().status(), 404);
    drop(server);

    let server = Server::start(&["--no-ui"]);
    let page = client().get(server.url("/")).send().await.unwrap();
    assert_eq!(page.status(), 404);
    assert_eq!(client().get(server.url("/ui/app.js")).send().await.unwrap().status(), 404);
    assert_eq!(client().get(server.url("/healthz")).send().await.unwrap().status(), 200);
}

/// What the browser test needs, or why it cannot run here.
fn browser_tools(web: &Path) -> Result<PathBuf, String> {
    let chromium = PathBuf::from(
        std::env::var("MESHSTREAM_CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into()),
    );
    if !chromium.exists() {
        return Err(format!("no {} (apt-get install chromium)", chromium.display()));
    }
    if !web.join("node_modules/playwright-core").exists() {
        return Err("no web/node_modules/playwright-core (npm ci in web/)".into());
    }
    if Command::new("node").arg("--version").output().is_err() {
        return Err("no node".into());
    }
    Ok(chromium)
}

#[test]
fn the_page_streams_faces_cancels_downloads_and_shows_errors_in_a_browser() {
    let web = Path::new(env!("CARGO_MANIFEST_DIR")).join("web");
    let chromium = match browser_tools(&web) {
        Ok(chromium) => chromium,
        Err(why) if std::env::var("MESHSTREAM_REQUIRE_BROWSER").is_ok_and(|v| v == "1") => {
            panic!("MESHSTREAM_REQUIRE_BROWSER=1 but {why}")
        }
        Err(why) => {
            eprintln!("skipped: the browser test cannot run here: {why}");
            return;
        }
    };
    let artifacts = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/web-viewer-artifacts");
    let _ = std::fs::remove_dir_all(&artifacts);
    // A small buffer, so that a cancelled sequence cannot run far ahead of the page.
    let server = Server::start(&["--stream-buffer", "4"]);
    let status = Command::new("node")
        .arg(web.join("tests/viewer.spec.mjs"))
        .env("MESHSTREAM_URL", &server.http)
        .env("ARTIFACTS", &artifacts)
        .env("CHROMIUM", &chromium)
        .status()
        .unwrap();
    assert!(status.success(), "the browser test failed; see {}", artifacts.display());

    // The files the page made hold the faces the server streamed.
    let seen: serde_json::Value =
        serde_json::from_slice(&std::fs::read(artifacts.join("result.json")).unwrap()).unwrap();
    for format in [Format::Gltf, Format::Obj, Format::Ply, Format::Stl] {
        let file = artifacts.join(format!("result.{}", format.extension()));
        let bytes = std::fs::read(&file).unwrap();
        let mesh = read_mesh(&bytes, format, &ReadLimits::default())
            .unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        assert_eq!(mesh.faces.len() as u64, seen["done_faces"].as_u64().unwrap(), "{seen}");
    }
}
