//! `mrptv hl2ss` against a fake hl2ss: two TCP servers speaking hl2ss's documented wire format
//! (calibration on request, then raw 640x480 frames with their trailer and a row-vector rig-node
//! pose per frame) from a synthetic HoloLens-like recording (distorted lenses, right camera
//! rolled 180 degrees, divergent axes). One right frame is withheld, as a lost frame would be.
//! The bridge streams to a real server that records the session; the vectors it gets back must
//! be those of `mrptv process` on that recording, and the recording must hold the original
//! images, poses and (fitted) calibration.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;

use mrptv::hl2ss::holograms as hologram;
use mrptv::hl2ss::{
    row_vector_from_isometry, StreamConfig, StreamMode, VlcCalibration, VlcFrame, VLC_PIXELS,
};
use mrptv::recording::{FrameEntry, Recording};
use mrptv::server::ServerOptions;
use mrptv_engine::synth::{Scenario, ScenarioSpec};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

mod common;
use common::*;

/// Frames the fake HoloLens streams a session.
const FRAMES: usize = 40;
const LOST_RIGHT_FRAME: usize = 7;
const FIRST_TICKS: u64 = 133_000_000_000;
/// The sensor clock's stamp of the first exposure, nanoseconds (its own epoch, not the host's).
const FIRST_SENSOR_NS: u64 = 4_210_000_000_000;

/// How the fake stamps its frames, and which clock the bridge is told to time them by.
#[derive(Clone, Copy)]
struct Timing {
    /// Host ticks are off the exposure by up to this much either way, independently per camera
    /// and frame, and the right camera's by as much again throughout, 100 ns ticks.
    jitter_ticks: i64,
    /// `--frame-clock`.
    clock: &'static str,
}

/// A HoloLens as hl2ss's own measurements describe it: host ticks +-1 ms off, per camera.
const DEVICE: Timing = Timing {
    jitter_ticks: 10_000,
    clock: "sensor",
};

/// Host-tick jitter of frame `i`, in [-j, j] ticks: a fixed pseudo-random sequence per camera.
fn jitter(i: usize, right: bool, j: i64) -> i64 {
    if j == 0 {
        return 0;
    }
    let mut z = (i as u64 * 2 + u64::from(right)).wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^= z >> 31;
    let uniform = (z >> 11) as f64 / (1u64 << 53) as f64;
    let systematic = if right { j } else { 0 };
    systematic + ((2.0 * uniform - 1.0) * j as f64).round() as i64
}
/// hl2ss's host ticks for a VLC frame run this long after mid-exposure (its
/// `etc/rm_timestamps.txt`), in 100 ns ticks.
const HOST_TICKS_AFTER_MID_EXPOSURE: i64 = 125_000;

/// The recording's rig pose at time `t_s`, between its frames as the head moved.
fn pose_at(rec: &Recording, t_s: f64) -> Isometry3<f64> {
    let poses: Vec<(f64, Isometry3<f64>)> = rec
        .frames
        .iter()
        .map(|e| (e.t_s, e.world_from_rig.expect("a pose per frame")))
        .collect();
    let after = poses
        .partition_point(|(t, _)| *t < t_s)
        .clamp(1, poses.len() - 1);
    let ((t0, p0), (t1, p1)) = (poses[after - 1], poses[after]);
    p0.lerp_slerp(&p1, (t_s - t0) / (t1 - t0))
}

/// One fake camera: answers calibration requests and streams the recording's frames.
fn fake_camera(
    rec: Recording,
    right: bool,
    camera_from_node: Isometry3<f64>,
    node_from_left: Isometry3<f64>,
    jitter_ticks: i64,
) -> u16 {
    let listener = TcpListener::bind("127.0.0.1:0").expect("port");
    let port = listener.local_addr().expect("addr").port();
    let camera = FakeCamera {
        rec,
        right,
        camera_from_node,
        node_from_left,
        jitter_ticks,
    };
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut stream) = stream else { return };
            camera.serve(&mut stream);
        }
    });
    port
}

/// What one fake camera streams, and how it stamps it.
struct FakeCamera {
    rec: Recording,
    right: bool,
    camera_from_node: Isometry3<f64>,
    node_from_left: Isometry3<f64>,
    jitter_ticks: i64,
}

