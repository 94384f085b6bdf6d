//! Rerun output checked with Rerun's own tool: the `rerun` CLI of the PyPI `rerun-sdk` of the
//! same version (`pip install -r tests/python/requirements.txt`) must verify every `.rrd` we
//! write, and `rerun rrd print` must list the documented entities with a row per frame.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use mrptv::client::{self, Rate, RecordingSource, ReplayOptions};
use mrptv::offline;
use mrptv::recording::Recording;
use mrptv::rerun_log::{RerunOptions, RerunSink};
use mrptv::server::{self, ServerOptions};
use mrptv_engine::synth::{Scenario, ScenarioSpec};
use mrptv_engine::PipelineConfig;

mod common;
use common::assert_rrd_verified;

fn mrptv() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mrptv"))
}

fn rerun_cli() -> Command {
    Command::new("rerun")
}

fn synth(dir: &Path, frames: usize) -> Recording {
    let spec = ScenarioSpec::new(Scenario::Flume);
    let particles = spec.default_particles;
    offline::write_synthetic(spec, dir, frames, particles, 5, |_| {}).expect("synth");
    Recording::open(dir).expect("recording")
}

/// Rows per entity and archetype (`/world/points@Points3D`) of the recording (blueprint entities
/// left out), from `rerun rrd print`.
fn rows_per_entity(rrd: &Path) -> BTreeMap<String, u64> {
    let out = rerun_cli()
        .args(["rrd", "print"])
        .arg(rrd)
        .output()
        .expect("rerun rrd print runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut rows: BTreeMap<String, u64> = BTreeMap::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        // Chunk(chunk_...) with 3 rows (1.4 KiB) - /world/points - data columns: [Points3D:positions ...]
        let Some(rest) = line.trim_start().strip_prefix("Chunk(") else {
            continue;
        };
        let Some((_, after)) = rest.split_once(") with ") else {
            continue;
        };
        let n: u64 = after
            .split_whitespace()
            .next()
            .and_then(|n| n.parse().ok())
            .expect("row count");
        let mut parts = after.split(" - ");
        let _size = parts.next();
        let entity = parts.next().expect("entity path").trim().to_string();
        let columns = parts.next().unwrap_or_default();
        // "data columns: [Points3D:positions Points3D:radii]"
        let archetype = columns
            .split_once('[')
            .and_then(|(_, c)| c.split(':').next())
            .unwrap_or_default();
        // `rrd print` lists the blueprint's chunks among the recording's: leave them out by path.
        let blueprint = ["/viewport", "/view/", "/container/", "/__properties"]
            .iter()
            .any(|p| entity.starts_with(p))
            || entity.ends_with("_panel");
        if blueprint {
            continue;
        }
        *rows.entry(format!("{entity}@{archetype}")).or_default() += n;
    }
    rows
}

fn rows(map: &BTreeMap<String, u64>, entity: &str) -> u64 {
    map.get(entity).copied().unwrap_or(0)
}

