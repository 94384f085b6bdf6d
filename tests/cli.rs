//! The `mrptv` binary end to end: synth -> process -> eval, determinism, and clear errors on bad
//! input (each names the file and what is wrong, exits non-zero, and never panics).

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn mrptv(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_mrptv"))
        .args(args)
        .output()
        .expect("binary runs")
}

fn ok(args: &[&str]) -> String {
    let out = mrptv(args);
    assert!(
        out.status.success(),
        "mrptv {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Runs a command that must fail; returns its stderr.
fn fails(args: &[&str]) -> String {
    let out = mrptv(args);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "mrptv {args:?} should fail");
    assert!(
        !stderr.contains("panicked"),
        "mrptv {args:?} panicked: {stderr}"
    );
    stderr
}

fn synth(dir: &Path, scenario: &str, frames: &str) -> PathBuf {
    let rec = dir.join(scenario);
    ok(&[
        "synth",
        scenario,
        rec.to_str().expect("utf8"),
        "--frames",
        frames,
        "--seed",
        "3",
    ]);
    rec
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf8 path")
}

#[test]
fn synth_process_eval_round_trip_is_deterministic() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = synth(dir.path(), "moving-head", "40");
    let header = fs::read_to_string(rec.join("frames.csv")).expect("frames");
    assert!(
        header.starts_with("index,t_s,world_from_rig_00,"),
        "pose columns written"
    );
    assert!(fs::read_to_string(rec.join("truth.csv"))
        .expect("truth")
        .starts_with("frame,t_s,pid,x,y,z,u,v,w\n"));
    let (t1, t2, p1, p2) = ["t1.csv", "t2.csv", "p1.csv", "p2.csv"]
        .map(|n| dir.path().join(n))
        .into();
    ok(&["process", s(&rec), "--out", s(&t1), "--points", s(&p1)]);
    ok(&["process", s(&rec), "--out", s(&t2), "--points", s(&p2)]);
    let (a, b) = (fs::read(&t1).expect("t1"), fs::read(&t2).expect("t2"));
    assert_eq!(a, b, "same recording and config, byte-identical tracks");
    assert_eq!(fs::read(&p1).expect("p1"), fs::read(&p2).expect("p2"));
    let tracks = String::from_utf8(a).expect("utf8");
    // The first nine columns keep their names and order; the uncertainties follow.
    assert!(tracks.starts_with("frame,t_s,track_id,x,y,z,u,v,w,su,sv,sw,sx,sy,sz\n"));
    assert!(tracks.lines().count() > 100, "vectors written");
    let points = fs::read_to_string(&p1).expect("points");
    assert!(points.starts_with("frame,t_s,x,y,z,xl,yl,xr,yr\n"));

    let json = ok(&[
        "eval",
        s(&rec.join("truth.csv")),
        s(&t1),
        "--json",
        "--window",
        "5",
    ]);
    let report: serde_json::Value = serde_json::from_str(&json).expect("json report");
    assert!(report["association_rate"].as_f64().expect("number") > 0.95);
    let text = ok(&["eval", s(&rec.join("truth.csv")), s(&t1)]);
    assert!(text.contains("ghost rate") && text.contains("by depth"));
    // The truth sits in its recording: the loss budget follows every measurable particle-frame
    // to one fate, and "measured" ones are among the associated.
    let budget = &report["loss_budget"];
    let rows: Vec<u64> = budget["losses"]
        .as_array()
        .expect("losses")
        .iter()
        .map(|l| l["rows"].as_u64().expect("rows"))
        .collect();
    assert_eq!(rows.len(), 9, "{budget}");
    assert_eq!(
        rows.iter().sum::<u64>(),
        budget["measurable"].as_u64().expect("n")
    );
    assert!(rows[8] > 0 && rows[8] <= report["associated_rows"].as_u64().expect("assoc"));
    assert!(text.contains("loss budget: ") && text.contains("3D track broken in the window"));
    let plain = ok(&["eval", s(&rec.join("truth.csv")), s(&t1), "--no-budget"]);
    assert!(!plain.contains("loss budget"), "{plain}");

    // A truth with further columns (another generator's, saying which images show each
    // particle) is read; hiding a particle from one image takes it out of the measurable set.
    let truth = fs::read_to_string(rec.join("truth.csv")).expect("truth");
    let mut lines = truth.lines();
    let mut wider = format!(
        "{},in_left,in_right,source\n",
        lines.next().expect("header")
    );
    let mut hidden = 0;
    for (i, line) in lines.enumerate() {
        let right = if i % 10 == 0 { 0 } else { 1 };
        hidden += 1 - right;
        wider.push_str(&format!("{line},1,{right},other\n"));
    }
    assert!(hidden > 0);
    let wide = rec.join("truth-wide.csv");
    fs::write(&wide, wider).expect("write");
    let json = ok(&["eval", s(&wide), s(&t1), "--json"]);
    let wide_report: serde_json::Value = serde_json::from_str(&json).expect("json");
    assert_eq!(wide_report["associated_rows"], report["associated_rows"]);
    assert!(
        wide_report["loss_budget"]["measurable"].as_u64() < budget["measurable"].as_u64(),
        "{json}"
    );
}

