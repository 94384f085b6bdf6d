//! The real `mrptv serve` process stopped by signals while a headset streams:
//! - SIGTERM: graceful; the recording and the `.rrd` are complete and every frame the session
//!   processed is in them;
//! - SIGKILL: no chance to clean up; the recording still opens, and every frame the server
//!   acknowledged as recorded (`recorded`) is in it and reads back intact.

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use mrptv::client::{Rate, ReplayOptions};
use mrptv::protocol::{Encoding, ServerMessage};
use mrptv::recording::Recording;
use mrptv_engine::synth::Scenario;
use tokio_tungstenite::tungstenite::Message;

mod common;
use common::*;

fn signal(pid: u32, name: &str) {
    let status = Command::new("kill")
        .args([format!("-{name}"), pid.to_string()])
        .status()
        .expect("kill runs");
    assert!(status.success(), "kill -{name} {pid}");
}

/// Every frame `frames.csv` lists loads, at the rig's size.
fn assert_readable(dir: &Path) -> Recording {
    let rec = Recording::open(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    for entry in &rec.frames {
        let (l, r) = rec
            .load(entry)
            .unwrap_or_else(|e| panic!("frame {}: {e}", entry.index));
        assert_eq!(l.len(), (rec.rig.width * rec.rig.height) as usize);
        assert_eq!(r.len(), l.len());
    }
    rec
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_mid_stream_leaves_a_complete_recording_and_rrd() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Flume, 300);
    let (record, rrd) = (tmp.path().join("recorded"), tmp.path().join("rrd"));
    let rerun_sink = format!("file:{}", rrd.display());
    let server = ServeProcess::start(&[
        "--record",
        record.to_str().expect("utf8"),
        "--rerun",
        &rerun_sink,
    ]);
    let url = format!("{}/v1/ingest", server.base.replace("http://", "ws://"));
    // 300 frames at 30 Hz: 10 s; the signal comes after about 1.5 s.
    let streaming = spawn_replay(
        &rec,
        ReplayOptions {
            rate: Rate::Recorded,
            ..replay_options(url, &config)
        },
    );
    tokio::time::sleep(Duration::from_millis(1500)).await;
    signal(server.child.id(), "TERM");
    let report = streaming.await.expect("replay ends with the server's bye");
    assert_eq!(report.bye_reason.as_deref(), Some("server shutting down"));
    let counters = report.counters.expect("final counters");
    assert!(
        counters.frames_processed > 10 && counters.frames_processed < 300,
        "{counters:?}"
    );
    let mut server = server;
    let status = tokio::task::spawn_blocking(move || {
        let status = server.child.wait().expect("waits");
        (status, server)
    })
    .await
    .expect("wait task")
    .0;
    assert!(status.success(), "graceful exit: {status}");

    let recorded = assert_readable(&the_only_subdir(&record));
    assert_eq!(recorded.frames.len() as u64, counters.frames_processed);
    assert_eq!(counters.frames_recorded, counters.frames_processed);
    assert_eq!(
        report.recorded_through,
        recorded.frames.last().map(|f| f.index),
        "the last acknowledgement covers the last frame"
    );
    let rrd_file = std::fs::read_dir(&rrd)
        .expect("rrd dir")
        .map(|e| e.expect("entry").path())
        .find(|p| p.extension().is_some_and(|e| e == "rrd"))
        .expect("an .rrd");
    assert_rrd_verified(&rrd_file);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_keeps_every_frame_acknowledged_as_recorded() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, _) = synth(&tmp.path().join("rec"), Scenario::Flume, 200);
    let record = tmp.path().join("recorded");
    let server = ServeProcess::start(&["--record", record.to_str().expect("utf8")]);
    let url = format!("{}/v1/ingest", server.base.replace("http://", "ws://"));
    let mut ws = connect(&url).await;
    ws.send(hello(&rec, |_| {})).await.expect("hello");
    assert!(matches!(
        next_text(&mut ws).await,
        ServerMessage::Welcome { .. }
    ));
    let (mut sink, mut stream) = ws.split();
    let frames: Vec<_> = rec
        .frames
        .iter()
        .map(|e| {
            let (l, r) = rec.load(e).expect("frame");
            frame(e.index, e.t_s, Encoding::Raw8, &l, &r)
        })
        .collect();
    let sender = tokio::spawn(async move {
        for f in frames {
            if sink.send(f).await.is_err() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    });
    let mut acknowledged = None;
    let mut acks = 0;
    while let Some(Ok(m)) = stream.next().await {
        if let Message::Text(t) = m {
            if let Ok(ServerMessage::Recorded {
                through_frame_index,
                frames_recorded,
                ..
            }) = serde_json::from_str(t.as_str())
            {
                assert!(
                    acknowledged < Some(through_frame_index),
                    "acks move forward"
                );
                acknowledged = Some(through_frame_index);
                acks += 1;
                if frames_recorded >= 40 {
                    break;
                }
            }
        }
    }
    // Killed while frames are still arriving, being processed and being written.
    signal(server.child.id(), "KILL");
    sender.abort();
    let acknowledged = acknowledged.expect("acknowledgements arrived");
    assert!(acks > 5, "acknowledged as they were synced: {acks} acks");
    let mut server = server;
    let _ = tokio::task::spawn_blocking(move || server.child.wait())
        .await
        .expect("wait task");

    let recorded = assert_readable(&the_only_subdir(&record));
    let indices: Vec<u64> = recorded.frames.iter().map(|f| f.index).collect();
    let expected: Vec<u64> = (0..=acknowledged).collect();
    assert_eq!(
        &indices[..expected.len().min(indices.len())],
        &expected[..],
        "every acknowledged frame, in order, none missing"
    );
    assert!(indices.len() as u64 > acknowledged);
    // What is there is what was sent.
    for entry in &recorded.frames {
        let original = &rec.frames[entry.index as usize];
        assert_eq!(entry.t_s, original.t_s);
        assert_eq!(
            recorded.load(entry).expect("recorded"),
            rec.load(original).expect("original"),
            "frame {}",
            entry.index
        );
    }
}
