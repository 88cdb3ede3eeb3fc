//! The viewer page of `meshstream serve`: served (or not, with `--no-ui`), and used in a real
//! browser by web/tests/viewer.spec.mjs, driven by puppeteer-core from web/node_modules: Debian's
//! chromium, and Firefox ESR on a virtual display (xvfb-run). Without those, a browser test says
//! so and passes, except where MESHSTREAM_REQUIRE_BROWSER=1 (CI), where it fails.

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
    // The Draco decoder, as WebAssembly (browsers compile it streaming only with this type).
    let wasm = get("/ui/draco/draco_decoder.wasm").await.unwrap();
    assert_eq!(wasm.headers()["content-type"], "application/wasm");
    assert!(wasm.bytes().await.unwrap().starts_with(b"\0asm"));
    assert_eq!(get("/ui/nothing.js").await.unwrap().status(), 404);
    drop(server);

    let server = Server::start(&["--no-ui"]);
    let page = client().get(server.url("/")).send().await.unwrap();
    assert_eq!(page.status(), 404);
    assert_eq!(client().get(server.url("/ui/app.js")).send().await.unwrap().status(), 404);
    assert_eq!(client().get(server.url("/healthz")).send().await.unwrap().status(), 200);
}

/// A browser the page is tested in.
#[derive(Clone, Copy)]
enum Browser {
    Chromium,
    Firefox,
}

impl Browser {
    fn name(self) -> &'static str {
        match self {
            Browser::Chromium => "chromium",
            Browser::Firefox => "firefox",
        }
    }

    /// Its executable: the spec's variable for it, the variable that overrides it, the default.
    fn executable(self) -> (&'static str, PathBuf) {
        let (variable, default) = match self {
            Browser::Chromium => ("CHROMIUM", "/usr/bin/chromium"),
            Browser::Firefox => ("FIREFOX", "/usr/bin/firefox-esr"),
        };
        let path =
            std::env::var(format!("MESHSTREAM_{variable}")).unwrap_or_else(|_| default.into());
        (variable, PathBuf::from(path))
    }

    /// The command that runs the spec: Firefox draws WebGL only on a display.
    fn spec_command(self) -> Command {
        match self {
            Browser::Chromium => Command::new("node"),
            Browser::Firefox => {
                let mut command = Command::new("xvfb-run");
                command.args(["--auto-servernum", "node"]);
                command
            }
        }
    }
}

/// Why the browser test cannot run here, if it cannot.
fn missing_tool(browser: Browser, web: &Path) -> Option<String> {
    let (_, executable) = browser.executable();
    if !executable.exists() {
        let package = match browser {
            Browser::Chromium => "chromium",
            Browser::Firefox => "firefox-esr",
        };
        return Some(format!("no {} (apt-get install {package})", executable.display()));
    }
    if !web.join("node_modules/puppeteer-core").exists() {
        return Some("no web/node_modules/puppeteer-core (npm ci in web/)".into());
    }
    if Command::new("node").arg("--version").output().is_err() {
        return Some("no node".into());
    }
    if matches!(browser, Browser::Firefox)
        && Command::new("xvfb-run").arg("--help").output().is_err()
    {
        return Some("no xvfb-run (apt-get install xvfb xauth)".into());
    }
    None
}

/// The spec in `browser` against a fresh server; then the files the page made hold the faces
/// the server streamed.
fn page_works_in(browser: Browser) {
    let web = Path::new(env!("CARGO_MANIFEST_DIR")).join("web");
    if let Some(why) = missing_tool(browser, &web) {
        if std::env::var("MESHSTREAM_REQUIRE_BROWSER").is_ok_and(|v| v == "1") {
            panic!("MESHSTREAM_REQUIRE_BROWSER=1 but {why}");
        }
        eprintln!("skipped: the {} test cannot run here: {why}", browser.name());
        return;
    }
    let artifacts = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("target/web-viewer-artifacts")
        .join(browser.name());
    let _ = std::fs::remove_dir_all(&artifacts);
    // A small buffer, so that a cancelled sequence cannot run far ahead of the page.
    let server = Server::start(&["--stream-buffer", "4"]);
    let (variable, executable) = browser.executable();
    let status = browser
        .spec_command()
        .arg(web.join("tests/viewer.spec.mjs"))
        .env("MESHSTREAM_URL", &server.http)
        .env("ARTIFACTS", &artifacts)
        .env("BROWSER", browser.name())
        .env(variable, &executable)
        .status()
        .unwrap();
    assert!(status.success(), "the {} test failed; see {}", browser.name(), artifacts.display());

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

#[test]
fn the_page_streams_faces_cancels_downloads_and_shows_errors_in_chromium() {
    page_works_in(Browser::Chromium);
}

#[test]
fn the_page_streams_faces_cancels_downloads_and_shows_errors_in_firefox() {
    page_works_in(Browser::Firefox);
}
