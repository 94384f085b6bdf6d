//! `mrptv load`: a bounded load test of `mrptv serve` on this machine. It starts a server as a
//! child process on 127.0.0.1 (never anything beyond loopback), drives N synthetic headsets and
//! M viewers at it for a fixed time or frame count, samples the server's memory from `/proc`,
//! stops it with SIGTERM and reports what it measured.
//!
//! The headsets send a ring of pre-rendered frames, so rendering costs nothing during the run
//! and the client side of this machine's two cores is mostly socket work. Their frame indices
//! and timestamps keep counting up across laps (tracks jump at each lap: a load test does not
//! measure accuracy).

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use serde::Serialize;
use thiserror::Error;
use tokio_tungstenite::tungstenite::Message;

use crate::client::{self, ClientError, FrameSource, Rate, ReplayOptions, SourceFrame};
use crate::protocol::Encoding;
use mrptv_engine::geometry::StereoRig;
use mrptv_engine::synth::{Scenario, ScenarioSpec, Synthesizer};

#[derive(Debug, Clone)]
pub struct LoadOptions {
    pub headsets: usize,
    pub viewers: usize,
    /// The run ends after this, or once every headset has sent `frames_per_headset`.
    pub duration: Duration,
    pub frames_per_headset: Option<u64>,
    pub rate: Rate,
    pub scenario: Scenario,
    /// Frames rendered once and sent in a loop.
    pub ring_frames: usize,
    /// The `mrptv` binary to run as the server.
    pub server_exe: PathBuf,
    /// Extra `serve` arguments (limits are raised to fit the load already).
    pub server_args: Vec<String>,
}

#[derive(Debug, Error)]
pub enum LoadError {
    #[error("cannot start the server {exe}: {error}")]
    Spawn { exe: String, error: std::io::Error },
    #[error("the server did not say where it listens; it printed:\n{0}")]
    NoAddress(String),
    #[error("headset {0}: {1}")]
    Headset(usize, ClientError),
    #[error("viewer {0}: {1}")]
    Viewer(usize, String),
}

/// What a run measured. Memory is the server process's, from `/proc/PID/status`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LoadReport {
    pub headsets: usize,
    pub viewers: usize,
    pub seconds: f64,
    pub frames_sent: u64,
    pub frames_processed: u64,
    pub frames_dropped: u64,
    pub frames_rejected: u64,
    pub frames_per_second: f64,
    /// Frame sent -> its causal batch back, over every headset, milliseconds.
    pub latency_ms_p50: Option<f64>,
    pub latency_ms_p90: Option<f64>,
    pub latency_ms_p99: Option<f64>,
    pub latency_ms_max: Option<f64>,
    /// Batches the headsets received (causal and refined): what viewers should see.
    pub batches_published: u64,
    /// Per viewer: the fewest and the mean batches received.
    pub viewer_batches_min: u64,
    pub viewer_batches_mean: f64,
    /// Server resident memory once it was up, at the end of the load, and its peak (VmHWM).
    pub rss_start_mib: f64,
    pub rss_end_mib: f64,
    pub rss_peak_mib: f64,
    /// The server exited cleanly on SIGTERM.
    pub clean_exit: bool,
}

/// A ring of frames, sent in laps with indices and timestamps that keep increasing.
struct LoopedSource {
    rig: StereoRig,
    ring: Arc<Vec<SourceFrame>>,
    interval_s: f64,
    next: u64,
    limit: Option<u64>,
}

impl FrameSource for LoopedSource {
    fn rig(&self) -> &StereoRig {
        &self.rig
    }

    fn next_frame(&mut self) -> Option<Result<SourceFrame, ClientError>> {
        if self.limit.is_some_and(|limit| self.next >= limit) {
            return None;
        }
        let frame = &self.ring[(self.next % self.ring.len() as u64) as usize];
        let out = SourceFrame {
            index: self.next,
            t_s: self.next as f64 * self.interval_s,
            world_from_rig: frame.world_from_rig,
            left: frame.left.clone(),
            right: frame.right.clone(),
        };
        self.next += 1;
        Some(Ok(out))
    }
}

/// Resident and peak memory of a process, MiB.
pub(crate) fn process_memory_mib(pid: u32) -> Option<(f64, f64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| -> Option<f64> {
        let line = status.lines().find(|l| l.starts_with(name))?;
        let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
        Some(kib / 1024.0)
    };
    Some((field("VmRSS:")?, field("VmHWM:")?))
}

struct ServerProcess {
    child: Child,
    addr: String,
}

