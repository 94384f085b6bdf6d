//! `mrptv process`: a recording in, velocity vectors (tracks.csv) out.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use mrptv::offline::{self, ProcessSinks, Sink};
use mrptv::recording::Recording;
use mrptv::rerun_log::{start_proxy, RerunLogger, RerunOptions, RerunSink};
use mrptv::tables::{self, TrackRow};
use mrptv::vtk::{self, VtkFormat};
use mrptv_engine::field::{self, CellSummary, FieldGrid, FieldSample};

use super::args::{ConfigChoices, ConfigFile, RerunArgs};
use super::{create_output, load_config, progress_bar, runtime, termination};

#[derive(clap::Args)]
pub struct Args {
    /// Recording directory (rig.json, frames.csv, left/, right/).
    rec: PathBuf,
    /// Output: tracks.csv (frame,t_s,track_id,x,y,z,u,v,w,su,sv,sw,sx,sy,sz: metres, m/s, world
    /// frame, then 1-sigma errors), or a VTK file for ParaView when it ends in .vtu or .vtk.
    #[arg(long)]
    out: PathBuf,
    /// Also write the mean-flow field: the vectors binned on a world-anchored grid, per cell
    /// x,y,z,n,u,v,w,std_u,std_v,std_w,sem_u,sem_v,sem_w,tracks (CSV; .vtu or .vtk for VTK).
    #[arg(long, value_name = "FILE")]
    field: Option<PathBuf>,
    /// With --field: the grid's cell size, metres [default: a tenth of the measurement
    /// volume's largest extent, rounded to 1, 2 or 5 times a power of ten].
    #[arg(long, value_name = "M", requires = "field")]
    field_cell: Option<f64>,
    /// Also write every stereo-matched particle: frame,t_s,x,y,z,xl,yl,xr,yr.
    #[arg(long)]
    points: Option<PathBuf>,
    #[command(flatten)]
    config: ConfigFile,
    #[command(flatten)]
    choices: ConfigChoices,
    #[command(flatten)]
    rerun: RerunArgs,
}

pub fn run(args: Args) -> Result<()> {
    let Args {
        rec,
        out,
        field,
        field_cell,
        points,
        config,
        choices,
        rerun: RerunArgs {
            mut rerun,
            rerun_images_every,
        },
    } = args;
    let recording = Recording::open(&rec)?;
    let config = choices.apply(load_config(&rec, &config)?);
    if let Some(cell) = field_cell {
        FieldGrid::new(cell, None)?;
    }
    let out_vtk = VtkFormat::of(&out);
    // A VTK file is written once the vectors are known; the rows gather in memory till then.
    let mut tracks_file = match out_vtk {
        Some(_) => None,
        None => Some(create_output(&out)?),
    };
    let mut tracks_text = Vec::new();
    let proxy = start_proxy(&mut rerun)?;
    let logger = start_logger(&rec, &recording, &rerun, rerun_images_every)?;
    let mut points_file = points.as_deref().map(create_output).transpose()?;
    let bar = progress_bar(recording.frames.len(), "process");
    let totals = offline::process_recording(
        &recording,
        config.clone(),
        ProcessSinks {
            tracks: Sink {
                path: &out,
                writer: match tracks_file.as_mut() {
                    Some(file) => file,
                    None => &mut tracks_text,
                },
            },
            points: match (points.as_deref(), points_file.as_mut()) {
                (Some(path), Some(file)) => Some(Sink { path, writer: file }),
                _ => None,
            },
            rerun: logger.as_ref(),
        },
        |n| bar.set_position(n as u64),
    )
    .with_context(|| format!("processing {}", rec.display()))?;
    bar.finish_and_clear();
    if let Some(mut file) = tracks_file {
        file.flush()
            .with_context(|| format!("writing {}", out.display()))?;
    }
    let rows = match (out_vtk, &field) {
        (None, None) => Vec::new(),
        (None, Some(_)) => tables::read_tracks(&out)?,
        (Some(_), _) => tables::parse_tracks(&out, tracks_text.as_slice())?,
    };
    if let Some(format) = out_vtk {
        let mut file = create_output(&out)?;
        vtk::write_tracks(&mut file, format, &rows)
            .and_then(|()| Ok(file.flush()?))
            .with_context(|| format!("writing {}", out.display()))?;
    }
    if let Some(path) = &field {
        let cells = write_field(path, field_cell, &rows)?;
        if let (Some(logger), Some(last)) = (&logger, rows.iter().max_by_key(|r| r.frame)) {
            logger.log_field(last.frame, last.t_s, cells, true);
        }
    }
    if let Some(logger) = logger {
        report_rerun(logger, &rerun);
    }
    print_totals(&totals, &out);
    super::print_health(&totals.health(&config));
    if let Some(proxy) = proxy {
        println!(
            "serving the Rerun log: rerun --connect {}   (Ctrl-C to stop)",
            proxy.url()
        );
        runtime()?.block_on(termination());
    }
    Ok(())
}