/// `--field` bins the vectors of `--out` on a world grid: one row per cell, counts adding up to
/// the vectors, centres on the grid; `.vtu` and `.vtk` outputs are read back by a real VTK
/// reader (Python's meshio) with the same numbers.
#[test]
fn process_writes_the_field_and_vtk_files_paraview_reads() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = synth(dir.path(), "flume", "60");
    let (tracks, field) = (dir.path().join("t.csv"), dir.path().join("field.csv"));
    let said = mrptv(&field_run(&rec, &tracks, &field, "0.05"));
    assert!(said.status.success());
    let stderr = String::from_utf8_lossy(&said.stderr);
    assert!(
        stderr.contains("field: ") && stderr.contains("cells of 0.05 m"),
        "{stderr}"
    );
    let rows = fs::read_to_string(&tracks).expect("tracks").lines().count() - 1;
    check_field_csv(&field, rows, 0.05);
    check_vtk_reads_back_as_the_csvs(dir.path(), &rec, &tracks, &field);
    check_old_tracks_files_still_read(dir.path(), &rec, &tracks);

    let e = fails(&field_run(&rec, &tracks, &field, "0"));
    assert!(e.contains("field cell size 0 m"), "{e}");
}

/// `mrptv process` of `rec` to `tracks`, with the field in cells `cell` metres wide to `field`.
fn field_run<'a>(rec: &'a Path, tracks: &'a Path, field: &'a Path, cell: &'a str) -> [&'a str; 8] {
    [
        "process",
        s(rec),
        "--out",
        s(tracks),
        "--field",
        s(field),
        "--field-cell",
        cell,
    ]
}

/// A field CSV of cells `cell_m` wide: its header, cells centred on the grid, their samples
/// adding up to the `rows` vectors, and at least one track (at most one per sample) in each.
fn check_field_csv(field: &Path, rows: usize, cell_m: f64) {
    let text = fs::read_to_string(field).expect("field");
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some("x,y,z,n,u,v,w,std_u,std_v,std_w,sem_u,sem_v,sem_w,tracks")
    );
    let cells: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|v| v.parse().expect("number")).collect())
        .collect();
    assert!(cells.len() > 5, "{} cells", cells.len());
    assert_eq!(cells.iter().map(|c| c[3]).sum::<f64>() as usize, rows);
    for c in &cells {
        for centre in &c[0..3] {
            let index = centre / cell_m - 0.5;
            assert!((index - index.round()).abs() < 1e-9, "centre {centre}");
        }
        assert!(
            c[13] >= 1.0 && c[13] <= c[3],
            "tracks {} of {} samples",
            c[13],
            c[3]
        );
    }
}

/// Reads a tracks CSV, a field CSV and their VTK files (argv 1-4) with meshio: the same values.
const VTK_READ_BACK: &str = r#"
import sys, csv, meshio, numpy as np
def rows(path):
    with open(path) as f:
        r = csv.reader(f); header = next(r)
        return header, np.array([[float(v) for v in row] for row in r])
