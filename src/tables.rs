//! The CSV files of the recording contract: `frames.csv`, `truth.csv`, `tracks.csv`,
//! `points.csv`. All-numeric with a fixed header, so a small strict reader that names the file,
//! line and column of anything wrong beats a general CSV crate here.

use std::fmt::Write as _;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use nalgebra::{Point3, Vector3};

pub use mrptv_engine::eval::TrackRow;
use mrptv_engine::field::{CellSummary, FIELD_COLUMNS};
use mrptv_engine::geometry::isometry_to_row_major;
use mrptv_engine::synth::TruthRow;
use mrptv_engine::{MatchedPoint, VelocityVector};

pub(crate) const FRAMES_HEADER: &str = "index,t_s";
pub(crate) const TRUTH_HEADER: &str = "frame,t_s,pid,x,y,z,u,v,w";
pub(crate) const TRACKS_HEADER: &str = "frame,t_s,track_id,x,y,z,u,v,w";
/// `tracks.csv` as written since vectors carry their uncertainty: `TRACKS_HEADER` and the 1-sigma
/// errors of velocity (m/s) and position (m) appended.
pub(crate) const TRACKS_HEADER_WITH_SIGMA: &str =
    "frame,t_s,track_id,x,y,z,u,v,w,su,sv,sw,sx,sy,sz";
pub(crate) const POINTS_HEADER: &str = "frame,t_s,x,y,z,xl,yl,xr,yr";

/// `frames.csv` header with the 16 optional pose columns.
pub fn frames_header_with_pose() -> String {
    let mut h = FRAMES_HEADER.to_string();
    for r in 0..4 {
        for c in 0..4 {
            let _ = write!(h, ",world_from_rig_{r}{c}");
        }
    }
    h
}

#[derive(Debug, thiserror::Error)]
pub enum TableError {
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{path}: empty file, expected the header '{expected}'")]
    Empty { path: PathBuf, expected: String },
    #[error("{path} line 1: header '{found}' is not {expected}")]
    Header {
        path: PathBuf,
        found: String,
        expected: String,
    },
    #[error("{path} line {line}: {message}")]
    Row {
        path: PathBuf,
        line: usize,
        message: String,
    },
}

/// A data row with the line it came from (1-based, header is line 1).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Row {
    pub(crate) line: usize,
    pub(crate) values: Vec<f64>,
}

/// Reads a numeric CSV whose header must equal one of `headers`; returns which one and the rows.
pub(crate) fn read_numeric(path: &Path, headers: &[&str]) -> Result<(usize, Vec<Row>), TableError> {
    parse_numeric(path, open(path)?, headers)
}

fn open(path: &Path) -> Result<BufReader<std::fs::File>, TableError> {
    let file = std::fs::File::open(path).map_err(|error| TableError::Io {
        path: path.to_path_buf(),
        error,
    })?;
    Ok(BufReader::new(file))
}

/// The header line of `lines`, without a byte-order mark or carriage return; `expected` names
/// the header wanted when there is none.
fn read_header(
    path: &Path,
    lines: &mut impl Iterator<Item = std::io::Result<String>>,
    expected: impl FnOnce() -> String,
) -> Result<String, TableError> {
    match lines.next() {
        Some(line) => {
            let line = line.map_err(|error| TableError::Io {
                path: path.to_path_buf(),
                error,
            })?;
            Ok(line
                .trim_end_matches('\r')
                .trim_start_matches('\u{feff}')
                .to_string())
        }
        None => Err(TableError::Empty {
            path: path.to_path_buf(),
            expected: expected(),
        }),
    }
}

/// [`read_numeric`] of text from anywhere; `path` names it in errors.
pub(crate) fn parse_numeric(
    path: &Path,
    text: impl BufRead,
    headers: &[&str],
) -> Result<(usize, Vec<Row>), TableError> {
    let mut lines = text.lines();
    let expected = || {
        headers
            .iter()
            .map(|h| format!("'{h}'"))
            .collect::<Vec<_>>()
            .join(" or ")
    };
    let header = read_header(path, &mut lines, expected)?;
    let header = header.as_str();
    let Some(variant) = headers.iter().position(|h| *h == header) else {
        return Err(TableError::Header {
            path: path.to_path_buf(),
            found: header.chars().take(200).collect(),
            expected: expected(),
        });
    };
    let names: Vec<&str> = headers[variant].split(',').collect();
    let rows = parse_rows(path, lines, &names, |_| true)?;
    Ok((variant, rows))
}

