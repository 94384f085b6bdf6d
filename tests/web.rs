//! The observer page (`web/`) in a real browser and the server's TLS, end to end:
//! - `web/tests/e2e.mjs` (Playwright driving Debian's Chromium) against a real
//!   `mrptv serve --demo`, over HTTP with the WebXR emulation runtime, and over HTTPS with a
//!   generated self-signed certificate;
//! - the page's unit tests (`node --test`) and the check that the vendored three.js is the
//!   pinned npm package;
//! - a headset (`mrptv replay`) over WSS, trusting the server's certificate and refused without.
//!
//! Needs Node.js, `npm ci --prefix web` and Chromium (`/usr/bin/chromium` or MRPTV_CHROMIUM);
//! a missing one fails the test with what to install. Screenshots and the measured figures go
//! to `web/test-artifacts/`.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Mutex;
use std::time::Duration;

mod common;
use common::ServeProcess as Server;

/// One browser at a time: two software-rendered pages on two cores would starve the demo.
static BROWSER: Mutex<()> = Mutex::new(());

fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn web() -> PathBuf {
    repo().join("web")
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf8 path")
}

/// Fails with what to install when the browser-test tools are missing.
fn require_tools() {
    let node = Command::new("node").arg("--version").output();
    assert!(
        node.is_ok_and(|o| o.status.success()),
        "node not found: install Node.js (Debian: apt-get install nodejs npm)"
    );
    assert!(
        web().join("node_modules/playwright-core").is_dir(),
        "web/node_modules missing: run `npm ci --prefix web`"
    );
    let chromium = std::env::var("MRPTV_CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    assert!(
        Path::new(&chromium).is_file(),
        "{chromium} not found: install Chromium (Debian: apt-get install chromium) or set MRPTV_CHROMIUM"
    );
}

fn node(args: &[&str]) -> Output {
    Command::new("node")
        .args(args)
        .current_dir(web())
        .output()
        .expect("node runs")
}