impl FakeCamera {
    /// One connection: a calibration request answered, or a stream configured and played.
    fn serve(&self, stream: &mut TcpStream) {
        let mut first = [0u8; 1];
        if stream.read_exact(&mut first).is_err() {
            return;
        }
        if first[0] == StreamMode::Calibration as u8 {
            let camera = if self.right {
                self.rec.rig.right
            } else {
                self.rec.rig.left
            };
            let calibration = VlcCalibration::from_camera(&camera, &self.camera_from_node);
            let _ = stream.write_all(&calibration.encode());
            return;
        }
        let config = read_stream_config(stream, first[0]);
        // Byte for byte what hl2ss's own client asks for: raw, or H.264 at some bitrate.
        let expected = if config.profile == mrptv::hl2ss::PROFILE_H264_BASE {
            StreamConfig::h264_with_poses(config.bitrate)
        } else {
            StreamConfig::raw_with_poses()
        };
        assert_eq!(config, expected, "the bridge asks as hl2ss's client does");
        self.play(stream, &config);
    }

    /// Streams the recording at the cameras' 30 Hz until it ends or the client leaves (hl2ss
    /// closes the stream when the app stops): raw, or real encoded video with each access
    /// unit led by an access unit delimiter as the HoloLens's encoder writes them.
    fn play(&self, stream: &mut TcpStream, config: &StreamConfig) {
        let rig = &self.rec.rig;
        let mut encoder = (config.profile == mrptv::hl2ss::PROFILE_H264_BASE).then(|| {
            let gop = mrptv::hl2ss::H264_GOP_FRAMES as u32;
            mrptv::video::H264Encoder::new(rig.width, rig.height, config.bitrate, 30.0, gop)
                .expect("encoder")
        });
        for (i, entry) in self.rec.frames.iter().enumerate() {
            if self.right && i == LOST_RIGHT_FRAME {
                continue;
            }
            let frame = self.frame(i, entry, config);
            let bytes = match &mut encoder {
                None => frame.encode(),
                Some(encoder) => {
                    let unit = encoder.encode(&frame.pixels).expect("encodes");
                    frame.encode_as(&[&[0, 0, 0, 1, 9, 0x10][..], &unit].concat())
                }
            };
            if stream.write_all(&bytes).is_err() {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(33));
        }
    }

    /// Frame `i` as a current hl2ss server stamps it: host ticks, moved by the client's options
    /// (none: raw host ticks), and the pose located at that stamp.
    fn frame(&self, i: usize, entry: &FrameEntry, config: &StreamConfig) -> VlcFrame {
        let option = |key: u64| config.options.iter().find(|(k, _)| *k == key).map(|o| o.1);
        let exposure_factor =
            option(mrptv::hl2ss::OPTION_TICKS_OFFSET_EXPOSURE).map_or(0.0, f64::from_bits);
        let constant = option(mrptv::hl2ss::OPTION_TICKS_OFFSET_CONSTANT).map_or(0, |v| v as i64);
        let (l, r) = self.rec.load(entry).expect("frame");
        // hl2ss's two cameras are triggered together; their stamps differ slightly.
        let mid_exposure = FIRST_TICKS as i64
            + (entry.t_s * 1e7).round() as i64
            + if self.right { 120 } else { 0 };
        let exposure_ns = 1000u64;
        let timestamp = mid_exposure
            + HOST_TICKS_AFTER_MID_EXPOSURE
            + (exposure_factor * exposure_ns as f64 / 100.0) as i64
            + constant
            + jitter(i, self.right, self.jitter_ticks);
        let stamped_t_s = entry.t_s + (timestamp - mid_exposure) as f64 / 1e7;
        let world_from_node = pose_at(&self.rec, stamped_t_s) * self.node_from_left.inverse();
        VlcFrame {
            timestamp: timestamp as u64,
            pixels: if self.right { r } else { l },
            // One sensor clock for both cameras, stepping exactly with the exposures.
            sensor_ticks: FIRST_SENSOR_NS + (entry.t_s * 1e9).round() as u64,
            exposure: exposure_ns,
            gain: 1,
            pose: Some(row_vector_from_isometry(&world_from_node)),
        }
    }
}

