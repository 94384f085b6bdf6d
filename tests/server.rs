//! The live service end to end: the real server on port 0, real WebSocket clients (the Rust
//! reference client, raw tokio-tungstenite connections, and the independent Python client),
//! vectors compared with the offline `process` output of the same frames.

use std::path::Path;
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use mrptv::client::{Rate, ReplayOptions};
use mrptv::offline::{self, ProcessSinks, Sink};
use mrptv::protocol::{
    decode_batch, encode_frame, BatchKind, Convention, DecodedBatch, Encoding, ErrorCode,
    FrameMessage, ServerMessage,
};
use mrptv::recording::Recording;
use mrptv::server::ServerOptions;
use mrptv::tables::{self, TrackRow};
use mrptv_engine::synth::Scenario;
use mrptv_engine::PipelineConfig;
use tokio_tungstenite::tungstenite::Message;

mod common;
use common::*;

fn offline_tracks(recording: &Recording, config: &PipelineConfig, out: &Path) -> Vec<TrackRow> {
    let mut file = std::fs::File::create(out).expect("create");
    offline::process_recording(
        recording,
        config.clone(),
        ProcessSinks {
            tracks: Sink {
                path: out,
                writer: &mut file,
            },
            points: None,
            rerun: None,
        },
        |_| {},
    )
    .expect("offline processing");
    tables::read_tracks(out).expect("tracks.csv")
}

/// Live vectors (float32, in `convention`) against offline rows (float64, OpenCV): same rows in
/// the same order, values equal to float32 rounding.
fn assert_same_vectors(live: &[DecodedBatch], offline: &[TrackRow]) {
    let rows: Vec<(u64, u64, [f64; 6])> = live
        .iter()
        .flat_map(|b| {
            b.vectors.iter().map(move |v| {
                let p = b.convention.flip(&v.position_m.map(f64::from).into());
                let u = b.convention.flip(&v.velocity_m_per_s.map(f64::from).into());
                (b.frame_index, v.track_id, [p.x, p.y, p.z, u.x, u.y, u.z])
            })
        })
        .collect();
    assert_eq!(rows.len(), offline.len(), "as many live vectors as offline");
    assert!(!rows.is_empty(), "vectors came back");
    for (live, off) in rows.iter().zip(offline) {
        assert_eq!(
            (live.0, live.1),
            (off.frame, off.track_id),
            "same frame and track"
        );
        let expected = values(off);
        for (a, b) in live.2.iter().zip(expected) {
            assert!(
                (a - b).abs() <= 1e-6 * b.abs().max(1e-3),
                "frame {} track {}: live {a} offline {b}",
                off.frame,
                off.track_id
            );
        }
    }
}

fn values(r: &TrackRow) -> [f64; 6] {
    let (p, v) = (r.position, r.velocity);
    [p.x, p.y, p.z, v.x, v.y, v.z]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rust_client_vectors_match_offline_processing_and_the_live_recording() {
    let tmp = tempfile::tempdir().expect("tmp");
    // Head motion: poses travel with every frame and vectors come back in the world frame.
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::MovingHead, 60);
    let record_dir = tmp.path().join("live");
    let server = TestServer::start(ServerOptions {
        record_dir: Some(record_dir.clone()),
        ..Default::default()
    })
    .await;
    let options = ReplayOptions {
        convention: Convention::WebXr,
        ..replay_options(server.ingest(), &config)
    };
    let report = replay(&rec, &options).await;
    server.stop().await;

    assert!(report.errors.is_empty(), "{:?}", report.errors);
    assert_eq!(report.frames_sent, 60);
    assert!(report.dropped_frames.is_empty());
    let counters = report.counters.expect("final counters in the bye");
    assert_eq!(counters.frames_processed, 60);
    // The session's health, as `process` reports it: ~20 particles, nearly all linked and
    // matched, most matched ones given a velocity once the window has filled.
    assert!(
        (10.0..=40.0).contains(&counters.detections_per_image)
            && counters.linked_fraction > 0.8
            && counters.matched_fraction > 0.8
            && (0.3..=1.0).contains(&counters.velocity_fraction)
            && (1.0..2.0).contains(&counters.stereo_candidates_per_particle),
        "{counters:?}"
    );
    assert_eq!(report.bye_reason.as_deref(), Some("client said bye"));
    // Every frame got its causal batch, in order, at once; all flagged causal and world.
    assert_eq!(report.latencies_s.len(), 60);
    let causal_frames: Vec<u64> = report.causal.iter().map(|b| b.frame_index).collect();
    assert_eq!(causal_frames, (0..60).collect::<Vec<_>>());
    assert!(report
        .causal
        .iter()
        .all(|b| b.world && b.kind == BatchKind::Causal));
    // Posed frames: every batch and vector says world frame; refined vectors say refined.
    assert!(report
        .refined
        .iter()
        .all(|b| b.world && b.kind == BatchKind::Refined));
    for b in report.causal.iter().chain(&report.refined) {
        let refined = b.kind == BatchKind::Refined;
        assert!(b
            .vectors
            .iter()
            .all(|v| v.flags == if refined { 3 } else { 2 }));
    }
    assert!(
        report.causal_vectors > 500,
        "{} causal",
        report.causal_vectors
    );
    let m = config.velocity.half_window_frames as u64;
    let refined_frames: Vec<u64> = report.refined.iter().map(|b| b.frame_index).collect();
    assert_eq!(refined_frames, (0..60 - m).collect::<Vec<_>>());

    let offline = offline_tracks(&rec, &config, &tmp.path().join("offline.csv"));
    assert_same_vectors(&report.refined, &offline);

    // The live recording reprocessed offline gives the very same vectors.
    let recorded_dir = the_only_subdir(&record_dir);
    let recorded = Recording::open(&recorded_dir).expect("recorded session");
    assert_eq!(recorded.frames.len(), 60);
    let recorded_config =
        mrptv::config::load(&recorded_dir.join("mrptv.toml")).expect("the session's config");
    assert_eq!(recorded_config, config);
    let again = offline_tracks(&recorded, &recorded_config, &tmp.path().join("again.csv"));
    assert_same_vectors(&report.refined, &again);
}