/// The data rows under a header of `names`; a column `numeric` refuses is not parsed (its
/// value is NaN).
fn parse_rows(
    path: &Path,
    lines: impl Iterator<Item = std::io::Result<String>>,
    names: &[&str],
    numeric: impl Fn(usize) -> bool,
) -> Result<Vec<Row>, TableError> {
    let mut rows = Vec::new();
    for (n, line) in lines.enumerate() {
        let line_no = n + 2;
        let line = line.map_err(|error| TableError::Io {
            path: path.to_path_buf(),
            error,
        })?;
        let line = line.trim_end_matches('\r');
        if line.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split(',').collect();
        if fields.len() != names.len() {
            return Err(TableError::Row {
                path: path.to_path_buf(),
                line: line_no,
                message: format!("{} fields, the header has {}", fields.len(), names.len()),
            });
        }
        let mut values = Vec::with_capacity(fields.len());
        for (column, (field, name)) in fields.iter().zip(names).enumerate() {
            if !numeric(column) {
                values.push(f64::NAN);
                continue;
            }
            match field.trim().parse::<f64>() {
                Ok(v) if v.is_finite() => values.push(v),
                _ => {
                    return Err(TableError::Row {
                        path: path.to_path_buf(),
                        line: line_no,
                        message: format!("{name} '{}' is not a finite number", field.trim()),
                    })
                }
            }
        }
        rows.push(Row {
            line: line_no,
            values,
        });
    }
    Ok(rows)
}

/// A non-negative whole number from a numeric field.
pub(crate) fn whole(path: &Path, row: &Row, column: usize, name: &str) -> Result<u64, TableError> {
    let v = row.values[column];
    if v >= 0.0 && v.fract() == 0.0 && v <= 9.007_199_254_740_992e15 {
        Ok(v as u64)
    } else {
        Err(TableError::Row {
            path: path.to_path_buf(),
            line: row.line,
            message: format!("{name} {v} is not a non-negative whole number"),
        })
    }
}

fn point(values: &[f64]) -> Point3<f64> {
    Point3::new(values[0], values[1], values[2])
}

fn vector(values: &[f64]) -> Vector3<f64> {
    Vector3::new(values[0], values[1], values[2])
}

/// Columns that may follow `TRUTH_HEADER` and say which images show the particle (0 or 1).
const TRUTH_VISIBILITY: [&str; 2] = ["in_left", "in_right"];

/// Reads `truth.csv`: `TRUTH_HEADER`, then any further columns (kept for other tools, not read),
/// of which `in_left` and `in_right`, when both are there, say which images show the particle.
pub fn read_truth(path: &Path) -> Result<Vec<TruthRow>, TableError> {
    let mut lines = open(path)?.lines();
    let expected = format!("'{TRUTH_HEADER}' (further columns may follow it)");
    let header = read_header(path, &mut lines, || expected.clone())?;
    let names: Vec<&str> = header.split(',').map(str::trim).collect();
    let known = TRUTH_HEADER.split(',').count();
    if names.len() < known || names[..known].join(",") != TRUTH_HEADER {
        return Err(TableError::Header {
            path: path.to_path_buf(),
            found: header.chars().take(200).collect(),
            expected,
        });
    }
    let visibility = TRUTH_VISIBILITY.map(|v| names.iter().position(|n| *n == v));
    let rows = parse_rows(path, lines, &names, |c| {
        c < known || visibility.contains(&Some(c))
    })?;
    rows.iter()
        .map(|r| {
            let visible = match visibility {
                [Some(l), Some(r_)] => Some([
                    flag(path, r, l, TRUTH_VISIBILITY[0])?,
                    flag(path, r, r_, TRUTH_VISIBILITY[1])?,
                ]),
                _ => None,
            };
            Ok(TruthRow {
                frame: whole(path, r, 0, "frame")?,
                t_s: r.values[1],
                pid: whole(path, r, 2, "pid")?,
                position: point(&r.values[3..6]),
                velocity: vector(&r.values[6..9]),
                visible,
            })
        })
        .collect()
}

