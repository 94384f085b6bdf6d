//! Helpers shared by the integration tests that talk to a live server.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use mrptv::client::{self, Rate, RecordingSource, ReplayOptions, ReplayReport};
use mrptv::offline;
use mrptv::protocol::{
    decode_batch, encode_frame, DecodedBatch, Encoding, ErrorCode, FrameMessage, ServerMessage,
};
use mrptv::recording::Recording;
use mrptv::server::{self, ServerOptions};
use mrptv_engine::synth::{Scenario, ScenarioSpec};
use mrptv_engine::PipelineConfig;
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio_tungstenite::tungstenite::Message;

pub struct TestServer {
    pub addr: std::net::SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<std::io::Result<server::ShutdownReport>>,
}

impl TestServer {
    pub async fn start(options: ServerOptions) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("port 0");
        let addr = listener.local_addr().expect("addr");
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(server::run(listener, options, async {
            let _ = stopped.await;
        }));
        Self {
            addr,
            stop: Some(stop),
            task,
        }
    }

    pub fn ingest(&self) -> String {
        format!("ws://{}/v1/ingest", self.addr)
    }

    pub fn watch(&self) -> String {
        format!("ws://{}/v1/watch", self.addr)
    }

    /// Asks the server to shut down and waits until it has, cleanly: every connection closed.
    pub async fn stop(mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        let report = tokio::time::timeout(Duration::from_secs(20), self.task)
            .await
            .expect("server stops within 20 s")
            .expect("server task")
            .expect("server ran");
        assert_eq!(report.connections_dropped, 0, "a clean shutdown");
    }
}

/// A synthetic recording and the config it is processed with (the defaults: `synth` writes none).
pub fn synth(dir: &Path, scenario: Scenario, frames: usize) -> (Recording, PipelineConfig) {
    let spec = ScenarioSpec::new(scenario);
    let config = PipelineConfig::default();
    let particles = spec.default_particles;
    offline::write_synthetic(spec, dir, frames, particles, 3, |_| {}).expect("synth");
    (Recording::open(dir).expect("recording"), config)
}

pub fn replay_options(url: String, config: &PipelineConfig) -> ReplayOptions {
    ReplayOptions {
        rate: Rate::Max,
        config: Some(config.clone()),
        finish_timeout: Duration::from_secs(60),
        ..ReplayOptions::new(url)
    }
}

pub async fn replay(rec: &Recording, options: &ReplayOptions) -> ReplayReport {
    let source = RecordingSource::new(rec.clone(), options.encoding);
    tokio::time::timeout(
        Duration::from_secs(120),
        client::replay(source, options, std::future::pending(), |_| {}),
    )
    .await
    .expect("replay finishes")
    .expect("replay succeeds")
}

/// Replays `rec` in the background.
pub fn spawn_replay(
    rec: &Recording,
    options: ReplayOptions,
) -> tokio::task::JoinHandle<ReplayReport> {
    let rec = rec.clone();
    tokio::spawn(async move { replay(&rec, &options).await })
}

pub fn the_only_subdir(dir: &Path) -> PathBuf {
    let dirs: Vec<PathBuf> = std::fs::read_dir(dir)
        .expect("record dir")
        .map(|e| e.expect("entry").path())
        .collect();
    assert_eq!(dirs.len(), 1, "one recorded session: {dirs:?}");
    dirs.into_iter().next().expect("one")
}
pub type Socket =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

pub async fn connect(url: &str) -> Socket {
    tokio_tungstenite::connect_async(url)
        .await
        .expect("connects")
        .0
}

/// The next text message, skipping binary ones and status reports.
pub async fn next_text(ws: &mut Socket) -> ServerMessage {
    loop {
        let m = tokio::time::timeout(Duration::from_secs(20), ws.next())
            .await
            .expect("a message within 20 s")
            .expect("open")
            .expect("readable");
        if let Message::Text(t) = m {
            let parsed: ServerMessage = serde_json::from_str(t.as_str()).expect("server JSON");
            if !matches!(parsed, ServerMessage::Status { .. }) {
                return parsed;
            }
        }
    }
}

pub async fn next_binary(ws: &mut Socket) -> DecodedBatch {
    loop {
        let m = tokio::time::timeout(Duration::from_secs(20), ws.next())
            .await
            .expect("a message within 20 s")
            .expect("open")
            .expect("readable");
        match m {
            Message::Binary(b) => return decode_batch(&b).expect("a batch"),
            Message::Text(t) => {
                let parsed: ServerMessage = serde_json::from_str(t.as_str()).expect("JSON");
                // Status reports and mean-flow fields come between batches.
                assert!(
                    matches!(
                        parsed,
                        ServerMessage::Status { .. } | ServerMessage::Field(_)
                    ),
                    "unexpected {parsed:?}"
                );
            }
            _ => {}
        }
    }
}