fn assert_success(what: &str, out: &Output) {
    assert!(
        out.status.success(),
        "{what} failed:\n--- stdout\n{}\n--- stderr\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Secrets the TLS tests run with, as a field deployment would.
const INGEST_SECRET: &str = "headset-secret-for-tests";
const WATCH_SECRET: &str = "viewer-secret-for-tests";

fn artifacts() -> PathBuf {
    let dir = web().join("test-artifacts");
    std::fs::create_dir_all(&dir).expect("artifacts dir");
    dir
}

fn e2e(url: &str, extra: &[&str]) -> String {
    let artifacts = artifacts();
    let mut args = vec!["tests/e2e.mjs", "--url", url, "--artifacts", s(&artifacts)];
    args.extend_from_slice(extra);
    let out = node(&args);
    assert_success("web/tests/e2e.mjs", &out);
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn the_page_shows_live_arrows_in_chromium_flat_and_in_emulated_webxr() {
    require_tools();
    let _one_browser = BROWSER.lock().unwrap_or_else(|e| e.into_inner());
    let server = Server::start(&["--demo"]);
    assert!(server.banner.contains("observers: open http://127.0.0.1:"));
    let report = e2e(&format!("{}/", server.base), &[]);
    println!("{report}");
    assert!(artifacts().join("page.png").is_file());
    assert!(artifacts().join("xr-vr.png").is_file());
}

#[test]
fn the_page_works_over_https_with_a_generated_certificate_and_a_viewers_secret() {
    require_tools();
    let tls_dir = tempfile::tempdir().expect("tmp");
    let _one_browser = BROWSER.lock().unwrap_or_else(|e| e.into_inner());
    let server = Server::start_with_env(
        &["--demo", "--tls", "--tls-dir", s(tls_dir.path())],
        &[
            ("MRPTV_INGEST_SECRET", INGEST_SECRET),
            ("MRPTV_WATCH_SECRET", WATCH_SECRET),
        ],
    );
    assert!(
        server.banner.contains("/?token=WATCH_SECRET in a browser")
            && !server.banner.contains(WATCH_SECRET)
            && !server.banner.contains(INGEST_SECRET),
        "the banner says a token is needed without printing it:\n{}",
        server.banner
    );
    assert!(
        server.base.starts_with("https://127.0.0.1:"),
        "{}",
        server.banner
    );
    assert!(
        server
            .banner
            .contains("TLS: generated a self-signed certificate"),
        "{}",
        server.banner
    );
    assert!(server.banner.contains("SHA-256 fingerprint "));
    assert!(tls_dir.path().join("cert.pem").is_file());
    // The demo headset got in with the ingest secret; the page with the watch secret.
    let report = e2e(
        &format!("{}/?token={WATCH_SECRET}", server.base),
        &["--flat-only"],
    );
    println!("{report}");
    assert!(report.contains("\"subscribed\":\"s1\""), "{report}");
    assert!(report.contains("needs the viewers' secret"), "{report}");

    // No plaintext fallback on a TLS port.
    let addr = server.base.trim_start_matches("https://");
    let mut tcp = std::net::TcpStream::connect(addr).expect("connect");
    tcp.set_read_timeout(Some(Duration::from_secs(5)))
        .expect("timeout");
    tcp.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        .expect("write");
    let mut answer = Vec::new();
    let _ = tcp.read_to_end(&mut answer);
    assert!(
        !String::from_utf8_lossy(&answer).contains("HTTP/1.1 200"),
        "plain HTTP answered on the TLS port"
    );
}

#[test]
fn a_headset_streams_over_wss_trusting_the_servers_certificate_with_its_secret() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = dir.path().join("rec");
    let synth = Command::new(env!("CARGO_BIN_EXE_mrptv"))
        .args(["synth", "flume", s(&rec), "--frames", "20", "--seed", "5"])
        .output()
        .expect("synth runs");
    assert_success("mrptv synth", &synth);
    let tls_dir = dir.path().join("tls");
    let server = Server::start_with_env(
        &["--tls", "--tls-dir", s(&tls_dir)],
        &[("MRPTV_INGEST_SECRET", INGEST_SECRET)],
    );
    let url = format!("{}/v1/ingest", server.base.replace("https://", "wss://"));
    let replay = |extra: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_mrptv"))
            .args(["replay", s(&rec), "--url", &url, "--rate", "max", "--json"])
            .args(extra)
            .env_remove("MRPTV_INGEST_SECRET")
            .output()
            .expect("replay runs")
    };
    // Without trusting the self-signed certificate the connection is refused: verification is on.
    let untrusted = replay(&[]);
    assert!(!untrusted.status.success());
    let stderr = String::from_utf8_lossy(&untrusted.stderr);
    assert!(
        stderr.contains("cannot connect") && stderr.contains("certificate"),
        "{stderr}"
    );
    let cert = tls_dir.join("cert.pem");
    // Trusted, but without the ingest secret: refused before any frame, and told why.
    let anonymous = replay(&["--ca-cert", s(&cert)]);
    assert!(!anonymous.status.success());
    let stderr = String::from_utf8_lossy(&anonymous.stderr);
    assert!(
        stderr.contains("Unauthorized") && stderr.contains("requires a secret for headsets"),
        "{stderr}"
    );
    let wrong = replay(&["--ca-cert", s(&cert), "--secret", "not-the-secret-at-all"]);
    assert!(String::from_utf8_lossy(&wrong.stderr).contains("wrong secret"));
    let trusted = replay(&["--ca-cert", s(&cert), "--secret", INGEST_SECRET]);
    assert_success("mrptv replay over wss", &trusted);
    let summary: serde_json::Value =
        serde_json::from_slice(&trusted.stdout).expect("replay --json prints JSON");
    assert_eq!(summary["frames_sent"], 20, "{summary}");
    assert_eq!(summary["frames_processed"], 20, "{summary}");
    assert_eq!(summary["frames_rejected"], 0, "{summary}");
    assert!(summary["causal_vectors"].as_u64() > Some(100), "{summary}");
}

#[test]
fn page_unit_tests_pass_and_vendored_three_is_the_pinned_package() {
    require_tools();
    let unit = node(&["--test", "tests/unit.test.mjs"]);
    assert_success("node --test web/tests/unit.test.mjs", &unit);
    let vendored = node(&["scripts/vendor.mjs", "--check"]);
    assert_success("web/scripts/vendor.mjs --check", &vendored);
    let json = |path: PathBuf| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(&path).expect("readable")).expect("JSON")
    };
    let pinned = json(web().join("package.json"));
    let vendored = json(web().join("vendor/three/package.json"));
    assert_eq!(
        pinned["devDependencies"]["three"], vendored["version"],
        "web/package.json pins the vendored three"
    );
}