th, t = rows(sys.argv[1]); fh, f = rows(sys.argv[2])
m = meshio.read(sys.argv[3])
assert len(m.points) == len(t), (len(m.points), len(t))
assert np.array_equal(m.points, t[:, 3:6])
assert np.array_equal(m.point_data["velocity"], t[:, 6:9])
assert np.array_equal(m.point_data["velocity_sigma"], t[:, 9:12])
assert np.array_equal(np.ravel(m.point_data["track_id"]), t[:, 2])
g = meshio.read(sys.argv[4])
assert np.array_equal(g.points, f[:, 0:3])
assert np.array_equal(g.point_data["velocity"], f[:, 4:7])
assert np.array_equal(np.ravel(g.point_data["n"]), f[:, 3])
assert np.array_equal(g.point_data["std"], f[:, 7:10])
print("read back", len(m.points), "vectors and", len(g.points), "cells")
"#;

/// The same run as VTK (both formats), read back by meshio: values equal to the CSVs'.
fn check_vtk_reads_back_as_the_csvs(dir: &Path, rec: &Path, tracks: &Path, field: &Path) {
    for ext in ["vtu", "vtk"] {
        let (vtk_tracks, vtk_field) = (
            dir.join(format!("t.{ext}")),
            dir.join(format!("field.{ext}")),
        );
        ok(&field_run(rec, &vtk_tracks, &vtk_field, "0.05"));
        let check = std::process::Command::new("python3")
            .arg("-c")
            .arg(VTK_READ_BACK)
            .args([tracks, field, &vtk_tracks, &vtk_field])
            .output()
            .expect("python3 runs (pip install -r tests/python/requirements.txt)");
        assert!(
            check.status.success(),
            "{ext}: {}{}",
            String::from_utf8_lossy(&check.stdout),
            String::from_utf8_lossy(&check.stderr)
        );
    }
}

/// A tracks file written before the uncertainty columns is still read (without the stated
/// uncertainty), and a current one with it.
fn check_old_tracks_files_still_read(dir: &Path, rec: &Path, tracks: &Path) {
    let old = dir.join("old.csv");
    let nine: Vec<String> = fs::read_to_string(tracks)
        .expect("tracks")
        .lines()
        .map(|l| l.split(',').take(9).collect::<Vec<_>>().join(","))
        .collect();
    fs::write(&old, nine.join("\n") + "\n").expect("write");
    let report = ok(&["eval", s(&rec.join("truth.csv")), s(&old)]);
    assert!(report.contains("ghost rate") && !report.contains("stated uncertainty"));
    let report = ok(&["eval", s(&rec.join("truth.csv")), s(tracks)]);
    assert!(report.contains("velocity within 2 sigma"), "{report}");
}

#[test]
fn single_frame_recording_gives_points_and_no_vectors() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = synth(dir.path(), "hololens-raw", "1");
    let (tracks, points) = (dir.path().join("t.csv"), dir.path().join("p.csv"));
    ok(&[
        "process",
        s(&rec),
        "--out",
        s(&tracks),
        "--points",
        s(&points),
    ]);
    assert_eq!(
        fs::read_to_string(&tracks).expect("tracks").lines().count(),
        1,
        "header only"
    );
    let points = fs::read_to_string(&points).expect("points");
    assert!(points.lines().count() > 10, "matched particles: {points}");
}

#[test]
fn method_flag_and_config_file_are_honoured() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = synth(dir.path(), "flume", "30");
    let config = dir.path().join("c.toml");
    fs::write(&config, ok(&["config", "--method"])).expect("write config");
    let (a, b) = (dir.path().join("a.csv"), dir.path().join("b.csv"));
    ok(&["process", s(&rec), "--out", s(&a), "--config", s(&config)]);
    ok(&["process", s(&rec), "--out", s(&b), "--method"]);
    assert!(fs::read(&a).expect("a").len() > 40);
}