impl ServerProcess {
    fn start(options: &LoadOptions) -> Result<Self, LoadError> {
        use std::io::BufRead;
        let mut child = Command::new(&options.server_exe)
            .args(["serve", "--bind", "127.0.0.1:0", "--max-frame-rate", "0"])
            .args(["--max-sessions", &(options.headsets + 1).to_string()])
            .args(["--max-viewers", &(options.viewers + 1).to_string()])
            .args([
                "--max-connections",
                &(options.headsets + options.viewers + 64).to_string(),
            ])
            .args(&options.server_args)
            .env("RUST_LOG", "warn")
            .env_remove("MRPTV_INGEST_SECRET")
            .env_remove("MRPTV_WATCH_SECRET")
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .map_err(|error| LoadError::Spawn {
                exe: options.server_exe.display().to_string(),
                error,
            })?;
        let mut printed = String::new();
        let mut addr = None;
        if let Some(stdout) = child.stdout.take() {
            let mut lines = std::io::BufReader::new(stdout).lines();
            for line in lines.by_ref() {
                let Ok(line) = line else { break };
                if let Some(a) = line.split("listening on http://").nth(1) {
                    addr = Some(a.trim().to_string());
                }
                printed.push_str(&line);
                printed.push('\n');
                if line.starts_with("Ctrl-C") {
                    break;
                }
            }
            std::thread::spawn(move || for _ in lines {});
        }
        match addr {
            Some(addr) => Ok(Self { child, addr }),
            None => {
                let _ = child.kill();
                let _ = child.wait();
                Err(LoadError::NoAddress(printed))
            }
        }
    }