pub async fn expect_error(ws: &mut Socket, send: Message, code: ErrorCode) -> String {
    ws.send(send).await.expect("sends");
    match next_text(ws).await {
        ServerMessage::Error {
            code: got, message, ..
        } => {
            assert_eq!(got, code, "{message}");
            assert!(
                message.len() > 10,
                "a message a person can act on: {message:?}"
            );
            message
        }
        other => panic!("expected {code:?}, got {other:?}"),
    }
}

pub fn hello(rec: &Recording, edit: impl FnOnce(&mut serde_json::Value)) -> Message {
    let mut v = serde_json::json!({
        "type": "hello", "protocol": 1, "client": "bad-message test",
        "rig": rec.rig.to_file(),
        "image": {"width": rec.rig.width, "height": rec.rig.height, "encoding": "raw8"},
    });
    edit(&mut v);
    Message::text(v.to_string())
}

pub fn frame(index: u64, t_s: f64, encoding: Encoding, left: &[u8], right: &[u8]) -> Message {
    Message::binary(
        encode_frame(&FrameMessage {
            encoding,
            frame_index: index,
            t_s,
            world_from_rig: None,
            left,
            right,
        })
        .expect("encodes"),
    )
}

/// A minimal HTTP/1.1 GET with extra header lines: the status code and the body.
pub async fn http_request(url: &str, headers: &str) -> (u16, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let rest = url.strip_prefix("http://").expect("http URL");
    let (host, path) = rest.split_at(rest.find('/').expect("path"));
    let mut tcp = tokio::net::TcpStream::connect(host)
        .await
        .expect("connects");
    let request =
        format!("GET {path} HTTP/1.1\r\nHost: {host}\r\n{headers}Connection: close\r\n\r\n");
    tcp.write_all(request.as_bytes()).await.expect("writes");
    let mut response = Vec::new();
    tcp.read_to_end(&mut response).await.expect("reads");
    let response = String::from_utf8_lossy(&response).into_owned();
    let status = response
        .split(' ')
        .nth(1)
        .and_then(|code| code.parse().ok())
        .unwrap_or_else(|| panic!("an HTTP response: {response:?}"));
    let body = response
        .split_once("\r\n\r\n")
        .map(|(_, body)| body.to_string())
        .unwrap_or_default();
    (status, body)
}

/// A minimal HTTP/1.1 GET: the body of a 200.
pub async fn http_get(url: &str) -> String {
    let (status, body) = http_request(url, "").await;
    assert_eq!(status, 200, "{url}: {body}");
    body
}

/// A running `mrptv serve`, stopped when dropped.
pub struct ServeProcess {
    pub child: Child,
    /// `http://127.0.0.1:PORT` or `https://...`
    pub base: String,
    /// Everything it printed before "Ctrl-C to stop."
    pub banner: String,
}

impl ServeProcess {
    pub fn start(args: &[&str]) -> ServeProcess {
        Self::start_with_env(args, &[])
    }

    pub fn start_with_env(args: &[&str], env: &[(&str, &str)]) -> ServeProcess {
        let mut child = Command::new(env!("CARGO_BIN_EXE_mrptv"))
            .args(["serve", "--bind", "127.0.0.1:0"])
            .args(args)
            .env("RUST_LOG", "warn")
            .env_remove("MRPTV_INGEST_SECRET")
            .env_remove("MRPTV_WATCH_SECRET")
            .envs(env.iter().copied())
            .stdout(Stdio::piped())
            .spawn()
            .expect("mrptv serve starts");
        let stdout = child.stdout.take().expect("stdout");
        let mut lines = BufReader::new(stdout).lines();
        let mut banner = String::new();
        let mut base = None;
        for line in lines.by_ref() {
            let line = line.expect("serve's stdout");
            if let Some(url) = line.split("listening on ").nth(1) {
                base = Some(url.trim().to_string());
            }
            banner.push_str(&line);
            banner.push('\n');
            if line.starts_with("Ctrl-C") {
                break;
            }
        }
        // Keep draining its output so it never blocks on a full pipe.
        std::thread::spawn(move || for _ in lines {});
        let base = base.unwrap_or_else(|| panic!("no listening address in:\n{banner}"));
        ServeProcess {
            child,
            base,
            banner,
        }
    }
}

impl Drop for ServeProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `rerun rrd verify` accepts the file (its exit code alone is not enough: a non-rrd file gives
/// 0 with "0 files verified").
pub fn assert_rrd_verified(rrd: &Path) {
    let out = Command::new("rerun")
        .args(["rrd", "verify"])
        .arg(rrd)
        .output()
        .expect("the rerun CLI runs (pip install -r tests/python/requirements.txt)");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        out.status.success() && text.contains("1 file verified"),
        "rerun rrd verify {}: {text}",
        rrd.display()
    );
}