/// A stream's configuration, as a client sends it after its first byte (`mode`).
fn read_stream_config(stream: &mut TcpStream, mode: u8) -> StreamConfig {
    let mut rest = [0u8; 8];
    stream.read_exact(&mut rest).expect("configuration");
    let mut head = [0u8; 9];
    head[0] = mode;
    head[1..].copy_from_slice(&rest);
    let mut options = vec![0u8; StreamConfig::options_bytes(&head)];
    stream.read_exact(&mut options).expect("options");
    StreamConfig::decode(&[&head[..], &options].concat()).expect("config")
}

type Commands = std::sync::Arc<std::sync::Mutex<Vec<(u32, Vec<u8>)>>>;

/// A fake message queue of hl2ss's Unity plugin: records every command, answers each one (a new
/// key for a create, 1 otherwise) as the plugin does.
fn fake_message_queue() -> (u16, Commands) {
    let listener = TcpListener::bind("127.0.0.1:0").expect("port");
    let port = listener.local_addr().expect("addr").port();
    let commands: Commands = Default::default();
    let record = commands.clone();
    std::thread::spawn(move || {
        let mut next_key = 1000u32;
        for stream in listener.incoming() {
            let Ok(mut stream) = stream else { return };
            loop {
                let mut head = [0u8; 8];
                if stream.read_exact(&mut head).is_err() {
                    break;
                }
                let id = u32::from_le_bytes([head[0], head[1], head[2], head[3]]);
                let size = u32::from_le_bytes([head[4], head[5], head[6], head[7]]) as usize;
                assert!(size < 1 << 20, "command {id} of {size} bytes");
                let mut data = vec![0u8; size];
                stream.read_exact(&mut data).expect("command data");
                let answer = if id == hologram::CREATE_PRIMITIVE {
                    next_key += 1;
                    next_key
                } else {
                    1
                };
                record.lock().expect("lock").push((id, data));
                if stream.write_all(&answer.to_le_bytes()).is_err() {
                    break;
                }
            }
        }
    });
    (port, commands)
}

fn floats(data: &[u8]) -> Vec<f32> {
    data.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

fn max_abs(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    (a.to_homogeneous() - b.to_homogeneous()).abs().max()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fake_hololens_streams_through_the_bridge_like_a_headset() {
    bridge_session(&[], DEVICE).await;
}

/// The same HoloLens streaming H.264 (as over Wi-Fi), decoded by the bridge; the holograms show
/// the session's mean-flow field (`--holograms field`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fake_hololens_streaming_h264_is_decoded_by_the_bridge() {
    bridge_session(&["--codec", "h264", "--bitrate-mbps", "2.5"], DEVICE).await;
}

/// On the sensor clock with jittered host stamps, the recorded pose is interpolated to the
/// exposure's fitted host time between poses located at the jittered stamps: off the
/// exposure's where the fake head's motion bends between them, and on the first frames, whose
/// fit has few stamps; never as far as 1.5 ms of the head's motion.
const POSE_TOLERANCE_JITTERED: f64 = 1.5e-4;

/// Host stamps jittered by +-1 ms per camera (the right one 1 ms late throughout): on the sensor
/// clock the recorded times are the exposures' and the vectors those of exact stamps; on the
/// host clock (`--frame-clock host`) what the jitter costs, at +-1 and +-2 ms, is printed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn host_tick_jitter_moves_neither_times_nor_vectors_on_the_sensor_clock() {
    let exact = bridge_session(
        &[],
        Timing {
            jitter_ticks: 0,
            clock: "sensor",
        },
    )
    .await;
    for (jitter_ticks, clock) in [(10_000, "sensor"), (10_000, "host"), (20_000, "host")] {
        let run = bridge_session(
            &[],
            Timing {
                jitter_ticks,
                clock,
            },
        )
        .await;
        let rms_ms = (run
            .times
            .iter()
            .map(|(t, _, e)| (t - e).powi(2))
            .sum::<f64>()
            / run.times.len() as f64)
            .sqrt()
            * 1e3;
        let (relative, compared) = velocity_difference(&exact, &run);
        println!(
            "+-{} ms host jitter, {clock} clock: t_s {rms_ms:.4} ms rms off the exposures; \
             velocities {:.1} % (rms, relative) off those of exact stamps over {compared} vectors",
            jitter_ticks as f64 / 1e4,
            100.0 * relative
        );
        assert!(compared > 100, "{compared} vectors compared");
        if clock == "sensor" {
            assert!(rms_ms < 0.02, "t_s {rms_ms} ms rms off");
            assert!(relative < 0.10, "velocities {relative} off");
        }
    }
}