/// A three-frame flume recording and copies of it to break, each processed to `out`.
struct Breakable {
    dir: tempfile::TempDir,
    rec: PathBuf,
    out: PathBuf,
}

impl Breakable {
    fn new() -> Self {
        let dir = tempfile::tempdir().expect("tmp");
        let rec = synth(dir.path(), "flume", "3");
        let out = dir.path().join("t.csv");
        Self { dir, rec, out }
    }

    /// A copy of the recording (rig, frames table, images) under `name`.
    fn copy(&self, name: &str) -> PathBuf {
        let to = self.dir.path().join(name);
        fs::create_dir_all(to.join("left")).expect("mkdir");
        fs::create_dir_all(to.join("right")).expect("mkdir");
        for f in ["rig.json", "frames.csv"] {
            fs::copy(self.rec.join(f), to.join(f)).expect("copy");
        }
        for side in ["left", "right"] {
            for i in 0..3 {
                let n = format!("{i:06}.png");
                fs::copy(self.rec.join(side).join(&n), to.join(side).join(&n)).expect("copy png");
            }
        }
        to
    }

    /// `mrptv process` on `rec`, which must fail: its stderr.
    fn process(&self, rec: &Path) -> String {
        fails(&["process", s(rec), "--out", s(&self.out)])
    }

    /// The recording's `rig.json`, as text.
    fn rig(&self) -> String {
        fs::read_to_string(self.rec.join("rig.json")).expect("rig")
    }

    /// A copy under `name` whose `rig.json` has `edit` applied.
    fn with_rig(&self, name: &str, edit: impl FnOnce(&mut serde_json::Value)) -> PathBuf {
        let r = self.copy(name);
        let mut file: serde_json::Value = serde_json::from_str(&self.rig()).expect("json");
        edit(&mut file);
        fs::write(r.join("rig.json"), file.to_string()).expect("write");
        r
    }
}

#[test]
fn a_missing_or_broken_recording_or_rig_is_named() {
    let b = Breakable::new();
    let e = b.process(&b.dir.path().join("nowhere"));
    assert!(
        e.contains("nowhere") && e.contains("not a recording directory"),
        "{e}"
    );

    let r = b.copy("missing-rig");
    fs::remove_file(r.join("rig.json")).expect("rm");
    let e = b.process(&r);
    assert!(e.contains("rig.json") && e.contains("No such file"), "{e}");

    let r = b.copy("malformed-rig");
    fs::write(
        r.join("rig.json"),
        "{\"image_size\": [640, 480],\n \"K1\": [[1,0,0]}",
    )
    .expect("write");
    let e = b.process(&r);
    assert!(e.contains("rig.json") && e.contains("line 2"), "{e}");

    let r = b.copy("nan-rig");
    fs::write(r.join("rig.json"), b.rig().replacen("363.0", "NaN", 1)).expect("write");
    let e = b.process(&r);
    assert!(
        e.contains("rig.json") && e.contains("line"),
        "NaN is not JSON: {e}"
    );

    let r = b.with_rig("singular-rig", |file| {
        file["K2"][0][0] = serde_json::json!(0.0)
    });
    let e = b.process(&r);
    assert!(
        e.contains("rig.json") && e.contains("K2: focal lengths fx, fy must be positive"),
        "{e}"
    );

    let r = b.with_rig("not-a-rotation", |file| {
        file["R"][1][1] = serde_json::json!(2.0)
    });
    let e = b.process(&r);
    assert!(e.contains("rig.json") && e.contains("R"), "{e}");
}