/// A headset sending `sparse` images: the session decodes them, records what it decoded, and
/// `mrptv process` on that recording gives the vectors the headset got.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sparse_frames_are_decoded_recorded_and_measured() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::HololensRaw, 40);
    let record_dir = tmp.path().join("live");
    let server = TestServer::start(ServerOptions {
        record_dir: Some(record_dir.clone()),
        ..Default::default()
    })
    .await;
    let options = ReplayOptions {
        encoding: Encoding::Sparse,
        ..replay_options(server.ingest(), &config)
    };
    let report = replay(&rec, &options).await;
    server.stop().await;
    assert!(report.errors.is_empty(), "{:?}", report.errors);
    assert_eq!(report.counters.map(|c| c.frames_processed), Some(40));
    assert!(report.causal_vectors > 200, "{}", report.causal_vectors);
    let recorded = Recording::open(&the_only_subdir(&record_dir)).expect("recorded session");
    assert_eq!(recorded.frames.len(), 40);
    // What was recorded is what the headset's encoder sent: every pixel it kept, exactly.
    let first = recorded.frames[0];
    let (left, _) = recorded.load(&first).expect("recorded images");
    let (original, _) = rec.load(&rec.frames[0]).expect("original images");
    let (w, h) = (rec.rig.width, rec.rig.height);
    let sent = Encoding::Sparse
        .encode_image(&original, w, h)
        .expect("encodes");
    assert_eq!(
        Encoding::Sparse.decode_image(&sent, w, h).expect("decodes"),
        left
    );
    let again = offline_tracks(&recorded, &config, &tmp.path().join("again.csv"));
    assert_same_vectors(&report.refined, &again);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_client_written_from_the_spec_gets_the_offline_vectors() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::MovingHead, 40);
    let server = TestServer::start(ServerOptions::default()).await;
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = tmp.path().join("python.csv");
    let command = std::process::Command::new("python3")
        .arg(root.join("tests/python/headset_client.py"))
        .args(["--url", &server.ingest(), "--rec"])
        .arg(tmp.path().join("rec"))
        .arg("--out")
        .arg(&out)
        .args(["--convention", "unity", "--schemas"])
        .arg(root.join("protocol/schema"))
        .output();
    let output = tokio::task::spawn_blocking(move || command)
        .await
        .expect("joined")
        .expect("python3 runs (needs: pip install websockets jsonschema)");
    server.stop().await;
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    println!("{stdout}{stderr}");
    assert!(
        output.status.success(),
        "python client failed:\n{stdout}\n{stderr}"
    );
    let live = tables::read_tracks(&out).expect("python client's CSV");
    let offline = offline_tracks(&rec, &config, &tmp.path().join("offline.csv"));
    assert_eq!(live.len(), offline.len());
    assert!(!live.is_empty());
    for (a, b) in live.iter().zip(&offline) {
        assert_eq!((a.frame, a.track_id), (b.frame, b.track_id));
        for (x, y) in values(a).into_iter().zip(values(b)) {
            assert!((x - y).abs() <= 1e-6 * y.abs().max(1e-3), "{a:?} vs {b:?}");
        }
    }

    // The golden JSON messages satisfy the published schemas.
    let golden = std::process::Command::new("python3")
        .arg(root.join("tests/python/headset_client.py"))
        .arg("--check-golden")
        .arg(root.join("protocol/golden"))
        .arg("--schemas")
        .arg(root.join("protocol/schema"))
        .output()
        .expect("python3 runs");
    assert!(
        golden.status.success(),
        "golden check failed:\n{}\n{}",
        String::from_utf8_lossy(&golden.stdout),
        String::from_utf8_lossy(&golden.stderr)
    );
}