/// The rms difference of `run`'s velocities from `exact`'s, relative to `exact`'s rms speed,
/// over vectors of the same original frame at the same place (within 3 mm); frames near one
/// either session skipped (a busy machine) are left out. With the number compared.
fn velocity_difference(exact: &Session, run: &Session) -> (f64, usize) {
    let originals = |s: &Session| -> std::collections::BTreeMap<u64, usize> {
        let by_t: Vec<(f64, usize)> = s.times.iter().map(|(t, i, _)| (*t, *i)).collect();
        s.rows
            .iter()
            .filter_map(|r| {
                by_t.iter()
                    .find(|(t, _)| (t - r.t_s).abs() < 1e-9)
                    .map(|(_, i)| (r.frame, *i))
            })
            .collect()
    };
    let (oe, or) = (originals(exact), originals(run));
    let received = |s: &Session| s.times.iter().map(|t| t.1).collect::<Vec<usize>>();
    let (re, rr) = (received(exact), received(run));
    let complete = |i: usize| {
        (i.saturating_sub(6)..=i + 6)
            .filter(|&k| k != LOST_RIGHT_FRAME && k < FRAMES)
            .all(|k| re.contains(&k) && rr.contains(&k))
    };
    let (mut diff, mut speed, mut n) = (0.0, 0.0, 0);
    for a in &exact.rows {
        let Some(&i) = oe.get(&a.frame).filter(|&&i| complete(i)) else {
            continue;
        };
        let matched = run
            .rows
            .iter()
            .find(|b| or.get(&b.frame) == Some(&i) && (b.position - a.position).norm() < 3e-3);
        if let Some(b) = matched {
            diff += (b.velocity - a.velocity).norm_squared();
            speed += a.velocity.norm_squared();
            n += 1;
        }
    }
    ((diff / speed.max(1e-300)).sqrt(), n)
}

/// What a bridge session gave: the live vectors, and per recorded frame its `t_s` with the
/// exposure time of the original frame it is.
struct Session {
    rows: Vec<mrptv::tables::TrackRow>,
    times: Vec<(f64, usize, f64)>,
}

/// `mrptv hl2ss` with `codec_args` against the fake HoloLens stamping as `timing` says, a
/// recording server, and a fake message queue; everything checked.
async fn bridge_session(codec_args: &[&str], timing: Timing) -> Session {
    let h264 = !codec_args.is_empty();
    let tmp = tempfile::tempdir().expect("tmp");
    let rec = headset_recording(tmp.path());
    let ports = fake_headset(&rec, timing.jitter_ticks);
    let record = tmp.path().join("recorded");
    let server = recording_server(&record).await;
    let (mq_port, commands) = fake_message_queue();
    let live = tmp.path().join("live.csv");
    let args = bridge_args(ports, &server.ingest(), mq_port, &live, codec_args, timing);
    let (summary, bridge_seconds) = run_bridge(args).await;
    let processed = check_bridge_summary(&summary);
    server.stop().await;

    // The session's recording: the original images and poses, and the fitted calibration.
    let recorded = Recording::open(&the_only_subdir(&record)).expect("recording");
    assert_eq!(recorded.frames.len() as u64, processed);
    let times = check_recorded_frames(&recorded, &rec, timing, h264);
    check_fitted_calibration(&recorded, &rec);

    // The vectors the bridge got back are what offline processing of that recording gives.
    let offline = tmp.path().join("offline.csv");
    process_offline(&recorded, &offline);
    assert_same_rows(&live, &offline);
    let rows = mrptv::tables::read_tracks(&live).expect("live rows");

    let commands = commands.lock().expect("lock").clone();
    check_holograms(&commands, &summary, &offline, bridge_seconds);
    Session { rows, times }
}