/// A 0 or 1 field as a flag.
fn flag(path: &Path, row: &Row, column: usize, name: &str) -> Result<bool, TableError> {
    match row.values[column] {
        0.0 => Ok(false),
        1.0 => Ok(true),
        v => Err(TableError::Row {
            path: path.to_path_buf(),
            line: row.line,
            message: format!("{name} {v} is not 0 or 1"),
        }),
    }
}

/// Reads `tracks.csv` with or without the uncertainty columns.
pub fn read_tracks(path: &Path) -> Result<Vec<TrackRow>, TableError> {
    let (_, rows) = read_numeric(path, &[TRACKS_HEADER_WITH_SIGMA, TRACKS_HEADER])?;
    track_rows(path, &rows)
}

/// [`read_tracks`] of text from anywhere; `path` names it in errors.
pub fn parse_tracks(path: &Path, text: impl BufRead) -> Result<Vec<TrackRow>, TableError> {
    let (_, rows) = parse_numeric(path, text, &[TRACKS_HEADER_WITH_SIGMA, TRACKS_HEADER])?;
    track_rows(path, &rows)
}

fn track_rows(path: &Path, rows: &[Row]) -> Result<Vec<TrackRow>, TableError> {
    rows.iter()
        .map(|r| {
            Ok(TrackRow {
                frame: whole(path, r, 0, "frame")?,
                t_s: r.values[1],
                track_id: whole(path, r, 2, "track_id")?,
                position: point(&r.values[3..6]),
                velocity: vector(&r.values[6..9]),
                sigma: (r.values.len() >= 15)
                    .then(|| (vector(&r.values[9..12]), vector(&r.values[12..15]))),
            })
        })
        .collect()
}

// Writers use Rust's shortest round-trip float formatting: exact and deterministic.

pub(crate) fn write_truth_row(
    out: &mut (impl Write + ?Sized),
    r: &TruthRow,
) -> std::io::Result<()> {
    let (p, v) = (r.position, r.velocity);
    writeln!(
        out,
        "{},{},{},{},{},{},{},{},{}",
        r.frame, r.t_s, r.pid, p.x, p.y, p.z, v.x, v.y, v.z
    )
}

/// A `tracks.csv` row under `TRACKS_HEADER_WITH_SIGMA`.
pub(crate) fn write_track_row(
    out: &mut (impl Write + ?Sized),
    v: &VelocityVector,
) -> std::io::Result<()> {
    let (p, u) = (v.position_in_world, v.velocity_in_world);
    let (su, sp) = (v.velocity_sigma, v.position_sigma);
    writeln!(
        out,
        "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
        v.frame_index,
        v.t_s,
        v.track_id,
        p.x,
        p.y,
        p.z,
        u.x,
        u.y,
        u.z,
        su.x,
        su.y,
        su.z,
        sp.x,
        sp.y,
        sp.z
    )
}

/// `field.csv`: the header (`FIELD_COLUMNS`: per grid cell its centre, world frame, m; sample
/// count; mean velocity, m/s; standard deviation and standard error of the mean per component;
/// distinct tracks), then a row per cell.
pub fn write_field(out: &mut (impl Write + ?Sized), cells: &[CellSummary]) -> std::io::Result<()> {
    writeln!(out, "{}", FIELD_COLUMNS.join(","))?;
    for c in cells {
        let row: Vec<String> = c.values().iter().map(|v| v.to_string()).collect();
        writeln!(out, "{}", row.join(","))?;
    }
    Ok(())
}

pub(crate) fn write_point_row(
    out: &mut (impl Write + ?Sized),
    frame: u64,
    t_s: f64,
    m: &MatchedPoint,
) -> std::io::Result<()> {
    let p = m.point_in_world;
    writeln!(
        out,
        "{},{},{},{},{},{},{},{},{}",
        frame, t_s, p.x, p.y, p.z, m.left_px.x, m.left_px.y, m.right_px.x, m.right_px.y
    )
}