#[test]
fn a_broken_frames_table_is_named_by_line() {
    let b = Breakable::new();
    for (name, text, expected) in [
        (
            "bad-frames",
            "index,t_s\n0,0\n1,zero\n",
            "frames.csv line 3: t_s 'zero' is not a finite number",
        ),
        (
            "empty-frames",
            "",
            "frames.csv: empty file, expected the header",
        ),
        (
            "repeated-time",
            "index,t_s\n0,0\n1,0.1\n2,0.1\n",
            "frames.csv line 4: t_s 0.1 does not increase",
        ),
        (
            "repeated-index",
            "index,t_s\n0,0\n0,0.1\n",
            "frames.csv line 3: index 0 does not increase",
        ),
        (
            "short-line",
            "index,t_s\n0,0\n1\n",
            "frames.csv line 3: 1 fields, the header has 2",
        ),
        (
            "negative-index",
            "index,t_s\n-1,0\n",
            "frames.csv line 2: index -1 is not a non-negative whole number",
        ),
        (
            "infinite-time",
            "index,t_s\n0,inf\n",
            "frames.csv line 2: t_s 'inf' is not a finite number",
        ),
    ] {
        let r = b.copy(name);
        fs::write(r.join("frames.csv"), text).expect("write");
        let e = b.process(&r);
        assert!(e.contains(expected), "{name}: {e}");
    }

    let r = b.copy("bad-pose");
    let mut header = mrptv::tables::frames_header_with_pose();
    header.push('\n');
    let identity = "1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1";
    let scaled = "2,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1";
    fs::write(
        r.join("frames.csv"),
        format!("{header}0,0,{identity}\n1,0.1,{scaled}\n"),
    )
    .expect("write");
    let e = b.process(&r);
    assert!(
        e.contains("frames.csv line 3") && e.contains("world_from_rig"),
        "{e}"
    );
}

#[test]
fn degenerate_images_give_no_vectors_and_bad_ones_are_named() {
    let b = Breakable::new();
    // Degenerate but valid images: processed, no particles, no vectors, no error.
    let r = b.copy("all-black-and-white");
    for (side, value) in [("left", 0u8), ("right", 255u8)] {
        for i in 0..3 {
            let png =
                mrptv::recording::encode_gray_png(&vec![value; 640 * 480], 640, 480).expect("png");
            fs::write(r.join(side).join(format!("{i:06}.png")), png).expect("write");
        }
    }
    ok(&["process", s(&r), "--out", s(&b.out)]);
    let rows = fs::read_to_string(&b.out).expect("tracks.csv");
    assert_eq!(rows.lines().count(), 1, "a header and no vectors: {rows}");

    let r = b.copy("missing-image");
    fs::remove_file(r.join("right").join("000002.png")).expect("rm");
    let e = b.process(&r);
    assert!(
        e.contains("000002.png") && e.contains("No such file"),
        "{e}"
    );
    assert_eq!(
        e.matches("No such file").count(),
        1,
        "each error printed once: {e}"
    );

    let r = b.copy("wrong-size");
    let small = mrptv::recording::encode_gray_png(&[0u8; 32 * 24], 32, 24).expect("png");
    fs::write(r.join("left").join("000001.png"), small).expect("write");
    let e = b.process(&r);
    assert!(
        e.contains("000001.png") && e.contains("image is 32x24, rig.json image_size is 640x480"),
        "{e}"
    );

    let r = b.copy("not-png");
    fs::write(r.join("left").join("000000.png"), b"GIF89a...").expect("write");
    let e = b.process(&r);
    assert!(
        e.contains("000000.png") && e.contains("not a readable PNG"),
        "{e}"
    );
}

#[test]
fn config_typos_wrong_tables_and_bad_scenarios_are_named() {
    let b = Breakable::new();
    let r = b.copy("config-typo");
    fs::write(r.join("mrptv.toml"), "[velocity]\nhalf_windw_frames = 3\n").expect("write");
    let e = b.process(&r);
    assert!(
        e.contains("mrptv.toml") && e.contains("half_windw_frames"),
        "{e}"
    );

    let e = fails(&[
        "eval",
        s(&b.rec.join("truth.csv")),
        s(&b.rec.join("frames.csv")),
    ]);
    assert!(
        e.contains("frames.csv line 1: header 'index,t_s' is not 'frame,t_s,track_id,x,y,z,u,v,w,su,sv,sw,sx,sy,sz' or 'frame,t_s,track_id,x,y,z,u,v,w'"),
        "{e}"
    );

    let e = fails(&["synth", "nope", s(&b.dir.path().join("x"))]);
    assert!(e.contains("unknown scenario 'nope'"), "{e}");
    let e = fails(&["synth", "flume", s(&b.rec)]);
    assert!(e.contains("exists and is not empty"), "{e}");
}