#[test]
fn process_writes_an_rrd_that_rerun_reads_with_every_entity() {
    let tmp = tempfile::tempdir().expect("tmp");
    let frames = 30;
    synth(&tmp.path().join("rec"), frames);
    let rrd = tmp.path().join("run.rrd");
    let out = mrptv()
        .arg("process")
        .arg(tmp.path().join("rec"))
        .arg("--out")
        .arg(tmp.path().join("tracks.csv"))
        .arg("--field")
        .arg(tmp.path().join("field.csv"))
        .arg("--rerun")
        .arg(format!("file:{}", rrd.display()))
        .args(["--rerun-images-every", "10"])
        .output()
        .expect("runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_rrd_verified(&rrd);
    let entities = rows_per_entity(&rrd);
    println!("{entities:#?}");
    let m = PipelineConfig::default().velocity.half_window_frames as u64;
    let n = frames as u64;
    for (entity, expected) in [
        // Static: calibration, axes, legend, plot styles.
        ("/world@ViewCoordinates", 1),
        ("/world/rig/left@Pinhole", 1),
        ("/world/rig/left@Transform3D", 1),
        ("/world/rig/right@Pinhole", 1),
        ("/world/rig/right@Transform3D", 1),
        ("/legend@TextDocument", 1),
        ("/plots/matches@SeriesLines", 1),
        // A row per frame.
        ("/world/rig@Transform3D", n),
        ("/world/rig/left/detections@Points2D", n),
        ("/world/rig/right/detections@Points2D", n),
        ("/world/points@Points3D", n),
        ("/world/tracks@LineStrips3D", n),
        ("/world/vectors_live@Arrows3D", n),
        ("/plots/matches@Scalars", n),
        ("/plots/detections/left@Scalars", n),
        ("/plots/detections/right@Scalars", n),
        ("/plots/tracks@Scalars", n),
        ("/plots/vectors@Scalars", n),
        ("/plots/processing_ms@Scalars", n),
        // Refined vectors from the (M+1)-th frame on; images every 10th frame.
        ("/world/vectors@Arrows3D", n - m),
        ("/world/rig/left/image@Image", 3),
        ("/world/rig/right/image@Image", 3),
        // The mean-flow field of --field, once, at the last frame with vectors.
        ("/world/field@Arrows3D", 1),
    ] {
        assert_eq!(rows(&entities, entity), expected, "{entity}");
    }
    assert_eq!(
        rows(&entities, "/plots/latency_ms@Scalars"),
        0,
        "offline: no latency"
    );
}

#[test]
fn a_viewer_that_is_not_there_does_not_stop_processing() {
    let tmp = tempfile::tempdir().expect("tmp");
    synth(&tmp.path().join("rec"), 12);
    let run = |extra: &[&str], out: &Path| {
        let o = mrptv()
            .arg("process")
            .arg(tmp.path().join("rec"))
            .arg("--out")
            .arg(out)
            .args(extra)
            .output()
            .expect("runs");
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        std::fs::read(out).expect("tracks.csv")
    };
    let plain = run(&[], &tmp.path().join("plain.csv"));
    // Nothing listens on port 9: the sink fails, the run does not.
    let logged = run(
        &["--rerun", "connect:rerun+http://127.0.0.1:9/proxy"],
        &tmp.path().join("logged.csv"),
    );
    assert_eq!(plain, logged);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_logs_each_session_to_its_own_rrd() {
    let tmp = tempfile::tempdir().expect("tmp");
    let frames = 20;
    let rec = synth(&tmp.path().join("rec"), frames);
    let dir = tmp.path().join("rrd");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("port 0");
    let addr = listener.local_addr().expect("addr");
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(server::run(
        listener,
        ServerOptions {
            rerun: Some(RerunOptions {
                sinks: vec![RerunSink::File(dir.clone())],
                images_every: 5,
                ..Default::default()
            }),
            // The field on every frame with refined vectors.
            field: mrptv::server::FieldOptions {
                cell_m: Some(0.05),
                interval: Duration::ZERO,
                ..Default::default()
            },
            ..Default::default()
        },
        async {
            let _ = stopped.await;
        },
    ));
    let options = ReplayOptions {
        rate: Rate::Max,
        config: Some(PipelineConfig::default()),
        ..ReplayOptions::new(format!("ws://{addr}/v1/ingest"))
    };
    for _ in 0..2 {
        let source = RecordingSource::new(rec.clone(), options.encoding);
        let report = tokio::time::timeout(
            Duration::from_secs(60),
            client::replay(source, &options, std::future::pending(), |_| {}),
        )
        .await
        .expect("replay finishes")
        .expect("replay succeeds");
        assert!(report.errors.is_empty(), "{:?}", report.errors);
    }
    let _ = stop.send(());
    server.await.expect("server task").expect("server ran");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("rrd dir")
        .map(|e| e.expect("entry").path())
        .collect();
    files.sort();
    assert_eq!(files.len(), 2, "one .rrd per session: {files:?}");
    for file in &files {
        assert!(
            file.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with('s') && n.ends_with(".rrd")),
            "{file:?}"
        );
        let rrd = file.clone();
        tokio::task::spawn_blocking(move || assert_rrd_verified(&rrd))
            .await
            .expect("verified");
        let rrd = file.clone();
        let entities = tokio::task::spawn_blocking(move || rows_per_entity(&rrd))
            .await
            .expect("printed");
        assert_eq!(rows(&entities, "/plots/latency_ms@Scalars"), frames as u64);
        assert_eq!(
            rows(&entities, "/world/vectors_live@Arrows3D"),
            frames as u64
        );
        assert_eq!(rows(&entities, "/world/rig/left/image@Image"), 4);
        let m = PipelineConfig::default().velocity.half_window_frames as u64;
        assert_eq!(
            rows(&entities, "/world/field@Arrows3D"),
            frames as u64 - m,
            "the live field, logged with each refined frame"
        );
    }
}

/// Runs a recording through `process_recording` logging to `sinks`; the logger's summary.
fn process_logged(
    rec: &Recording,
    sinks: &[RerunSink],
    out: &Path,
) -> mrptv::rerun_log::RerunSummary {
    let logger =
        mrptv::rerun_log::RerunLogger::start("test", sinks, &rec.rig, &RerunOptions::default())
            .expect("logger starts");
    let mut file = std::fs::File::create(out).expect("create");
    offline::process_recording(
        rec,
        PipelineConfig::default(),
        offline::ProcessSinks {
            tracks: offline::Sink {
                path: out,
                writer: &mut file,
            },
            points: None,
            rerun: Some(&logger),
        },
        |_| {},
    )
    .expect("processing");
    logger.finish()
}

#[test]
fn serve_sink_runs_a_grpc_server_that_takes_the_log() {
    let tmp = tempfile::tempdir().expect("tmp");
    let rec = synth(&tmp.path().join("rec"), 10);
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let mut sinks = vec![RerunSink::Serve(port)];
    let proxy = mrptv::rerun_log::start_proxy(&mut sinks)
        .expect("serves")
        .expect("a proxy");
    assert_eq!(
        sinks,
        vec![RerunSink::Connect(format!(
            "rerun+http://127.0.0.1:{port}/proxy"
        ))]
    );
    // The same port cannot be served twice: a clear error, not a silent failure.
    assert!(mrptv::rerun_log::RerunProxy::start(port).is_err());
    let summary = process_logged(&rec, &sinks, &tmp.path().join("a.csv"));
    assert!(
        summary.flushed,
        "everything reached the server: {summary:?}"
    );
    assert_eq!(summary.frames_logged, 10);
    drop(proxy);
    // Nobody there any more: the flush says so, and the run still completes.
    let summary = process_logged(&rec, &sinks, &tmp.path().join("b.csv"));
    assert!(!summary.flushed, "{summary:?}");
    assert_eq!(summary.frames_logged, 10);
}
