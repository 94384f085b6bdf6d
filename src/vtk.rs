//! VTK files ParaView opens as points carrying data: `.vtu` (VTK XML unstructured grid) or `.vtk`
//! (legacy, version 4.2), ASCII, one vertex cell per point. Written by hand: two small text
//! formats, not worth a dependency.

use std::io::Write;
use std::path::Path;

use nalgebra::{Point3, Vector3};

use crate::tables::TrackRow;
use mrptv_engine::field::CellSummary;

/// Which VTK file a path asks for, by its extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VtkFormat {
    /// `.vtu`: VTK XML UnstructuredGrid.
    Xml,
    /// `.vtk`: legacy ASCII.
    Legacy,
}

impl VtkFormat {
    /// `None` for a path that is not `.vtu` or `.vtk` (any case).
    pub fn of(path: &Path) -> Option<Self> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "vtu" => Some(Self::Xml),
            "vtk" => Some(Self::Legacy),
            _ => None,
        }
    }
}

/// A per-point array: `components` values per point, point after point.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PointArray {
    pub(crate) name: &'static str,
    pub(crate) components: usize,
    pub(crate) values: Vec<f64>,
}

impl PointArray {
    pub(crate) fn new(name: &'static str, components: usize) -> Self {
        Self {
            name,
            components,
            values: Vec::new(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum VtkError {
    #[error("VTK array '{name}' holds {values} values, not {expected} ({components} per point)")]
    Shape {
        name: &'static str,
        values: usize,
        components: usize,
        expected: usize,
    },
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// Writes `points` with their `arrays`; the array named `vectors` (if any) is marked as the
/// points' vectors, so ParaView's glyphs use it by default.
pub(crate) fn write_points(
    out: &mut impl Write,
    format: VtkFormat,
    title: &str,
    points: &[Point3<f64>],
    arrays: &[PointArray],
    vectors: &str,
) -> Result<(), VtkError> {
    let n = points.len();
    for a in arrays {
        if a.values.len() != n * a.components {
            return Err(VtkError::Shape {
                name: a.name,
                values: a.values.len(),
                components: a.components,
                expected: n * a.components,
            });
        }
    }
    match format {
        VtkFormat::Xml => write_xml(out, points, arrays, vectors)?,
        VtkFormat::Legacy => write_legacy(out, title, points, arrays, vectors)?,
    }
    Ok(())
}

fn push3(array: &mut PointArray, v: &Vector3<f64>) {
    array.values.extend_from_slice(&[v.x, v.y, v.z]);
}

/// `tracks.csv`'s rows as points: `velocity`, `frame`, `t_s`, `track_id` and (where the rows
/// carry them) `velocity_sigma`, `position_sigma`.
pub fn write_tracks(
    out: &mut impl Write,
    format: VtkFormat,
    rows: &[TrackRow],
) -> Result<(), VtkError> {
    let mut velocity = PointArray::new("velocity", 3);
    let mut frame = PointArray::new("frame", 1);
    let mut t_s = PointArray::new("t_s", 1);
    let mut track_id = PointArray::new("track_id", 1);
    let mut velocity_sigma = PointArray::new("velocity_sigma", 3);
    let mut position_sigma = PointArray::new("position_sigma", 3);
    let with_sigma = rows.iter().all(|r| r.sigma.is_some());
    for r in rows {
        push3(&mut velocity, &r.velocity);
        frame.values.push(r.frame as f64);
        t_s.values.push(r.t_s);
        track_id.values.push(r.track_id as f64);
        if let (true, Some((sv, sp))) = (with_sigma, r.sigma) {
            push3(&mut velocity_sigma, &sv);
            push3(&mut position_sigma, &sp);
        }
    }
    let mut arrays = vec![velocity, frame, t_s, track_id];
    if with_sigma {
        arrays.extend([velocity_sigma, position_sigma]);
    }
    let points: Vec<Point3<f64>> = rows.iter().map(|r| r.position).collect();
    write_points(out, format, "mrptv tracks", &points, &arrays, "velocity")
}

/// A field's cells as points at their centres: `velocity` (the mean), `n`, `std`, `sem`,
/// `tracks`, `speed` (of the mean).
pub fn write_field(
    out: &mut impl Write,
    format: VtkFormat,
    cells: &[CellSummary],
) -> Result<(), VtkError> {
    let mut velocity = PointArray::new("velocity", 3);
    let mut n = PointArray::new("n", 1);
    let mut std = PointArray::new("std", 3);
    let mut sem = PointArray::new("sem", 3);
    let mut tracks = PointArray::new("tracks", 1);
    let mut speed = PointArray::new("speed", 1);
    for c in cells {
        push3(&mut velocity, &c.mean);
        n.values.push(c.samples as f64);
        push3(&mut std, &c.std);
        push3(&mut sem, &c.sem);
        tracks.values.push(c.tracks as f64);
        speed.values.push(c.mean.norm());
    }
    let points: Vec<Point3<f64>> = cells.iter().map(|c| c.centre).collect();
    write_points(
        out,
        format,
        "mrptv field",
        &points,
        &[velocity, n, std, sem, tracks, speed],
        "velocity",
    )
}

/// Values, a point's components per line (shortest round-trip formatting: exact).
fn write_values(out: &mut impl Write, values: &[f64], per_line: usize) -> std::io::Result<()> {
    for row in values.chunks(per_line.max(1)) {
        let line: Vec<String> = row.iter().map(|v| format!("{v}")).collect();
        writeln!(out, "{}", line.join(" "))?;
    }
    Ok(())
}

fn coordinates(points: &[Point3<f64>]) -> Vec<f64> {
    points.iter().flat_map(|p| [p.x, p.y, p.z]).collect()
}

fn write_xml(
    out: &mut impl Write,
    points: &[Point3<f64>],
    arrays: &[PointArray],
    vectors: &str,
) -> std::io::Result<()> {
    let n = points.len();
    writeln!(out, r#"<?xml version="1.0"?>"#)?;
    writeln!(
        out,
        r#"<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" header_type="UInt64">"#
    )?;
    writeln!(out, "<UnstructuredGrid>")?;
    writeln!(out, r#"<Piece NumberOfPoints="{n}" NumberOfCells="{n}">"#)?;
    if arrays.iter().any(|a| a.name == vectors) {
        writeln!(out, r#"<PointData Vectors="{vectors}">"#)?;
    } else {
        writeln!(out, "<PointData>")?;
    }
    for a in arrays {
        writeln!(
            out,
            r#"<DataArray type="Float64" Name="{}" NumberOfComponents="{}" format="ascii">"#,
            a.name, a.components
        )?;
        write_values(out, &a.values, a.components)?;
        writeln!(out, "</DataArray>")?;
    }
    writeln!(out, "</PointData>")?;
    writeln!(out, "<Points>")?;
    writeln!(
        out,
        r#"<DataArray type="Float64" NumberOfComponents="3" format="ascii">"#
    )?;
    write_values(out, &coordinates(points), 3)?;
    writeln!(out, "</DataArray>")?;
    writeln!(out, "</Points>")?;
    writeln!(out, "<Cells>")?;
    let index_list =
        |from: usize| -> Vec<String> { (from..n + from).map(|i| i.to_string()).collect() };
    writeln!(
        out,
        r#"<DataArray type="Int64" Name="connectivity" format="ascii">"#
    )?;
    writeln!(out, "{}", index_list(0).join(" "))?;
    writeln!(out, "</DataArray>")?;
    writeln!(
        out,
        r#"<DataArray type="Int64" Name="offsets" format="ascii">"#
    )?;
    writeln!(out, "{}", index_list(1).join(" "))?;
    writeln!(out, "</DataArray>")?;
    // Cell type 1: VTK_VERTEX.
    writeln!(
        out,
        r#"<DataArray type="UInt8" Name="types" format="ascii">"#
    )?;
    writeln!(out, "{}", vec!["1"; n].join(" "))?;
    writeln!(out, "</DataArray>")?;
    writeln!(out, "</Cells>")?;
    writeln!(out, "</Piece>")?;
    writeln!(out, "</UnstructuredGrid>")?;
    writeln!(out, "</VTKFile>")?;
    Ok(())
}

fn write_legacy(
    out: &mut impl Write,
    title: &str,
    points: &[Point3<f64>],
    arrays: &[PointArray],
    vectors: &str,
) -> std::io::Result<()> {
    let n = points.len();
    writeln!(out, "# vtk DataFile Version 4.2")?;
    // The title line is one line of at most 256 characters.
    let title: String = title.chars().filter(|c| *c != '\n').take(255).collect();
    writeln!(out, "{title}")?;
    writeln!(out, "ASCII")?;
    writeln!(out, "DATASET UNSTRUCTURED_GRID")?;
    writeln!(out, "POINTS {n} double")?;
    write_values(out, &coordinates(points), 3)?;
    writeln!(out, "CELLS {n} {}", 2 * n)?;
    for i in 0..n {
        writeln!(out, "1 {i}")?;
    }
    writeln!(out, "CELL_TYPES {n}")?;
    for _ in 0..n {
        writeln!(out, "1")?;
    }
    writeln!(out, "POINT_DATA {n}")?;
    let (marked, others): (Vec<&PointArray>, Vec<&PointArray>) = arrays
        .iter()
        .partition(|a| a.name == vectors && a.components == 3);
    for a in &marked {
        writeln!(out, "VECTORS {} double", a.name)?;
        write_values(out, &a.values, 3)?;
    }
    if !others.is_empty() {
        writeln!(out, "FIELD point_data {}", others.len())?;
        for a in others {
            writeln!(out, "{} {} {n} double", a.name, a.components)?;
            write_values(out, &a.values, a.components)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn example() -> (Vec<Point3<f64>>, Vec<PointArray>) {
        let points = vec![Point3::new(0.0, 0.5, 1.0), Point3::new(-0.25, 0.0, 2.0)];
        let mut velocity = PointArray::new("velocity", 3);
        velocity.values = vec![1.0, 0.0, 0.0, 0.0, 0.5, -0.125];
        let mut count = PointArray::new("n", 1);
        count.values = vec![3.0, 40.0];
        (points, vec![velocity, count])
    }

    fn text(format: VtkFormat) -> String {
        let (points, arrays) = example();
        let mut out = Vec::new();
        write_points(&mut out, format, "t", &points, &arrays, "velocity").expect("write");
        String::from_utf8(out).expect("utf-8")
    }

    #[test]
    fn formats_follow_the_extension() {
        assert_eq!(VtkFormat::of(Path::new("a/f.vtu")), Some(VtkFormat::Xml));
        assert_eq!(VtkFormat::of(Path::new("f.VTK")), Some(VtkFormat::Legacy));
        assert_eq!(VtkFormat::of(Path::new("f.csv")), None);
        assert_eq!(VtkFormat::of(Path::new("vtu")), None);
    }

    #[test]
    fn xml_holds_vertices_and_arrays() {
        let t = text(VtkFormat::Xml);
        assert!(t.contains(r#"<Piece NumberOfPoints="2" NumberOfCells="2">"#));
        assert!(t.contains(r#"<PointData Vectors="velocity">"#));
        assert!(t.contains("0 0.5 -0.125\n"));
        assert!(t.contains("-0.25 0 2\n"));
        assert!(t.contains("\n1 2\n"), "offsets");
    }

    #[test]
    fn legacy_marks_vectors_and_lists_the_rest_as_field_data() {
        let t = text(VtkFormat::Legacy);
        assert!(t.starts_with("# vtk DataFile Version 4.2\nt\nASCII\n"));
        assert!(t.contains("CELLS 2 4\n1 0\n1 1\nCELL_TYPES 2\n1\n1\n"));
        assert!(t.contains("VECTORS velocity double\n1 0 0\n0 0.5 -0.125\n"));
        assert!(t.contains("FIELD point_data 1\nn 1 2 double\n3\n40\n"));
    }

    #[test]
    fn an_array_of_the_wrong_length_is_refused() {
        let (points, mut arrays) = example();
        arrays[1].values.pop();
        let err = write_points(
            &mut Vec::new(),
            VtkFormat::Xml,
            "t",
            &points,
            &arrays,
            "velocity",
        )
        .expect_err("short array");
        assert!(
            err.to_string().contains("'n' holds 1 values, not 2"),
            "{err}"
        );
    }
}