/// Arrows in the hologram pool the bridge is asked for.
const ARROWS: usize = 50;

/// A synthetic HoloLens 2 recording on a moving head (a pose located off mid-exposure is
/// another pose), written under `tmp`.
fn headset_recording(tmp: &Path) -> Recording {
    let mut spec = ScenarioSpec::new(Scenario::HololensRaw);
    spec.head = ScenarioSpec::new(Scenario::MovingHead).head;
    let dir = tmp.join("rec");
    let particles = spec.default_particles;
    mrptv::offline::write_synthetic(spec, &dir, FRAMES, particles, 3, |_| {}).expect("synth");
    let rec = Recording::open(&dir).expect("recording");
    assert_eq!(rec.rig.width * rec.rig.height, VLC_PIXELS as u32);
    rec
}

/// The fake HoloLens's two cameras, host stamps jittered by up to `jitter_ticks`: the left one
/// somewhere on the headset's rig node, the right one where the rig puts it. Their ports.
fn fake_headset(rec: &Recording, jitter_ticks: i64) -> (u16, u16) {
    let left_from_node = Isometry3::from_parts(
        Translation3::new(-0.04, 0.01, -0.02),
        UnitQuaternion::from_euler_angles(0.05, -0.3, 1.57),
    );
    let right_from_node = rec.rig.right_from_left * left_from_node;
    let node_from_left = left_from_node.inverse();
    let j = jitter_ticks;
    (
        fake_camera(rec.clone(), false, left_from_node, node_from_left, j),
        fake_camera(rec.clone(), true, right_from_node, node_from_left, j),
    )
}

/// A server that records its sessions into `record` and sends fields from the first refined
/// frame on, ten a second (40 frames are 1.3 s).
async fn recording_server(record: &Path) -> TestServer {
    TestServer::start(ServerOptions {
        record_dir: Some(record.to_path_buf()),
        config: mrptv_engine::PipelineConfig::default(),
        field: mrptv::server::FieldOptions {
            cell_m: Some(0.05),
            interval: std::time::Duration::from_millis(100),
            ..Default::default()
        },
        ..Default::default()
    })
    .await
}

/// `mrptv hl2ss`'s arguments: the fake's cameras (`left`, `right` ports), the server's ingest
/// `url`, the fake message queue, the live vectors to `live`, the holograms (of the field when
/// streaming H.264), `codec_args` and the frame clock.
fn bridge_args(
    (left, right): (u16, u16),
    url: &str,
    mq_port: u16,
    live: &Path,
    codec_args: &[&str],
    timing: Timing,
) -> Vec<String> {
    let holograms_of_the_field = !codec_args.is_empty();
    let mut args: Vec<String> = [
        "hl2ss",
        "--host",
        "127.0.0.1",
        "--left-port",
        &left.to_string(),
        "--right-port",
        &right.to_string(),
        "--url",
        url,
        "--out",
        &live.display().to_string(),
        "--json",
        "--mq-port",
        &mq_port.to_string(),
        "--hologram-arrows",
        &ARROWS.to_string(),
        "--hologram-rate",
        "10",
        "--frame-clock",
        timing.clock,
    ]
    .iter()
    .chain(codec_args)
    .map(|a| a.to_string())
    .collect();
    args.push("--holograms".into());
    if holograms_of_the_field {
        args.push("field".into());
    }
    args
}

/// Runs the bridge to its end: its JSON summary and how long it ran, seconds. Its fit residual
/// is reported for each camera, and small.
async fn run_bridge(args: Vec<String>) -> (serde_json::Value, f64) {
    let started = std::time::Instant::now();
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new(env!("CARGO_BIN_EXE_mrptv"))
            .args(&args)
            .env_remove("MRPTV_INGEST_SECRET")
            .output()
            .expect("mrptv hl2ss runs")
    })
    .await
    .expect("bridge task");
    let bridge_seconds = started.elapsed().as_secs_f64();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    for camera in ["left camera", "right camera"] {
        let line = stderr
            .lines()
            .find(|l| l.starts_with(camera))
            .unwrap_or_else(|| panic!("no {camera} fit in {stderr}"));
        let rms: f64 = line
            .split("residual ")
            .nth(1)
            .and_then(|r| r.split(' ').next())
            .and_then(|r| r.parse().ok())
            .unwrap_or_else(|| panic!("{line}"));
        assert!(rms < 0.01, "{line}");
    }
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).expect("a JSON summary");
    println!("{summary}\n{stderr}");
    (summary, bridge_seconds)
}

