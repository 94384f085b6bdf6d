//! A headset on a bad link: delay, jitter and stalls through an impairment proxy, and a rate
//! limit below the stream's bit rate with `tc tbf` between two network namespaces. What must
//! hold on any machine is asserted (the session stays up, every frame sent is answered, drops
//! are counted and reported, the stream recovers with the link, the server's queue never grows
//! past its bound); the latencies and drops measured are printed, and docs/live-service.md tabulates them (scripts/measure live).

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use mrptv::client::{Rate, ReplayOptions};
use mrptv::protocol::Encoding;
use mrptv::server::ServerOptions;
use mrptv_engine::synth::Scenario;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

mod common;
use common::*;

/// How the proxy treats bytes: each chunk is held `delay` +- `jitter` (in order, as TCP
/// delivers), and every `stall_every` nothing moves for `stall_for` (what a lost packet and
/// its retransmission look like to TCP).
#[derive(Debug, Clone, Copy)]
struct Impairment {
    delay: Duration,
    jitter: Duration,
    stall_every: Duration,
    stall_for: Duration,
}

impl Impairment {
    /// When a chunk read at `at` may be written: after its delay, after the chunk before it,
    /// and outside any stall.
    fn release(&self, started: Instant, at: Instant, previous: Instant, draw: f64) -> Instant {
        let jitter = self.jitter.as_secs_f64() * (2.0 * draw - 1.0);
        let held = Duration::from_secs_f64((self.delay.as_secs_f64() + jitter).max(0.0));
        let mut release = (at + held).max(previous);
        let period = self.stall_every.as_secs_f64();
        if period > 0.0 {
            let since = (release - started).as_secs_f64();
            let into = since % period;
            let stall_from = period - self.stall_for.as_secs_f64();
            if into >= stall_from {
                release += Duration::from_secs_f64(period - into);
            }
        }
        release
    }
}

/// A TCP proxy to `upstream` impairing both directions; its port.
async fn impairment_proxy(upstream: std::net::SocketAddr, impairment: Impairment) -> u16 {
    let listener = TcpListener::bind("127.0.0.1:0").await.expect("port");
    let port = listener.local_addr().expect("addr").port();
    let started = Instant::now();
    tokio::spawn(async move {
        let mut seed = 0x9E37_79B9_7F4A_7C15u64;
        while let Ok((client, _)) = listener.accept().await {
            let Ok(server) = TcpStream::connect(upstream).await else {
                continue;
            };
            let (client_read, client_write) = client.into_split();
            let (server_read, server_write) = server.into_split();
            seed = seed.wrapping_add(1);
            for (read, write, seed) in [
                (
                    Box::new(client_read) as Box<dyn tokio::io::AsyncRead + Unpin + Send>,
                    Box::new(server_write) as Box<dyn tokio::io::AsyncWrite + Unpin + Send>,
                    seed,
                ),
                (Box::new(server_read), Box::new(client_write), seed ^ 0xFF),
            ] {
                tokio::spawn(carry(read, write, impairment, started, seed));
            }
        }
    });
    port
}

async fn carry(
    mut read: Box<dyn tokio::io::AsyncRead + Unpin + Send>,
    mut write: Box<dyn tokio::io::AsyncWrite + Unpin + Send>,
    impairment: Impairment,
    started: Instant,
    mut seed: u64,
) {
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<(Instant, Vec<u8>)>();
    let writer = tokio::spawn(async move {
        while let Some((release, chunk)) = rx.recv().await {
            tokio::time::sleep_until(release.into()).await;
            if write.write_all(&chunk).await.is_err() {
                break;
            }
        }
        let _ = write.shutdown().await;
    });
    let mut previous = started;
    let mut buffer = vec![0u8; 64 << 10];
    loop {
        let n = match read.read(&mut buffer).await {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let draw = (seed >> 11) as f64 / (1u64 << 53) as f64;
        previous = impairment.release(started, Instant::now(), previous, draw);
        if tx.send((previous, buffer[..n].to_vec())).is_err() {
            break;
        }
    }
    drop(tx);
    let _ = writer.await;
}

/// Nearest-rank percentiles of seconds, as milliseconds.
fn percentiles_ms(seconds: &[f64]) -> (f64, f64) {
    let mut sorted = seconds.to_vec();
    sorted.sort_by(f64::total_cmp);
    let at = |p: f64| {
        let rank = ((p / 100.0) * sorted.len() as f64).ceil() as usize;
        sorted.get(rank.max(1) - 1).map_or(f64::NAN, |s| s * 1e3)
    };
    (at(50.0), at(99.0))
}

/// A 30 Hz headset through delay 20 +- 10 ms and a 300 ms stall every second: the session
/// stays up, every frame is answered, and the stream goes on after each stall.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_jittery_stalling_link_keeps_the_session_and_the_stream() {
    let tmp = tempfile::tempdir().expect("tmp");
    let frames = 90;
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Flume, frames);
    for (name, impairment) in [
        (
            "delay 20 +- 10 ms",
            Impairment {
                delay: Duration::from_millis(20),
                jitter: Duration::from_millis(10),
                stall_every: Duration::ZERO,
                stall_for: Duration::ZERO,
            },
        ),
        (
            "delay 20 +- 10 ms, 300 ms stall every 1 s",
            Impairment {
                delay: Duration::from_millis(20),
                jitter: Duration::from_millis(10),
                stall_every: Duration::from_secs(1),
                stall_for: Duration::from_millis(300),
            },
        ),
    ] {
        let server = TestServer::start(ServerOptions::default()).await;
        let port = impairment_proxy(server.addr, impairment).await;
        // Paced as a live headset: 30 Hz, the recording's timestamps.
        let options = ReplayOptions {
            encoding: Encoding::Sparse,
            rate: Rate::Recorded,
            ..replay_options(format!("ws://127.0.0.1:{port}/v1/ingest"), &config)
        };
        let report = replay(&rec, &options).await;
        server.stop().await;
        let (p50, p99) = percentiles_ms(&report.ages_s);
        println!(
            "{name}: {} sent, {} skipped by the headset, {} dropped by the server; age p50 {p50:.1} ms, p99 {p99:.1} ms",
            report.frames_sent,
            report.frames_skipped,
            report.dropped_frames.len()
        );
        assert_session_survived(name, &report, frames as u64);
    }
}