/// A malformed `sparse` image (truncated, a non-zero reserved byte, a block side of 0, a run
/// across rows) is `bad_image`, as the spec's error table says; the session lives on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_sparse_images_are_bad_image_and_the_session_lives_on() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, _) = synth(&tmp.path().join("rec"), Scenario::Flume, 2);
    let server = TestServer::start(ServerOptions::default()).await;
    let mut ws = connect(&server.ingest()).await;
    ws.send(hello(&rec, |v| v["image"]["encoding"] = "sparse".into()))
        .await
        .expect("sends");
    assert!(matches!(
        next_text(&mut ws).await,
        ServerMessage::Welcome { .. }
    ));
    let (w, h) = (rec.rig.width, rec.rig.height);
    let (left, right) = rec.load(&rec.frames[0]).expect("frame 0");
    let encode = |p: &[u8]| Encoding::Sparse.encode_image(p, w, h).expect("encodes");
    let (l, r) = (encode(&left), encode(&right));
    type Edit = fn(&mut Vec<u8>);
    let broken: [(&str, Edit); 4] = [
        ("truncated", |b| b.truncate(b.len() - 1)),
        ("reserved", |b| b[1] = 1),
        ("block side 0", |b| b[0] = 0),
        ("trailing byte", |b| b.push(0)),
    ];
    for (what, edit) in &broken {
        let mut bad = l.clone();
        edit(&mut bad);
        let m = expect_error(
            &mut ws,
            frame(0, 0.0, Encoding::Sparse, &bad, &r),
            ErrorCode::BadImage,
        )
        .await;
        assert!(m.contains("left"), "{what}: {m}");
    }
    ws.send(frame(0, 0.0, Encoding::Sparse, &l, &r))
        .await
        .expect("sends");
    assert_eq!(next_binary(&mut ws).await.frame_index, 0);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_messages_get_clear_errors_and_other_sessions_are_unaffected() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Flume, 40);
    let server = TestServer::start(ServerOptions::default()).await;
    // A well-behaved headset streams alongside throughout, sending PNG files as they are.
    let good = spawn_replay(
        &rec,
        ReplayOptions {
            encoding: Encoding::Png,
            ..replay_options(server.ingest(), &config)
        },
    );

    let mut ws = connect(&server.ingest()).await;
    let (left, right) = rec.load(&rec.frames[0]).expect("frame 0");
    let raw = |i, t| frame(i, t, Encoding::Raw8, &left, &right);
    expect_error(&mut ws, raw(0, 0.0), ErrorCode::NotReady).await;
    expect_error(
        &mut ws,
        Message::text("{not json"),
        ErrorCode::MalformedJson,
    )
    .await;
    expect_error(
        &mut ws,
        Message::text(r#"{"type":"launch"}"#),
        ErrorCode::UnknownType,
    )
    .await;
    expect_error(&mut ws, Message::text("[1,2]"), ErrorCode::UnknownType).await;
    let v2 = hello(&rec, |v| v["protocol"] = 2.into());
    expect_error(&mut ws, v2, ErrorCode::UnsupportedVersion).await;
    let singular = hello(&rec, |v| v["rig"]["K1"][0][0] = 0.0.into());
    let m = expect_error(&mut ws, singular, ErrorCode::BadCalibration).await;
    assert!(m.contains("K1"), "names the field: {m}");
    let size = hello(&rec, |v| v["image"]["width"] = 320.into());
    expect_error(&mut ws, size, ErrorCode::BadHello).await;
    let typo = hello(&rec, |v| v["convension"] = "unity".into());
    expect_error(&mut ws, typo, ErrorCode::BadHello).await;
    let config_typo = hello(&rec, |v| {
        v["config"] = serde_json::json!({"velocity": {"m": 3}})
    });
    expect_error(&mut ws, config_typo, ErrorCode::BadConfig).await;

    // The same connection can still open a session.
    ws.send(hello(&rec, |_| {})).await.expect("sends");
    assert!(matches!(
        next_text(&mut ws).await,
        ServerMessage::Welcome { .. }
    ));
    expect_error(&mut ws, hello(&rec, |_| {}), ErrorCode::AlreadyStarted).await;
    let Message::Binary(whole) = raw(0, 0.0) else {
        unreachable!()
    };
    let truncated = Message::binary(whole[..whole.len() - 7].to_vec());
    let m = expect_error(&mut ws, truncated, ErrorCode::BadFrame).await;
    assert!(m.contains("header announces"), "{m}");
    expect_error(
        &mut ws,
        Message::binary(b"MRPF".to_vec()),
        ErrorCode::BadFrame,
    )
    .await;
    expect_error(
        &mut ws,
        Message::binary(b"hello, server".to_vec()),
        ErrorCode::BadFrame,
    )
    .await;
    let small = frame(0, 0.0, Encoding::Raw8, &left[..1000], &right[..1000]);
    expect_error(&mut ws, small, ErrorCode::BadImage).await;
    let png = frame(0, 0.0, Encoding::Png, &left, &right);
    expect_error(&mut ws, png, ErrorCode::BadFrame).await;
    expect_error(&mut ws, raw(0, f64::NAN), ErrorCode::BadTimestamp).await;
    let edited = |edit: &dyn Fn(&mut Vec<u8>)| {
        let Message::Binary(b) = raw(0, 0.0) else {
            unreachable!()
        };
        let mut b = b.to_vec();
        edit(&mut b);
        Message::binary(b)
    };
    ws.send(edited(&|b| b[4] = 2)).await.expect("sends");
    match next_text(&mut ws).await {
        ServerMessage::Error {
            code, frame_index, ..
        } => assert_eq!(
            (code, frame_index),
            (ErrorCode::UnsupportedVersion, Some(0))
        ),
        other => panic!("{other:?}"),
    }
    expect_error(&mut ws, edited(&|b| b[6] = 2), ErrorCode::BadFrame).await;
    let mut scaled = encode_frame(&FrameMessage {
        encoding: Encoding::Raw8,
        frame_index: 0,
        t_s: 0.0,
        world_from_rig: Some(nalgebra::Isometry3::identity()),
        left: &left,
        right: &right,
    })
    .expect("encodes");
    scaled[32..40].copy_from_slice(&1.5f64.to_le_bytes()); // m00 = 1.5: not a rotation
    let m = expect_error(&mut ws, Message::binary(scaled), ErrorCode::BadFrame).await;
    assert!(m.contains("rigid"), "{m}");

    // A good frame gets its causal batch; the session survived all of the above.
    ws.send(raw(5, 1.0)).await.expect("sends");
    assert_eq!(next_binary(&mut ws).await.frame_index, 5);
    expect_error(&mut ws, raw(5, 2.0), ErrorCode::BadFrame).await;
    expect_error(&mut ws, raw(6, 0.5), ErrorCode::BadTimestamp).await;
    ws.send(raw(7, 1.5)).await.expect("sends");
    assert_eq!(next_binary(&mut ws).await.frame_index, 7);

    ws.send(Message::text(r#"{"type":"bye"}"#))
        .await
        .expect("sends");
    let bye = loop {
        match next_text(&mut ws).await {
            ServerMessage::Bye { counters, .. } => break counters.expect("counters"),
            ServerMessage::Error { message, .. } => panic!("unexpected error {message}"),
            _ => {}
        }
    };
    assert_eq!(bye.frames_processed, 2);
    assert_eq!(bye.frames_rejected, 11, "{bye:?}");

    let report = good.await.expect("good headset");
    assert!(report.errors.is_empty(), "{:?}", report.errors);
    assert_eq!(report.counters.map(|c| c.frames_processed), Some(40));
    // No poses: rig frame, said in every batch and vector.
    for b in report.causal.iter().chain(&report.refined) {
        assert!(!b.world);
        assert!(b.vectors.iter().all(|v| v.flags & 2 == 0));
    }
    let offline = offline_tracks(&rec, &config, &tmp.path().join("offline.csv"));
    assert_same_vectors(&report.refined, &offline);
    server.stop().await;
}

/// Reads a viewer until its session ends: the causal and refined batches received.
async fn watch_until_ended<S>(
    mut viewer: tokio_tungstenite::WebSocketStream<S>,
) -> (Vec<DecodedBatch>, Vec<DecodedBatch>)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin,
{
    let mut causal = Vec::new();
    let mut refined = Vec::new();
    loop {
        let m = tokio::time::timeout(Duration::from_secs(60), viewer.next())
            .await
            .expect("viewer gets messages")
            .expect("open")
            .expect("readable");
        match m {
            Message::Binary(b) => {
                let batch = decode_batch(&b).expect("batch");
                match batch.kind {
                    BatchKind::Causal => causal.push(batch),
                    BatchKind::Refined => refined.push(batch),
                }
            }
            Message::Text(t) => {
                if let Ok(ServerMessage::SessionEnded { .. }) = serde_json::from_str(t.as_str()) {
                    return (causal, refined);
                }
            }
            _ => {}
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewers_get_the_batches_and_a_stalled_viewer_slows_nothing() {
    let tmp = tempfile::tempdir().expect("tmp");
    // ~350 causal vectors per batch: a real load for the viewers.
    let frames = 40;
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Dense, frames);
    let server = TestServer::start(ServerOptions {
        viewer_buffer: 16,
        ..Default::default()
    })
    .await;

    let mut viewer = connect(&server.watch()).await;
    assert!(
        matches!(next_text(&mut viewer).await, ServerMessage::Sessions { sessions } if sessions.is_empty())
    );
    let unknown = Message::text(r#"{"type":"subscribe","session":"s99"}"#);
    expect_error(&mut viewer, unknown, ErrorCode::UnknownSession).await;
    viewer
        .send(Message::text(
            r#"{"type":"subscribe","session":"*","convention":"unity"}"#,
        ))
        .await
        .expect("subscribes");
    assert!(matches!(
        next_text(&mut viewer).await,
        ServerMessage::Subscribed {
            convention: Convention::Unity,
            ..
        }
    ));
    let reading = tokio::spawn(watch_until_ended(viewer));

    // This viewer subscribes, then stops reading, with a tiny receive buffer.
    let socket = tokio::net::TcpSocket::new_v4().expect("socket");
    socket.set_recv_buffer_size(4096).expect("small buffer");
    let tcp = socket.connect(server.addr).await.expect("connects");
    let (mut stalled, _) = tokio_tungstenite::client_async(server.watch(), tcp)
        .await
        .expect("handshake");
    stalled
        .send(Message::text(r#"{"type":"subscribe","session":"*"}"#))
        .await
        .expect("subscribes");

    let report = replay(&rec, &replay_options(server.ingest(), &config)).await;
    assert!(report.errors.is_empty() && report.dropped_frames.is_empty());
    assert_eq!(
        report.counters.map(|c| c.frames_processed),
        Some(frames as u64)
    );

    // The reading viewer got every batch the headset got, in its own convention.
    let (causal, refined) = reading.await.expect("viewer task");
    assert_eq!(causal.len(), frames);
    assert!(causal
        .iter()
        .chain(&refined)
        .all(|b| b.convention == Convention::Unity));
    let offline = offline_tracks(&rec, &config, &tmp.path().join("offline.csv"));
    assert_same_vectors(&refined, &offline);

    // Reading again, the stalled viewer gets the newest batches. (Whether it lost any depends on
    // the kernel's socket buffers; `server::watch`'s unit test makes a viewer lag for certain.)
    let (stalled_causal, _) = watch_until_ended(stalled).await;
    let seen: Vec<u64> = stalled_causal.iter().map(|b| b.frame_index).collect();
    println!("stalled viewer received causal batches of frames {seen:?}");
    assert_eq!(
        seen.last(),
        Some(&(frames as u64 - 1)),
        "newest wins: {seen:?}"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_headset_outrunning_its_session_loses_the_oldest_frames_and_is_told() {
    let tmp = tempfile::tempdir().expect("tmp");
    // 1000 particles: several milliseconds per frame, far slower than loopback delivery.
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Dense, 24);
    let server = TestServer::start(ServerOptions {
        queue_frames: 1,
        ..Default::default()
    })
    .await;
    let options = ReplayOptions {
        max_in_flight: 24,
        ..replay_options(server.ingest(), &config)
    };
    let report = replay(&rec, &options).await;
    server.stop().await;
    let c = report.counters.expect("counters");
    assert!(
        c.frames_dropped > 0,
        "queue of 1 and no flow control: {c:?}"
    );
    assert_eq!(c.frames_received, 24);
    assert_eq!(c.frames_processed + c.frames_dropped, 24, "{c:?}");
    assert_eq!(report.dropped_frames.len() as u64, c.frames_dropped);
    // Every frame was answered exactly once: a causal batch or a drop notice.
    assert_eq!(report.latencies_s.len() as u64, c.frames_processed);
    let mut answered: Vec<u64> = report.causal.iter().map(|b| b.frame_index).collect();
    answered.extend(&report.dropped_frames);
    answered.sort_unstable();
    assert_eq!(answered, (0..24).collect::<Vec<_>>());
    // Oldest first: the newest frame is never the one dropped.
    assert!(!report.dropped_frames.contains(&23));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_processes_queued_frames_says_bye_and_leaves_complete_recordings() {
    let tmp = tempfile::tempdir().expect("tmp");
    // Slow frames (1000 particles) sent 4 at a time: the queue holds frames when the stop comes.
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Dense, 80);
    let record_dir = tmp.path().join("live");
    let server = TestServer::start(ServerOptions {
        record_dir: Some(record_dir.clone()),
        ..Default::default()
    })
    .await;
    let options = ReplayOptions {
        max_in_flight: 4,
        ..replay_options(server.ingest(), &config)
    };
    let streaming = spawn_replay(&rec, options);
    let mut viewer = connect(&server.watch()).await;
    viewer
        .send(Message::text(r#"{"type":"subscribe","session":"*"}"#))
        .await
        .expect("subscribes");
    // Stop once enough frames for centred vectors are processed, however fast this machine is.
    let mut processed = 0;
    for _ in 0..600 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        let listed = http_get(&format!("http://{}/v1/sessions", server.addr)).await;
        let sessions: serde_json::Value = serde_json::from_str(&listed).expect("sessions json");
        let s1 = sessions["sessions"]
            .as_array()
            .and_then(|all| all.iter().find(|s| s["id"] == "s1"));
        processed = s1.map_or(0, |s| {
            s["counters"]["frames_processed"].as_u64().unwrap_or(0)
        });
        if processed >= 20 {
            break;
        }
    }
    assert!(processed >= 20, "the session processed {processed} frames");
    let health = http_get(&format!("http://{}/healthz", server.addr)).await;
    assert!(health.contains(r#""status":"ok""#), "{health}");
    server.stop().await;

    let report = streaming.await.expect("replay task");
    assert_eq!(report.bye_reason.as_deref(), Some("server shutting down"));
    let c = report.counters.expect("counters");
    assert!(c.frames_processed >= 20 && c.frames_processed < 80, "{c:?}");
    // Every frame the server took was processed, answered and recorded before it said bye.
    assert_eq!(c.frames_processed, c.frames_received, "{c:?}");
    assert_eq!(report.latencies_s.len() as u64, c.frames_processed);
    let recorded = Recording::open(&the_only_subdir(&record_dir)).expect("complete recording");
    assert_eq!(recorded.frames.len() as u64, c.frames_processed);
    let again = offline_tracks(&recorded, &config, &tmp.path().join("again.csv"));
    assert_same_vectors(&report.refined, &again);
    // The viewer got the session's end before its own bye.
    let mut ended = false;
    loop {
        match next_text(&mut viewer).await {
            ServerMessage::SessionEnded { .. } => ended = true,
            ServerMessage::Bye { reason, .. } => {
                assert_eq!(reason, "server shutting down");
                break;
            }
            _ => {}
        }
    }
    assert!(ended, "session_ended before the viewer's bye");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_headset_vanishing_without_bye_still_gets_its_frames_processed_and_recorded() {
    let tmp = tempfile::tempdir().expect("tmp");
    // Slow frames (1000 particles), so that some are still queued when the headset vanishes.
    let (rec, _) = synth(&tmp.path().join("rec"), Scenario::Dense, 12);
    let record_dir = tmp.path().join("live");
    let server = TestServer::start(ServerOptions {
        record_dir: Some(record_dir.clone()),
        queue_frames: 16,
        ..Default::default()
    })
    .await;
    let mut ws = connect(&server.ingest()).await;
    ws.send(hello(&rec, |_| {})).await.expect("hello");
    assert!(matches!(
        next_text(&mut ws).await,
        ServerMessage::Welcome { .. }
    ));
    for entry in &rec.frames {
        let (left, right) = rec.load(entry).expect("frame");
        ws.send(frame(entry.index, entry.t_s, Encoding::Raw8, &left, &right))
            .await
            .expect("sends");
    }
    // Frames on the wire are only the server's once it has read them (a vanishing peer's
    // connection may be reset, dropping unread bytes): wait until all 12 are received.
    let sessions_url = format!("http://{}/v1/sessions", server.addr);
    let mut waited = 0;
    let processed_at_vanish = loop {
        let listed = http_get(&sessions_url).await;
        let value: serde_json::Value = serde_json::from_str(&listed).expect("JSON");
        let counters = &value["sessions"][0]["counters"];
        if counters["frames_received"] == 12 {
            break counters["frames_processed"].as_u64().unwrap_or(0);
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
        waited += 1;
        assert!(waited < 4000, "the server receives the frames: {listed}");
    };
    // Gone mid-stream: no bye, no close handshake.
    drop(ws);
    println!("{processed_at_vanish} of 12 frames processed when the headset vanished");
    let mut waited = 0;
    while http_get(&sessions_url).await.contains(r#""id":"s1""#) {
        tokio::time::sleep(Duration::from_millis(50)).await;
        waited += 1;
        assert!(waited < 400, "the session ends after its headset vanished");
    }
    let recorded = Recording::open(&the_only_subdir(&record_dir)).expect("complete recording");
    assert_eq!(
        recorded.frames.len(),
        12,
        "every frame received was processed and recorded"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewers_list_subscribe_by_id_and_unsubscribe() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Flume, 150);
    let server = TestServer::start(ServerOptions::default()).await;
    let streaming = spawn_replay(
        &rec,
        ReplayOptions {
            rate: Rate::Recorded,
            ..replay_options(server.ingest(), &config)
        },
    );
    let mut viewer = connect(&server.watch()).await;
    let id = loop {
        viewer
            .send(Message::text(r#"{"type":"list"}"#))
            .await
            .expect("lists");
        if let ServerMessage::Sessions { sessions } = next_text(&mut viewer).await {
            if let Some(s) = sessions.first() {
                assert_eq!(s.session.client, "mrptv-replay 0.1.0");
                break s.session.id.clone();
            }
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let subscribe = format!(r#"{{"type":"subscribe","session":"{id}","convention":"opencv"}}"#);
    viewer
        .send(Message::text(subscribe))
        .await
        .expect("subscribes");
    loop {
        if let ServerMessage::Subscribed {
            session,
            convention,
            ..
        } = next_text(&mut viewer).await
        {
            assert_eq!(
                (session.as_str(), convention),
                (id.as_str(), Convention::OpenCv)
            );
            break;
        }
    }
    let batch = next_binary(&mut viewer).await;
    assert_eq!(
        (batch.session_number, batch.convention),
        (1, Convention::OpenCv)
    );
    // age_us covers queue wait, decode and pipeline, so it is at least the pipeline time.
    assert!(
        batch.age_us >= batch.processing_us && batch.age_us > 0,
        "age {} us, processing {} us",
        batch.age_us,
        batch.processing_us
    );
    // A ping is answered with its id, between batches.
    viewer
        .send(Message::text(
            r#"{"type":"ping","id":18446744073709551615}"#,
        ))
        .await
        .expect("pings");
    loop {
        if let ServerMessage::Pong { id } = next_text(&mut viewer).await {
            assert_eq!(id, u64::MAX);
            break;
        }
    }
    let info = http_get(&format!("http://{}/v1/sessions", server.addr)).await;
    assert!(info.contains(r#""viewers":1"#), "{info}");
    viewer
        .send(Message::text(r#"{"type":"unsubscribe"}"#))
        .await
        .expect("unsubscribes");
    loop {
        match tokio::time::timeout(Duration::from_secs(20), viewer.next())
            .await
            .expect("reply")
            .expect("open")
            .expect("readable")
        {
            Message::Text(t) if t.as_str().contains("unsubscribed") => break,
            _ => {}
        }
    }
    // Unsubscribed: batches stop (within what was already on its way).
    let quiet = tokio::time::timeout(Duration::from_millis(500), async {
        loop {
            if let Some(Ok(Message::Binary(_))) = viewer.next().await {
                continue;
            }
        }
    });
    let _ = quiet.await;
    let info = http_get(&format!("http://{}/v1/sessions", server.addr)).await;
    assert!(info.contains(r#""viewers":0"#), "{info}");
    let more = tokio::time::timeout(Duration::from_millis(300), viewer.next()).await;
    assert!(
        !matches!(more, Ok(Some(Ok(Message::Binary(_))))),
        "no batches after unsubscribing"
    );
    server.stop().await;
    let report = streaming.await.expect("replay");
    assert_eq!(report.bye_reason.as_deref(), Some("server shutting down"));
}

/// A viewer asking for uncertainties gets each vector's velocity errors (those of `tracks.csv`,
/// to float32 rounding), and the session's mean-flow field as it accumulates; `reset_field`
/// empties it. A headset asking for them in `hello` gets them in its own batches.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewers_get_uncertainties_and_the_mean_flow_field_and_can_reset_it() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Flume, 240);
    let offline = offline_tracks(&rec, &config, &tmp.path().join("offline.csv"));
    let sigma_of: std::collections::HashMap<(u64, u64), [f64; 3]> = offline
        .iter()
        .map(|r| {
            let (sv, _) = r.sigma.expect("tracks carry sigmas");
            ((r.frame, r.track_id), [sv.x, sv.y, sv.z])
        })
        .collect();
    let options = ServerOptions {
        field: mrptv::server::FieldOptions {
            interval: Duration::from_millis(200),
            ..Default::default()
        },
        ..Default::default()
    };
    let server = TestServer::start(options).await;
    let mut viewer = connect(&server.watch()).await;
    viewer
        .send(Message::text(
            r#"{"type":"subscribe","session":"*","convention":"webxr","uncertainty":true}"#,
        ))
        .await
        .expect("subscribes");
    match next_text(&mut viewer).await {
        ServerMessage::Sessions { .. } => {}
        other => panic!("sessions first, got {other:?}"),
    }
    assert!(matches!(
        next_text(&mut viewer).await,
        ServerMessage::Subscribed {
            uncertainty: true,
            ..
        }
    ));
    let streaming = spawn_replay(
        &rec,
        ReplayOptions {
            rate: Rate::Recorded,
            ..replay_options(server.ingest(), &config)
        },
    );
    let mut compared = 0;
    // Samples of each field before the reset was answered, and after.
    let (mut before, mut after) = (Vec::new(), Vec::new());
    let mut reset_answered = false;
    while after.len() < 3 {
        let m = tokio::time::timeout(Duration::from_secs(30), viewer.next())
            .await
            .expect("a message within 30 s")
            .expect("open")
            .expect("readable");
        match m {
            Message::Binary(b) => {
                let batch = decode_batch(&b).expect("batch");
                assert_eq!(b[7] & 2, 2, "uncertainty flag set");
                assert_eq!(b.len(), 40 + 52 * batch.vectors.len());
                if batch.kind != BatchKind::Refined {
                    continue;
                }
                for v in &batch.vectors {
                    let sigma = v.velocity_sigma.expect("sigmas");
                    let truth = sigma_of[&(batch.frame_index, v.track_id)];
                    for k in 0..3 {
                        assert_eq!(sigma[k], truth[k] as f32, "sigma of track {}", v.track_id);
                    }
                    compared += 1;
                }
            }
            Message::Text(t) => match serde_json::from_str(t.as_str()).expect("JSON") {
                ServerMessage::Field(field) => {
                    assert_eq!(field.session, "s1");
                    assert_eq!(
                        field.columns[..10].join(","),
                        "x,y,z,n,u,v,w,std_u,std_v,std_w"
                    );
                    assert!(field.cell_m > 0.0 && !field.cells.is_empty() && !field.truncated);
                    let counted: f64 = field.cells.iter().map(|c| c[3]).sum();
                    assert_eq!(counted as u64, field.samples, "every sample in one cell");
                    if reset_answered {
                        after.push(field.samples);
                    } else {
                        if before.is_empty() {
                            viewer
                                .send(Message::text(r#"{"type":"reset_field","session":"s1"}"#))
                                .await
                                .expect("resets");
                        }
                        before.push(field.samples);
                    }
                }
                ServerMessage::FieldReset { sessions } => {
                    assert_eq!(sessions, vec!["s1".to_string()]);
                    reset_answered = true;
                }
                _ => {}
            },
            _ => {}
        }
    }
    assert!(compared > 100, "{compared} vectors' sigmas compared");
    // The field started again (one field sent before the reset took effect may still come
    // after its answer): a field of fewer samples than it had grown to, then growing.
    let grown = before
        .iter()
        .copied()
        .max()
        .expect("a field before the reset");
    let restart = after
        .iter()
        .position(|&n| n < grown)
        .unwrap_or_else(|| panic!("no field restarted after the reset: {before:?} then {after:?}"));
    assert!(
        after[restart..].windows(2).all(|w| w[0] <= w[1]),
        "{before:?} then {after:?}"
    );
    expect_error(
        &mut viewer,
        Message::text(r#"{"type":"reset_field","session":"s9"}"#),
        ErrorCode::UnknownSession,
    )
    .await;
    streaming.await.expect("replay");

    // A headset asking for them in its hello.
    let mut headset = connect(&server.ingest()).await;
    headset
        .send(hello(&rec, |h| h["uncertainty"] = serde_json::json!(true)))
        .await
        .expect("hello");
    assert!(matches!(
        next_text(&mut headset).await,
        ServerMessage::Welcome { .. }
    ));
    let mut with_vectors = 0;
    for (i, entry) in rec.frames.iter().take(40).enumerate() {
        let (left, right) = rec.load(entry).expect("frame");
        headset
            .send(frame(
                i as u64,
                entry.t_s,
                mrptv::protocol::Encoding::Raw8,
                &left,
                &right,
            ))
            .await
            .expect("frame");
        loop {
            let m = tokio::time::timeout(Duration::from_secs(20), headset.next())
                .await
                .expect("answer")
                .expect("open")
                .expect("readable");
            if let Message::Binary(b) = m {
                let batch = decode_batch(&b).expect("batch");
                assert_eq!(b[7] & 2, 2, "the headset's batches carry sigmas");
                with_vectors +=
                    usize::from(batch.vectors.iter().any(|v| v.velocity_sigma.is_some()));
                if batch.kind == BatchKind::Causal {
                    break;
                }
            }
        }
    }
    assert!(with_vectors > 10, "{with_vectors} batches with sigmas");
    server.stop().await;
}

/// A headset with no config, streaming flow too fast for the published linking box (45-75 px
/// per frame): the session learns the particles' steps from the images and gives centred vectors
/// within its first second of frames (30 frames at 30 Hz, the centred window's latency included).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_on_fast_flow_gives_vectors_within_its_first_second() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, _) = synth(&tmp.path().join("rec"), Scenario::Fast, 30);
    let server = TestServer::start(ServerOptions::default()).await;
    let options = ReplayOptions {
        config: None,
        ..replay_options(server.ingest(), &PipelineConfig::default())
    };
    let report = replay(&rec, &options).await;
    server.stop().await;
    assert!(report.errors.is_empty(), "{:?}", report.errors);
    assert_eq!(report.frames_sent, 30);
    let m = PipelineConfig::default().velocity.half_window_frames as u64;
    let centred: usize = report
        .refined
        .iter()
        .filter(|b| b.frame_index + m < 30)
        .map(|b| b.vectors.len())
        .sum();
    let first = report
        .refined
        .iter()
        .find(|b| !b.vectors.is_empty())
        .map(|b| b.frame_index);
    println!("centred vectors for the first second: {centred}, first at frame {first:?}");
    assert!(
        centred >= 100,
        "only {centred} centred vectors in the first second"
    );
    assert!(
        first.is_some_and(|f| f <= 5),
        "first centred vector at {first:?}"
    );
}