/// The bridge's counts: every frame but the lost right one paired, and every pair processed or
/// counted stale (a busy machine may fall behind; whether the server kept up is the
/// benchmarks' business). The pairs processed.
fn check_bridge_summary(summary: &serde_json::Value) -> u64 {
    let frames = FRAMES as u64;
    let bridge = &summary["bridge"];
    assert_eq!(bridge["left_frames"], frames, "{summary}");
    assert_eq!(bridge["right_frames"], frames - 1, "{summary}");
    assert_eq!(bridge["pairs"], frames - 1, "{summary}");
    assert_eq!(
        bridge["unpaired_left"], 1,
        "the left frame of the lost right one: {summary}"
    );
    assert_eq!(bridge["unpaired_right"], 0, "{summary}");
    assert_eq!(bridge["unposed"], 0, "{summary}");
    let stale = bridge["stale"].as_u64().expect("stale");
    let processed = summary["frames_processed"].as_u64().expect("processed");
    assert_eq!(processed + stale, frames - 1, "{summary}");
    assert!(processed > 0, "{summary}");
    assert_eq!(summary["errors"], 0, "{summary}");
    assert!(
        stale > 0 || summary["refined_vectors"].as_u64() > Some(100),
        "{summary}"
    );
    processed
}

/// Each recorded frame is one of the originals: its time the exposure's, its pose the
/// exposure's (on the sensor clock), its images the original ones (within the codec's loss
/// when streamed as `h264`). Per recorded frame, its `t_s`, the original's index and exposure.
fn check_recorded_frames(
    recorded: &Recording,
    rec: &Recording,
    timing: Timing,
    h264: bool,
) -> Vec<(f64, usize, f64)> {
    let mut times = Vec::new();
    let mut pose_errors = Vec::new();
    for got in &recorded.frames {
        let (original_index, original) = original_of(got, rec);
        let exposure = original.t_s - rec.frames[0].t_s;
        times.push((got.t_s, original_index, exposure));
        // On the sensor clock, the exposure times whatever the host stamps did.
        let dt = got.t_s - exposure;
        let tolerance_s = if timing.clock == "sensor" { 1e-6 } else { 5e-3 };
        assert!(
            dt.abs() < tolerance_s,
            "frame {} is none of the originals ({dt} s off)",
            got.index
        );
        pose_errors.push(check_recorded_pose(got, original, timing));
        let (got_images, original_images) = (
            recorded.load(got).expect("recorded"),
            rec.load(original).expect("original"),
        );
        if h264 {
            check_decoded(got.index, &got_images, &original_images);
        } else {
            assert_eq!(got_images, original_images, "frame {}", got.index);
        }
    }
    pose_errors.sort_by(f64::total_cmp);
    println!(
        "recorded poses at most {:.2e} off the exposures', median {:.2e}",
        pose_errors.last().copied().unwrap_or(0.0),
        pose_errors[pose_errors.len() / 2]
    );
    times
}

/// The original frame (not the lost one) whose exposure a recorded frame's time is nearest.
fn original_of<'a>(got: &FrameEntry, rec: &'a Recording) -> (usize, &'a FrameEntry) {
    let exposure = |e: &FrameEntry| e.t_s - rec.frames[0].t_s;
    rec.frames
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != LOST_RIGHT_FRAME)
        .min_by(|a, b| {
            let off = |e| (got.t_s - exposure(e)).abs();
            off(a.1).total_cmp(&off(b.1))
        })
        .expect("originals")
}