/// What must hold of a live session over any link, on any machine.
fn assert_session_survived(name: &str, report: &mrptv::client::ReplayReport, frames: u64) {
    assert!(report.errors.is_empty(), "{name}: {:?}", report.errors);
    assert_eq!(
        report.bye_reason.as_deref(),
        Some("client said bye"),
        "{name}"
    );
    assert_eq!(report.frames_sent + report.frames_skipped, frames, "{name}");
    let counters = report.counters.expect("final counters");
    // Every frame sent was answered: processed (its causal batch) or dropped (and told).
    assert_eq!(
        report.causal_batches + report.dropped_frames.len() as u64,
        report.frames_sent,
        "{name}"
    );
    assert_eq!(
        counters.frames_processed + counters.frames_dropped,
        report.frames_sent,
        "{name}: {counters:?}"
    );
    assert_eq!(
        counters.frames_dropped,
        report.dropped_frames.len() as u64,
        "{name}: every drop is reported to the headset"
    );
    // The last frame is never skipped (nothing newer overtakes it): the stream recovered.
    assert_eq!(
        report.causal.last().map(|b| b.frame_index),
        Some(frames - 1),
        "{name}: the stream goes on to the end"
    );
}

/// Runs `ip` or `tc` with these arguments; the error names the command.
fn run(program: &str, args: &[&str]) -> Result<(), String> {
    let out = Command::new(program)
        .args(args)
        .output()
        .map_err(|e| format!("{program}: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{program} {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

/// Two network namespaces joined by a veth pair, removed on drop.
struct Link {
    headset: String,
    server: String,
    headset_dev: String,
    server_ip: String,
    children: Vec<Child>,
}

impl Link {
    fn create() -> Result<Self, String> {
        let id = std::process::id() % 100_000;
        let link = Link {
            headset: format!("mrptv-h{id}"),
            server: format!("mrptv-s{id}"),
            headset_dev: format!("mh{id}"),
            server_ip: format!("10.77.{}.2", id % 250),
            children: Vec::new(),
        };
        let server_dev = format!("ms{id}");
        let headset_ip = format!("10.77.{}.1/24", id % 250);
        let server_cidr = format!("{}/24", link.server_ip);
        run("ip", &["netns", "add", &link.headset])?;
        run("ip", &["netns", "add", &link.server])?;
        for (ns, dev, ip) in [
            (&link.headset, &link.headset_dev, &headset_ip),
            (&link.server, &server_dev, &server_cidr),
        ] {
            if dev == &link.headset_dev {
                run(
                    "ip",
                    &[
                        "link",
                        "add",
                        dev,
                        "type",
                        "veth",
                        "peer",
                        "name",
                        &server_dev,
                    ],
                )?;
            }
            run("ip", &["link", "set", dev, "netns", ns])?;
            run("ip", &["-n", ns, "addr", "add", ip, "dev", dev])?;
            run("ip", &["-n", ns, "link", "set", dev, "up"])?;
            run("ip", &["-n", ns, "link", "set", "lo", "up"])?;
        }
        Ok(link)
    }

    /// Limits the headset's uplink (its egress) with a token bucket.
    fn limit(&self, verb: &str, rate: &str) -> Result<(), String> {
        let args = [
            "-n",
            self.headset.as_str(),
            "qdisc",
            verb,
            "dev",
            self.headset_dev.as_str(),
            "root",
            "tbf",
            "rate",
            rate,
            "burst",
            "64kb",
            "latency",
            "100ms",
        ];
        run("tc", &args)
    }

    fn spawn(&mut self, ns: &str, args: &[&str]) -> std::io::Result<&mut Child> {
        let child = Command::new("ip")
            .args(["netns", "exec", ns, env!("CARGO_BIN_EXE_mrptv")])
            .args(args)
            .env_remove("MRPTV_INGEST_SECRET")
            .env_remove("MRPTV_WATCH_SECRET")
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()?;
        self.children.push(child);
        Ok(self.children.last_mut().expect("just pushed"))
    }
}

impl Drop for Link {
    fn drop(&mut self) {
        for child in &mut self.children {
            let _ = child.kill();
            let _ = child.wait();
        }
        let _ = run("ip", &["netns", "del", &self.headset]);
        let _ = run("ip", &["netns", "del", &self.server]);
    }
}

/// A raw8 stream (147 Mbit/s) through a 20 Mbit/s uplink, lifted to 1 Gbit/s halfway: the
/// headset skips what the link cannot carry, the session stays up, and the stream recovers.
/// Then the `sparse` encoding (a few Mbit/s) through the same 20 Mbit/s.
#[test]
fn a_rate_limited_uplink_costs_frames_not_the_session() {
    let mut link = match Link::create() {
        Ok(link) => link,
        Err(e) => {
            // Only where namespaces cannot be made (not root); CI runs as root and runs this.
            eprintln!("SKIPPED a_rate_limited_uplink_costs_frames_not_the_session: cannot build network namespaces here ({e}); run as root to test a rate-limited link");
            return;
        }
    };
    link.limit("add", "20mbit").expect("tc tbf");
    let tmp = tempfile::tempdir().expect("tmp");
    let frames = 120usize;
    let (_rec, _) = synth(&tmp.path().join("rec"), Scenario::Flume, frames);
    let bind = format!("{}:8770", link.server_ip);
    let server_ns = link.server.clone();
    let server = link
        .spawn(&server_ns, &["serve", "--bind", &bind])
        .expect("serve starts");
    let stdout = server.stdout.take().expect("stdout");
    // Read to the end, so the server never writes to a closed pipe.
    let (listening, heard) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::BufReader::new(stdout)
            .lines()
            .map_while(Result::ok)
        {
            if line.contains("listening on") {
                let _ = listening.send(());
            }
        }
    });
    heard
        .recv_timeout(Duration::from_secs(60))
        .expect("the server listens");
    let url = format!("ws://{bind}/v1/ingest");
    let rec = tmp.path().join("rec");
    let headset_ns = link.headset.clone();
    let replay = |encoding: &str| -> (Child, Instant) {
        let child = Command::new("ip")
            .args(["netns", "exec", &headset_ns, env!("CARGO_BIN_EXE_mrptv")])
            .args(["replay"])
            .arg(&rec)
            .args(["--url", &url, "--json", "--encoding", encoding])
            .env_remove("MRPTV_INGEST_SECRET")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("replay starts");
        (child, Instant::now())
    };
    let summary = |child: Child| -> serde_json::Value {
        let out = child.wait_with_output().expect("replay ends");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice(&out.stdout).expect("a JSON summary")
    };

    // raw8 through 20 Mbit/s, the limit lifted after 2 s of the 4 s stream.
    let (child, started) = replay("raw8");
    std::thread::sleep(Duration::from_secs(2).saturating_sub(started.elapsed()));
    link.limit("change", "1gbit").expect("tc change");
    let raw = summary(child);
    println!("raw8, 20 Mbit/s then 1 Gbit/s: {raw}");
    // sparse through 20 Mbit/s.
    link.limit("change", "20mbit").expect("tc change");
    let (child, _) = replay("sparse");
    let sparse = summary(child);
    println!("sparse, 20 Mbit/s: {sparse}");
    for (name, s) in [("raw8", &raw), ("sparse", &sparse)] {
        let n = |key: &str| {
            s[key]
                .as_u64()
                .unwrap_or_else(|| panic!("{name}: {key} in {s}"))
        };
        assert_eq!(n("errors"), 0, "{name}: {s}");
        assert_eq!(
            n("frames_sent") + n("frames_skipped"),
            frames as u64,
            "{name}: {s}"
        );
        assert_eq!(
            n("frames_processed") + n("frames_dropped"),
            n("frames_sent"),
            "{name}: every frame sent is processed or dropped and told: {s}"
        );
        assert!(n("frames_processed") > 0, "{name}: {s}");
    }
    assert!(
        raw["frames_skipped"].as_u64() > Some(0),
        "147 Mbit/s cannot all pass 20 Mbit/s: {raw}"
    );
    // Nothing newer overtakes the last frame, so it is sent: the stream recovered.
    for (name, s) in [("raw8", &raw), ("sparse", &sparse)] {
        assert_eq!(
            s["last_causal_frame"].as_u64(),
            Some(frames as u64 - 1),
            "{name}: {s}"
        );
    }
}