#[test]
fn load_drives_headsets_and_viewers_and_reports_what_it_measured() {
    let out = ok(&[
        "load",
        "--headsets",
        "2",
        "--viewers",
        "3",
        "--seconds",
        "3",
        "--json",
    ]);
    let r: serde_json::Value = serde_json::from_str(out.trim()).expect("one JSON report");
    let n = |k: &str| r[k].as_f64().unwrap_or_else(|| panic!("{k} in {r}"));
    // 2 headsets x 30 Hz x 3 s, give or take start-up.
    assert!((150.0..=185.0).contains(&n("frames_sent")), "{r}");
    assert_eq!(n("frames_processed"), n("frames_sent"), "{r}");
    assert_eq!(n("frames_dropped") + n("frames_rejected"), 0.0, "{r}");
    assert!(n("latency_ms_p50") > 0.0 && n("latency_ms_p99") >= n("latency_ms_p50"));
    assert!(
        n("batches_published") > n("frames_processed"),
        "causal and refined: {r}"
    );
    assert_eq!(n("viewer_batches_min"), n("batches_published"), "{r}");
    assert!(
        n("rss_start_mib") > 1.0 && n("rss_peak_mib") >= n("rss_end_mib"),
        "{r}"
    );
    assert_eq!(r["clean_exit"], true, "{r}");
    let e = fails(&["load", "--headsets", "0"]);
    assert!(e.contains("--headsets must be at least 1"), "{e}");
}

#[test]
fn serving_beyond_loopback_without_secrets_or_tls_says_what_is_exposed() {
    use std::io::{BufRead, BufReader};
    let mut child = Command::new(env!("CARGO_BIN_EXE_mrptv"))
        .args(["serve", "--bind", "0.0.0.0:0"])
        .env_remove("MRPTV_INGEST_SECRET")
        .env_remove("MRPTV_WATCH_SECRET")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("serve starts");
    let stderr = child.stderr.take().expect("stderr");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if line.starts_with("warning:") && tx.send(line).is_err() {
                break;
            }
        }
    });
    let warnings: Vec<String> = (0..2)
        .map_while(|_| rx.recv_timeout(std::time::Duration::from_secs(15)).ok())
        .collect();
    let _ = child.kill();
    let _ = child.wait();
    assert_eq!(warnings.len(), 2, "{warnings:?}");
    assert!(
        warnings[0].contains("no secret for headsets or viewers"),
        "{warnings:?}"
    );
    assert!(warnings[1].contains("without TLS"), "{warnings:?}");
    let e = fails(&["serve", "--ingest-secret", "short"]);
    assert!(e.contains("at least 12"), "{e}");
    let e = fails(&[
        "serve",
        "--ingest-secret",
        "the-same-secret",
        "--watch-secret",
        "the-same-secret",
    ]);
    assert!(e.contains("the same"), "{e}");
}

/// `--depth-range` bounds the stereo search: the run says which depths it searched, and a range
/// the two cameras cannot both see is refused with the range they can.
#[test]
fn depth_range_bounds_the_stereo_search_and_says_so() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = synth(dir.path(), "convergent", "12");
    let tracks = dir.path().join("tracks.csv");
    let (rec_s, tracks_s) = (s(&rec), s(&tracks));
    let with_range = |range: Option<&str>| {
        let mut args = vec!["process", rec_s, "--out", tracks_s];
        args.extend(range.map(|r| ["--depth-range", r]).into_iter().flatten());
        args.into_iter().map(String::from).collect::<Vec<_>>()
    };
    let stderr_of = |args: Vec<String>| {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let out = mrptv(&args);
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{stderr}");
        stderr
    };
    let stderr = stderr_of(with_range(None));
    assert!(
        stderr.contains("settled: stereo search depths 0.")
            && stderr.contains("epipolar band 2.00 px")
            && stderr.contains("health: ")
            && !stderr.contains("warning"),
        "{stderr}"
    );
    let stderr = stderr_of(with_range(Some("0.45..0.7")));
    assert!(
        stderr.contains("stereo search depths 0.450..0.700 m"),
        "{stderr}"
    );
    let refused = |range: &str| {
        let args = with_range(Some(range));
        fails(&args.iter().map(String::as_str).collect::<Vec<_>>())
    };
    let e = refused("5..9");
    assert!(
        e.contains("depth_range_m 5..9 m lies outside") && e.contains(" m)"),
        "{e}"
    );
    let e = refused("0.8..0.3");
    assert!(e.contains("0 < NEAR < FAR"), "{e}");
}