/// How far a recorded frame's pose is from its original's. The fake's world is hl2ss's (y up);
/// the server works in OpenCV's axes (y down). On the sensor clock the pose is the exposure's,
/// interpolated between jittered stamps.
fn check_recorded_pose(got: &FrameEntry, original: &FrameEntry, timing: Timing) -> f64 {
    let d = max_abs(
        &got.world_from_rig.expect("posed"),
        &(mrptv::hl2ss::bridge::opencv_from_hl2ss_world()
            * original.world_from_rig.expect("posed")),
    );
    let tolerance = if timing.jitter_ticks == 0 {
        1e-5
    } else {
        POSE_TOLERANCE_JITTERED
    };
    assert!(
        timing.clock != "sensor" || d < tolerance,
        "frame {}: pose off by {d}",
        got.index
    );
    d
}

/// What the decoder gave for frame `index`: each image within the codec's loss of the
/// original, and not the raw one.
fn check_decoded(index: u64, got: &(Vec<u8>, Vec<u8>), original: &(Vec<u8>, Vec<u8>)) {
    for (a, b) in [(&got.0, &original.0), (&got.1, &original.1)] {
        let mean_abs = a
            .iter()
            .zip(b.iter())
            .map(|(x, y)| f64::from(x.abs_diff(*y)))
            .sum::<f64>()
            / a.len() as f64;
        assert!(
            mean_abs < 3.0,
            "frame {index}: {mean_abs:.2} grey levels off"
        );
        assert_ne!(a, b, "frame {index}: decoded, not raw");
    }
}

/// The calibration the bridge fitted is the recording's.
fn check_fitted_calibration(recorded: &Recording, rec: &Recording) {
    let (fitted, truth) = (&recorded.rig, &rec.rig);
    for (a, b) in [(fitted.left, truth.left), (fitted.right, truth.right)] {
        for (x, y) in [(a.fx, b.fx), (a.fy, b.fy), (a.cx, b.cx), (a.cy, b.cy)] {
            assert!((x - y).abs() < 0.05, "{a:?} vs {b:?}");
        }
    }
    assert!(max_abs(&fitted.right_from_left, &truth.right_from_left) < 1e-5);
}

/// `mrptv process` on the session's recording, to `out`.
fn process_offline(recorded: &Recording, out: &Path) {
    let processed = std::process::Command::new(env!("CARGO_BIN_EXE_mrptv"))
        .arg("process")
        .arg(recorded.dir.as_path())
        .arg("--out")
        .arg(out)
        .output()
        .expect("process runs");
    assert!(
        processed.status.success(),
        "{}",
        String::from_utf8_lossy(&processed.stderr)
    );
}

/// The holograms: one pool of arrows, created once, then display lists at most 10 a second,
/// each arrow within reach of the vectors `process` wrote to `offline`; the pool removed at
/// the end.
fn check_holograms(
    commands: &[(u32, Vec<u8>)],
    summary: &serde_json::Value,
    offline: &Path,
    bridge_seconds: f64,
) {
    let updates = summary["hologram_updates"]
        .as_u64()
        .expect("hologram updates");
    assert_eq!(summary["hologram_commands_refused"], 0, "{summary}");
    let creates: Vec<usize> = (0..commands.len())
        .filter(|&i| commands[i].0 == hologram::CREATE_PRIMITIVE)
        .collect();
    assert_eq!(creates.len(), ARROWS, "a pool, created once");
    assert!(creates
        .iter()
        .all(|&i| i <= ARROWS && commands[i].1 == hologram::CYLINDER.to_le_bytes()));
    let mut lists = DisplayLists {
        keys: (1001..=1000 + ARROWS as u32).collect(),
        bounds: vector_bounds(offline),
        open: false,
        lists: 0,
        transforms: 0,
    };
    for (id, data) in commands {
        lists.check(*id, data);
    }
    assert!(!lists.open);
    // The pool's creation and hiding, then one list per update.
    assert_eq!(lists.lists as u64, 2 + updates);
    // 40 frames at 30 Hz is 1.3 s: at most 10 updates a second, never one per frame.
    assert!(
        updates >= 3 && updates as f64 <= bridge_seconds * 10.0 + 1.0,
        "{updates} updates in {bridge_seconds:.2} s"
    );
    assert!(lists.transforms > 0);
    let removed = commands
        .iter()
        .filter(|(id, _)| *id == hologram::REMOVE)
        .count();
    assert_eq!(removed, ARROWS, "the pool is removed at the end");
}