/// The Rerun logger of the run, named after the recording; `None` without sinks.
fn start_logger(
    rec: &Path,
    recording: &Recording,
    sinks: &[RerunSink],
    images_every: u64,
) -> Result<Option<RerunLogger>> {
    if sinks.is_empty() {
        return Ok(None);
    }
    let options = RerunOptions {
        images_every,
        ..Default::default()
    };
    let name = rec.file_name().map_or_else(
        || rec.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    );
    Ok(Some(RerunLogger::start(
        &name,
        sinks,
        &recording.rig,
        &options,
    )?))
}

/// What the run found, on stderr.
fn print_totals(totals: &offline::RunTotals, out: &Path) {
    eprintln!(
        "{} frames: {:.1} detections/image, {:.1} matches/frame, {} vectors ({} rejected as rough, {} as straying from their neighbours, {} as no measurement: outside the volume or impossibly fast) -> {}; pipeline {:.1} frames/s",
        totals.frames,
        (totals.counts.detections_left + totals.counts.detections_right) as f64 / (2 * totals.frames.max(1)) as f64,
        totals.counts.matches as f64 / totals.frames.max(1) as f64,
        totals.counts.vectors,
        totals.counts.rejected,
        totals.counts.outliers,
        totals.counts.implausible,
        out.display(),
        totals.frames as f64 / totals.pipeline_s.max(1e-9)
    );
}

/// Bins the vectors on a grid of `cell_m` (or the default for their volume) and writes the
/// field as CSV or VTK, by `path`'s extension.
fn write_field(path: &Path, cell_m: Option<f64>, rows: &[TrackRow]) -> Result<Vec<CellSummary>> {
    let positions: Vec<_> = rows.iter().map(|r| r.position).collect();
    let Some(cell_m) = cell_m.or_else(|| field::default_cell_m(&positions)) else {
        anyhow::bail!(
            "no field written to {}: too few vectors to size its grid (give --field-cell)",
            path.display()
        );
    };
    let mut grid = FieldGrid::new(cell_m, None)?;
    for r in rows {
        grid.add(FieldSample::from(r));
    }
    let cells: Vec<_> = grid.cells().collect();
    let mut file = create_output(path)?;
    let written: Result<()> = match VtkFormat::of(path) {
        Some(format) => vtk::write_field(&mut file, format, &cells).map_err(Into::into),
        None => tables::write_field(&mut file, &cells).map_err(Into::into),
    };
    written
        .and_then(|()| Ok(file.flush()?))
        .with_context(|| format!("writing {}", path.display()))?;
    eprintln!(
        "field: {} cells of {} m from {} vectors -> {}",
        cells.len(),
        cell_m,
        rows.len(),
        path.display()
    );
    Ok(cells)
}

/// Waits for the Rerun logger to drain and says where the log went.
fn report_rerun(logger: RerunLogger, sinks: &[RerunSink]) {
    let summary = logger.finish();
    eprintln!(
        "rerun: {} frames logged to {}{}",
        summary.frames_logged,
        sinks
            .iter()
            .map(|s| match s {
                RerunSink::File(p) => p.display().to_string(),
                RerunSink::Connect(url) => url.clone(),
                RerunSink::Serve(port) => format!("serve:{port}"),
            })
            .collect::<Vec<_>>()
            .join(", "),
        if summary.flushed && summary.errors == 0 {
            ""
        } else {
            " (a sink failed: see the warning above; tracks.csv is complete)"
        }
    );
}