/// A run that gives no vectors exits cleanly but says why, in words.
#[test]
fn a_run_without_vectors_says_why() {
    let dir = tempfile::tempdir().expect("tmp");
    let tracks = dir.path().join("tracks.csv");
    let process = |rec: &Path, config: Option<&Path>| {
        let mut args = vec!["process", s(rec), "--out", s(&tracks)];
        args.extend(config.map(|c| ["--config", s(c)]).into_iter().flatten());
        let out = mrptv(&args);
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{stderr}");
        assert!(stderr.contains(" 0 vectors"), "{stderr}");
        stderr
    };
    // The published search on a toed-in rig: K, a quarter of the image width, stops far short of
    // the ~1,000 px disparities.
    let convergent = synth(dir.path(), "convergent", "12");
    let fractions = dir.path().join("fractions.toml");
    fs::write(
        &fractions,
        "[stereo]\ndisparity_range_fraction = 0.25\nepipolar_band_fraction = 0.01\n",
    )
    .expect("config");
    let stderr = process(&convergent, Some(&fractions));
    assert!(
        stderr.contains("warning: no vectors: particles were detected")
            && stderr.contains("none matched between the cameras")
            && stderr.contains("--depth-range"),
        "{stderr}"
    );
    let short = synth(dir.path(), "flume", "4");
    let stderr = process(&short, None);
    assert!(
        stderr.contains("warning: no vectors: the recording has 4 frames")
            && stderr.contains("seen through 5"),
        "{stderr}"
    );
}

/// Every command's `--help` and `-h` (and `--version`) are as recorded in `tests/cli_help/`:
/// scripts and the docs quote them, so they change only on purpose (`MRPTV_UPDATE_GOLDEN=1`
/// rewrites the files; review the diff).
#[test]
fn help_texts_are_as_recorded() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/cli_help");
    let update = std::env::var_os("MRPTV_UPDATE_GOLDEN").is_some();
    let commands = [
        "synth", "process", "eval", "demo", "serve", "replay", "hl2ss", "load", "config",
    ];
    let mut cases: Vec<(String, Vec<&str>)> = vec![
        ("mrptv".into(), vec!["--help"]),
        ("mrptv-h".into(), vec!["-h"]),
        ("version".into(), vec!["--version"]),
    ];
    for command in commands {
        cases.push((command.into(), vec![command, "--help"]));
        cases.push((format!("{command}-h"), vec![command, "-h"]));
    }
    let mut differ = Vec::new();
    for (name, args) in &cases {
        let out = mrptv(args);
        assert!(out.status.success(), "mrptv {args:?} failed");
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        let path = dir.join(format!("{name}.txt"));
        if update {
            fs::write(&path, &text).expect("write golden help");
            continue;
        }
        let recorded = fs::read_to_string(&path).unwrap_or_else(|e| {
            panic!("{}: {e} (MRPTV_UPDATE_GOLDEN=1 writes it)", path.display())
        });
        if text != recorded {
            differ.push(format!(
                "mrptv {}: differs from {}:\n{text}",
                args.join(" "),
                path.display()
            ));
        }
    }
    let recorded_files = fs::read_dir(&dir).expect("tests/cli_help").count();
    assert_eq!(
        recorded_files,
        cases.len(),
        "tests/cli_help/ holds files no case checks, or misses some"
    );
    assert!(differ.is_empty(), "{}", differ.join("\n\n"));
}