/// The box the vectors of a `tracks.csv` in OpenCV's axes lie in, in Unity's (y flipped).
fn vector_bounds(tracks: &Path) -> ([f64; 3], [f64; 3]) {
    let rows = mrptv::tables::read_tracks(tracks).expect("offline rows");
    rows.iter().fold(
        ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
        |(mut lo, mut hi), r| {
            let p = [r.position.x, -r.position.y, r.position.z];
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
            (lo, hi)
        },
    )
}

/// The hologram commands seen so far, checked one by one.
struct DisplayLists {
    /// The pool's objects.
    keys: Vec<u32>,
    /// Where the vectors are (lowest and highest corner).
    bounds: ([f64; 3], [f64; 3]),
    open: bool,
    lists: usize,
    transforms: usize,
}

impl DisplayLists {
    /// One command: lists neither nested nor left open, transforms batched in them (unit
    /// rotations, positive scales, arrows near the vectors), colours in range, only the pool's
    /// objects touched.
    fn check(&mut self, id: u32, data: &[u8]) {
        let key = |data: &[u8]| u32::from_le_bytes([data[0], data[1], data[2], data[3]]);
        match id {
            hologram::BEGIN_DISPLAY_LIST => {
                assert!(!self.open, "display lists do not nest");
                self.open = true;
                self.lists += 1;
            }
            hologram::END_DISPLAY_LIST => {
                assert!(self.open, "an end without a begin");
                self.open = false;
            }
            hologram::SET_WORLD_TRANSFORM => {
                assert!(self.open, "transforms are batched in display lists");
                assert_eq!(data.len(), 44);
                assert!(self.keys.contains(&key(data)), "an object of the pool");
                self.check_transform(&floats(&data[4..]));
                self.transforms += 1;
            }
            hologram::SET_COLOR => {
                assert_eq!(data.len(), 20);
                let rgba = floats(&data[4..]);
                assert!(rgba.iter().all(|c| (0.0..=1.0).contains(c)), "{rgba:?}");
            }
            hologram::SET_ACTIVE => assert_eq!(data.len(), 8),
            hologram::REMOVE => assert!(self.keys.contains(&key(data))),
            hologram::CREATE_PRIMITIVE => {}
            other => panic!("unexpected command {other}"),
        }
    }

    /// An arrow's transform (position, rotation, scale): finite, a unit rotation, a positive
    /// scale, within 0.2 m of the vectors' box.
    fn check_transform(&self, v: &[f32]) {
        assert!(v.iter().all(|x| x.is_finite()));
        let q_norm = v[3..7].iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((q_norm - 1.0).abs() < 1e-4, "unit rotation: {v:?}");
        assert!(
            v[7] > 0.0 && v[8] > 0.0 && v[9] > 0.0,
            "positive scale: {v:?}"
        );
        let (lo, hi) = self.bounds;
        for k in 0..3 {
            let c = f64::from(v[k]);
            assert!(
                c > lo[k] - 0.2 && c < hi[k] + 0.2,
                "arrow at {v:?} outside {lo:?}..{hi:?}"
            );
        }
    }
}

/// Two `tracks.csv` files with the same rows, values equal to float32 rounding; the live one in
/// the bridge's WebXR axes (hl2ss's world), the offline one in OpenCV's.
fn assert_same_rows(live: &Path, offline: &Path) {
    let live = mrptv::tables::read_tracks(live).expect("live.csv");
    let offline = mrptv::tables::read_tracks(offline).expect("offline.csv");
    assert_eq!(live.len(), offline.len(), "as many vectors live as offline");
    assert!(!live.is_empty());
    for (a, b) in live.iter().zip(&offline) {
        assert_eq!((a.frame, a.track_id), (b.frame, b.track_id));
        let values = |r: &mrptv::tables::TrackRow, s: f64| {
            [
                r.position.x,
                s * r.position.y,
                s * r.position.z,
                r.velocity.x,
                s * r.velocity.y,
                s * r.velocity.z,
            ]
        };
        for (x, y) in values(a, -1.0).iter().zip(values(b, 1.0)) {
            assert!(
                (x - y).abs() <= 1e-6 * y.abs().max(1e-3),
                "frame {} track {}: live {x} offline {y}",
                a.frame,
                a.track_id
            );
        }
    }
}