pub(crate) fn format_frame_row(
    index: u64,
    t_s: f64,
    world_from_rig: Option<&nalgebra::Isometry3<f64>>,
) -> String {
    let mut line = format!("{index},{t_s}");
    if let Some(pose) = world_from_rig {
        for v in isometry_to_row_major(pose) {
            let _ = write!(line, ",{v}");
        }
    }
    line.push('\n');
    line
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &tempfile::TempDir, name: &str, text: &str) -> PathBuf {
        let p = dir.path().join(name);
        std::fs::write(&p, text).expect("write");
        p
    }

    #[test]
    fn names_line_and_column_of_a_bad_value() {
        let dir = tempfile::tempdir().expect("tmp");
        let p = write(
            &dir,
            "t.csv",
            "frame,t_s,track_id,x,y,z,u,v,w\n0,0,1,0,0,0,0,0,0\n1,0.1,1,0,abc,0,0,0,0\n",
        );
        let e = read_tracks(&p).unwrap_err().to_string();
        assert!(
            e.ends_with("t.csv line 3: y 'abc' is not a finite number"),
            "{e}"
        );
    }

    #[test]
    fn truth_may_carry_further_columns_and_say_what_each_image_shows() {
        let dir = tempfile::tempdir().expect("tmp");
        let p = write(
            &dir,
            "truth.csv",
            "frame,t_s,pid,x,y,z,u,v,w,in_left,in_right,note\n0,0,1,0,0,1,0,0,0,1,0,edge\n",
        );
        let rows = read_truth(&p).expect("truth with further columns");
        assert_eq!(rows[0].visible, Some([true, false]));
        let p = write(
            &dir,
            "plain.csv",
            "frame,t_s,pid,x,y,z,u,v,w,note\n0,0,1,0,0,1,0,0,0,x\n",
        );
        assert_eq!(read_truth(&p).expect("plain")[0].visible, None);
        let p = write(
            &dir,
            "bad.csv",
            "frame,t_s,pid,x,y,z,u,v,w,in_left,in_right\n0,0,1,0,0,1,0,0,0,2,1\n",
        );
        let e = read_truth(&p).unwrap_err().to_string();
        assert!(
            e.ends_with("bad.csv line 2: in_left 2 is not 0 or 1"),
            "{e}"
        );
    }

    #[test]
    fn wrong_header_and_field_count() {
        let dir = tempfile::tempdir().expect("tmp");
        let p = write(&dir, "a.csv", "frame,t,pid\n");
        assert!(read_truth(&p)
            .unwrap_err()
            .to_string()
            .contains("header 'frame,t,pid' is not 'frame,t_s,pid,x,y,z,u,v,w'"));
        let p = write(&dir, "b.csv", "index,t_s\n0,0.0,7\n");
        let e = read_numeric(&p, &[FRAMES_HEADER]).unwrap_err().to_string();
        assert!(e.ends_with("line 2: 3 fields, the header has 2"), "{e}");
        let p = write(&dir, "c.csv", "");
        assert!(read_numeric(&p, &[FRAMES_HEADER])
            .unwrap_err()
            .to_string()
            .contains("empty file"));
        let p = write(&dir, "d.csv", "index,t_s\n1.5,0\n");
        let (_, rows) = read_numeric(&p, &[FRAMES_HEADER]).expect("numeric");
        assert!(whole(&p, &rows[0], 0, "index")
            .unwrap_err()
            .to_string()
            .contains("index 1.5 is not a non-negative whole number"));
    }

    #[test]
    fn nan_is_rejected() {
        let dir = tempfile::tempdir().expect("tmp");
        let p = write(&dir, "n.csv", "index,t_s\n0,NaN\n");
        assert!(read_numeric(&p, &[FRAMES_HEADER])
            .unwrap_err()
            .to_string()
            .contains("t_s 'NaN' is not a finite number"));
    }

    #[test]
    fn pose_header_has_sixteen_columns() {
        let h = frames_header_with_pose();
        assert_eq!(h.split(',').count(), 18);
        assert!(h.ends_with("world_from_rig_32,world_from_rig_33"));
    }
}