    /// SIGTERM, then up to 30 s for a clean exit; `true` if it exited with success.
    fn stop(mut self) -> bool {
        let pid = self.child.id().to_string();
        let _ = Command::new("kill").args(["-TERM", &pid]).status();
        let deadline = Instant::now() + Duration::from_secs(30);
        while Instant::now() < deadline {
            if let Ok(Some(status)) = self.child.try_wait() {
                return status.success();
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
        false
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

fn render_ring(scenario: Scenario, frames: usize) -> (StereoRig, Arc<Vec<SourceFrame>>, f64) {
    let spec = ScenarioSpec::new(scenario);
    let mut synth = Synthesizer::new(spec.clone(), spec.default_particles, 1);
    let ring = (0..frames.max(1))
        .map(|_| {
            let f = synth.next_frame();
            SourceFrame {
                index: f.index,
                t_s: f.t_s,
                world_from_rig: f.world_from_rig,
                left: f.left,
                right: f.right,
            }
        })
        .collect();
    (spec.rig.clone(), Arc::new(ring), spec.frame_interval_s)
}

/// A viewer subscribed to every session until `stop`; counts the batches it receives.
async fn watch(
    url: String,
    stop: tokio::sync::watch::Receiver<bool>,
    received: Arc<AtomicU64>,
) -> Result<(), String> {
    let (mut ws, _) = tokio_tungstenite::connect_async(url.as_str())
        .await
        .map_err(|e| e.to_string())?;
    ws.send(Message::text(r#"{"type":"subscribe","session":"*"}"#))
        .await
        .map_err(|e| e.to_string())?;
    let mut stop = stop;
    loop {
        tokio::select! {
            m = ws.next() => match m {
                Some(Ok(Message::Binary(_))) => {
                    received.fetch_add(1, Ordering::Relaxed);
                }
                Some(Ok(_)) => {}
                Some(Err(e)) => return Err(e.to_string()),
                None => break,
            },
            _ = stop.wait_for(|s| *s) => break,
        }
    }
    Ok(())
}

type Viewer = tokio::task::JoinHandle<Result<(), String>>;

/// Waits (5 s at most) until every viewer has received the `published` batches (the headsets
/// have their last ones; the viewers' copies may still be on the way), then stops the viewers;
/// the batches each received.
async fn stop_viewers(
    viewers: Vec<Viewer>,
    received: &[Arc<AtomicU64>],
    published: u64,
    stop: tokio::sync::watch::Sender<bool>,
) -> Result<Vec<u64>, LoadError> {
    let drain_by = Instant::now() + Duration::from_secs(5);
    while Instant::now() < drain_by
        && received
            .iter()
            .any(|r| r.load(Ordering::Relaxed) < published)
    {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let _ = stop.send(true);
    for (n, v) in viewers.into_iter().enumerate() {
        v.await
            .map_err(|e| LoadError::Viewer(n, e.to_string()))?
            .map_err(|e| LoadError::Viewer(n, e))?;
    }
    Ok(received.iter().map(|r| r.load(Ordering::Relaxed)).collect())
}

impl LoadReport {
    /// The latency percentiles of `latencies_s`, the processing rate, and the batches each
    /// viewer `received`.
    fn add_figures(&mut self, latencies_s: Vec<f64>, received: &[u64]) {
        let all = client::ReplayReport {
            latencies_s,
            ..Default::default()
        };
        let ms = |p: f64| all.latency_percentile_s(p).map(|s| s * 1e3);
        self.latency_ms_p50 = ms(50.0);
        self.latency_ms_p90 = ms(90.0);
        self.latency_ms_p99 = ms(99.0);
        self.latency_ms_max = ms(100.0);
        self.frames_per_second = self.frames_processed as f64 / self.seconds.max(1e-9);
        self.viewer_batches_min = received.iter().copied().min().unwrap_or(0);
        self.viewer_batches_mean = if received.is_empty() {
            0.0
        } else {
            received.iter().sum::<u64>() as f64 / received.len() as f64
        };
    }
}

type Headset = tokio::task::JoinHandle<Result<client::ReplayReport, ClientError>>;

/// Headset `n`: streams `source` to the server at `addr` until `stop` says so; each frame sent
/// counts in `sent`.
fn spawn_headset(
    n: usize,
    source: LoopedSource,
    options: &LoadOptions,
    addr: &str,
    mut stop: tokio::sync::watch::Receiver<bool>,
    sent: Arc<AtomicU64>,
) -> Headset {
    let replay = ReplayOptions {
        client_name: format!("mrptv load headset {n}"),
        encoding: Encoding::Raw8,
        rate: options.rate,
        keep_batches: false,
        ..ReplayOptions::new(format!("ws://{addr}/v1/ingest"))
    };
    tokio::spawn(async move {
        client::replay(
            source,
            &replay,
            async move {
                let _ = stop.wait_for(|s| *s).await;
            },
            |_| {
                sent.fetch_add(1, Ordering::Relaxed);
            },
        )
        .await
    })
}

/// Waits for every headset and adds what each sent and the server counted to `report`; their
/// latencies, seconds.
async fn add_headsets(
    report: &mut LoadReport,
    headsets: Vec<Headset>,
) -> Result<Vec<f64>, LoadError> {
    let mut latencies = Vec::new();
    for (n, h) in headsets.into_iter().enumerate() {
        let r = h
            .await
            .map_err(|e| LoadError::Headset(n, ClientError::Protocol(e.to_string())))?
            .map_err(|e| LoadError::Headset(n, e))?;
        report.frames_sent += r.frames_sent;
        if let Some(c) = r.counters {
            report.frames_processed += c.frames_processed;
            report.frames_dropped += c.frames_dropped;
            report.frames_rejected += c.frames_rejected;
        }
        report.batches_published += r.causal_batches + r.refined_batches;
        latencies.extend(r.latencies_s);
    }
    Ok(latencies)
}

/// Runs the load; `progress` gets (seconds elapsed, frames sent so far) about 4 times a second.
pub async fn run(
    options: &LoadOptions,
    mut progress: impl FnMut(f64, u64),
) -> Result<LoadReport, LoadError> {
    let (rig, ring, interval_s) = render_ring(options.scenario, options.ring_frames);
    let server = ServerProcess::start(options)?;
    let pid = server.child.id();
    let addr = server.addr.clone();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let (rss_start, _) = process_memory_mib(pid).unwrap_or_default();
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let (viewers_stop_tx, viewers_stop_rx) = tokio::sync::watch::channel(false);
    let received: Vec<Arc<AtomicU64>> = (0..options.viewers).map(|_| Default::default()).collect();
    let viewers: Vec<Viewer> = received
        .iter()
        .map(|count| {
            tokio::spawn(watch(
                format!("ws://{addr}/v1/watch"),
                viewers_stop_rx.clone(),
                Arc::clone(count),
            ))
        })
        .collect();
    // Viewers subscribe before the first frame, so every batch is theirs to receive.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let sent = Arc::new(AtomicU64::new(0));
    let started = Instant::now();
    let headsets: Vec<_> = (0..options.headsets)
        .map(|n| {
            let source = LoopedSource {
                rig: rig.clone(),
                ring: Arc::clone(&ring),
                interval_s,
                next: 0,
                limit: options.frames_per_headset,
            };
            spawn_headset(
                n,
                source,
                options,
                &addr,
                stop_rx.clone(),
                Arc::clone(&sent),
            )
        })
        .collect();
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    let mut all_done = false;
    while started.elapsed() < options.duration && !all_done {
        tick.tick().await;
        progress(
            started.elapsed().as_secs_f64(),
            sent.load(Ordering::Relaxed),
        );
        all_done = headsets.iter().all(|h| h.is_finished());
    }
    let seconds = started.elapsed().as_secs_f64();
    let _ = stop_tx.send(true);
    let mut report = LoadReport {
        headsets: options.headsets,
        viewers: options.viewers,
        seconds,
        ..Default::default()
    };
    let latencies = add_headsets(&mut report, headsets).await?;
    let (rss_end, rss_peak) = process_memory_mib(pid).unwrap_or_default();
    let received = stop_viewers(
        viewers,
        &received,
        report.batches_published,
        viewers_stop_tx,
    )
    .await?;
    report.clean_exit = tokio::task::spawn_blocking(move || server.stop())
        .await
        .unwrap_or(false);
    report.add_figures(latencies, &received);
    report.rss_start_mib = rss_start;
    report.rss_end_mib = rss_end;
    report.rss_peak_mib = rss_peak;
    Ok(report)
}
