//! Recording directories (the contract other tools rely on):
//!
//! ```text
//! rec/rig.json          stereo calibration (geometry::RigFile)
//! rec/frames.csv        index,t_s[,world_from_rig_00..world_from_rig_33]
//! rec/left/000000.png   8-bit grayscale, name = index zero-padded to 6 digits
//! rec/right/000000.png
//! ```
//! Optional: `mrptv.toml` (processing config suggested by whoever wrote the recording) and
//! `truth.csv` (synthetic recordings).

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::Isometry3;

use crate::tables::{self, TableError};
use mrptv_engine::geometry::{isometry_from_row_major, CalibrationError, RigFile, StereoRig};

#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{path}: {error}")]
    Json {
        path: PathBuf,
        error: serde_json::Error,
    },
    #[error("{path}: {error}")]
    Calibration {
        path: PathBuf,
        error: CalibrationError,
    },
    #[error(transparent)]
    Table(#[from] TableError),
    #[error("{path}: {message}")]
    Image { path: PathBuf, message: String },
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> RecordingError + '_ {
    move |error| RecordingError::Io {
        path: path.to_path_buf(),
        error,
    }
}

/// One line of `frames.csv`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameEntry {
    pub index: u64,
    pub t_s: f64,
    pub world_from_rig: Option<Isometry3<f64>>,
}

pub(crate) fn image_name(index: u64) -> String {
    format!("{index:06}.png")
}

pub(crate) fn read_rig(path: &Path) -> Result<StereoRig, RecordingError> {
    let text = fs::read_to_string(path).map_err(io_error(path))?;
    parse_rig(path, &text)
}

/// [`read_rig`] of text from anywhere; `path` names it in errors.
pub(crate) fn parse_rig(path: &Path, text: &str) -> Result<StereoRig, RecordingError> {
    let file: RigFile = serde_json::from_str(text).map_err(|error| RecordingError::Json {
        path: path.to_path_buf(),
        error,
    })?;
    StereoRig::from_file(&file).map_err(|error| RecordingError::Calibration {
        path: path.to_path_buf(),
        error,
    })
}

pub(crate) fn write_rig(path: &Path, rig: &StereoRig) -> Result<(), RecordingError> {
    let json =
        serde_json::to_string_pretty(&rig.to_file()).map_err(|error| RecordingError::Json {
            path: path.to_path_buf(),
            error,
        })?;
    fs::write(path, json + "\n").map_err(io_error(path))
}

pub(crate) fn read_frames(path: &Path) -> Result<Vec<FrameEntry>, RecordingError> {
    let file = fs::File::open(path).map_err(io_error(path))?;
    parse_frames(path, std::io::BufReader::new(file))
}

/// [`read_frames`] of text from anywhere; `path` names it in errors.
pub(crate) fn parse_frames(
    path: &Path,
    text: impl std::io::BufRead,
) -> Result<Vec<FrameEntry>, RecordingError> {
    let with_pose = tables::frames_header_with_pose();
    let (variant, rows) = tables::parse_numeric(path, text, &[tables::FRAMES_HEADER, &with_pose])?;
    let row_error = |line: usize, message: String| {
        RecordingError::Table(TableError::Row {
            path: path.to_path_buf(),
            line,
            message,
        })
    };
    let mut frames: Vec<FrameEntry> = Vec::with_capacity(rows.len());
    for row in &rows {
        let index = tables::whole(path, row, 0, "index")?;
        let t_s = row.values[1];
        if let Some(prev) = frames.last() {
            if index <= prev.index {
                return Err(row_error(
                    row.line,
                    format!("index {index} does not increase (previous {})", prev.index),
                ));
            }
            if t_s <= prev.t_s {
                return Err(row_error(
                    row.line,
                    format!("t_s {t_s} does not increase (previous {})", prev.t_s),
                ));
            }
        }
        let world_from_rig = if variant == 1 {
            let mut m = [0.0; 16];
            m.copy_from_slice(&row.values[2..18]);
            Some(
                isometry_from_row_major("world_from_rig", &m)
                    .map_err(|e| row_error(row.line, e.to_string()))?,
            )
        } else {
            None
        };
        frames.push(FrameEntry {
            index,
            t_s,
            world_from_rig,
        });
    }
    Ok(frames)
}

/// Reads an 8-bit grayscale PNG and checks its size.
pub(crate) fn read_gray_png(
    path: &Path,
    width: u32,
    height: u32,
) -> Result<Vec<u8>, RecordingError> {
    let bytes = fs::read(path).map_err(io_error(path))?;
    decode_gray_png(&bytes, width, height).map_err(|message| RecordingError::Image {
        path: path.to_path_buf(),
        message,
    })
}

/// Decodes an 8-bit grayscale PNG of a known size from memory.
pub(crate) fn decode_gray_png(bytes: &[u8], width: u32, height: u32) -> Result<Vec<u8>, String> {
    use image::ImageDecoder;
    let decoder = image::codecs::png::PngDecoder::new(std::io::Cursor::new(bytes))
        .map_err(|e| format!("not a readable PNG: {e}"))?;
    // The decoder reports 1-, 2- and 4-bit grayscale as the 8-bit it expands them to, so the
    // header says what was sent: its bit depth and colour type follow the signature, the IHDR
    // chunk's length and name, width and height (the decoder has checked that header).
    if let (Some(&depth), Some(&colour)) = (bytes.get(24), bytes.get(25)) {
        if (depth, colour) != (8, 0) {
            return Err(format!(
                "expected 8-bit grayscale, found a PNG of colour type {colour} at {depth} bits"
            ));
        }
    }
    let original = decoder.original_color_type();
    if original != image::ExtendedColorType::L8 {
        return Err(format!("expected 8-bit grayscale, found {original:?}"));
    }
    // Checked before decoding: a few kilobytes of PNG can claim gigapixels.
    let (w, h) = decoder.dimensions();
    if (w, h) != (width, height) {
        return Err(format!(
            "image is {w}x{h}, rig.json image_size is {width}x{height}"
        ));
    }
    let image = image::DynamicImage::from_decoder(decoder)
        .map_err(|e| format!("not a readable PNG: {e}"))?;
    let image::DynamicImage::ImageLuma8(gray) = image else {
        return Err(format!(
            "expected 8-bit grayscale, found {:?}",
            image.color()
        ));
    };
    Ok(gray.into_raw())
}

#[cfg(test)]
mod png_tests {
    use super::*;

    #[test]
    fn a_png_claiming_a_huge_image_is_refused_before_decoding() {
        // A valid header for 60000x60000 8-bit grayscale, with almost no data behind it.
        let mut png = encode_gray_png(&[0; 4], 2, 2).expect("png");
        let ihdr = 16; // 8-byte signature, 4-byte length, "IHDR"
        png[ihdr..ihdr + 4].copy_from_slice(&60000u32.to_be_bytes());
        png[ihdr + 4..ihdr + 8].copy_from_slice(&60000u32.to_be_bytes());
        // The chunk's CRC-32 covers its type and 13 data bytes.
        let crc = png[ihdr - 4..ihdr + 13].iter().fold(!0u32, |mut c, &b| {
            c ^= u32::from(b);
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    (c >> 1) ^ 0xEDB8_8320
                } else {
                    c >> 1
                };
            }
            c
        });
        png[ihdr + 13..ihdr + 17].copy_from_slice(&(!crc).to_be_bytes());
        let message = decode_gray_png(&png, 2, 2).expect_err("refused");
        assert!(message.contains("60000x60000"), "{message}");
    }
}

pub fn encode_gray_png(pixels: &[u8], width: u32, height: u32) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    let encoder = image::codecs::png::PngEncoder::new(&mut out);
    image::ImageEncoder::write_image(encoder, pixels, width, height, image::ExtendedColorType::L8)
        .map_err(|e| e.to_string())?;
    Ok(out)
}

/// An opened recording: calibration and frame list read and checked, images read on demand.
#[derive(Debug, Clone)]
pub struct Recording {
    pub dir: PathBuf,
    pub rig: StereoRig,
    pub frames: Vec<FrameEntry>,
}

impl Recording {
    pub fn open(dir: &Path) -> Result<Self, RecordingError> {
        if !dir.is_dir() {
            return Err(RecordingError::Io {
                path: dir.to_path_buf(),
                error: std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    "not a recording directory",
                ),
            });
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            rig: read_rig(&dir.join("rig.json"))?,
            frames: read_frames(&dir.join("frames.csv"))?,
        })
    }

    pub fn left_path(&self, index: u64) -> PathBuf {
        self.dir.join("left").join(image_name(index))
    }

    pub fn right_path(&self, index: u64) -> PathBuf {
        self.dir.join("right").join(image_name(index))
    }

    /// Left and right pixels of one frame.
    pub fn load(&self, entry: &FrameEntry) -> Result<(Vec<u8>, Vec<u8>), RecordingError> {
        let (w, h) = (self.rig.width, self.rig.height);
        Ok((
            read_gray_png(&self.left_path(entry.index), w, h)?,
            read_gray_png(&self.right_path(entry.index), w, h)?,
        ))
    }
}

/// Writes a recording frame by frame. Each image is written to a temporary name and renamed, and
/// the frame's line is appended to `frames.csv` only after both images are in place, so a
/// recording cut short at any moment lists only complete frames.
pub(crate) struct RecordingWriter {
    dir: PathBuf,
    frames: fs::File,
    /// Sync each image before naming it (live recordings, whose frames are acknowledged).
    durable: bool,
    with_pose: bool,
    width: u32,
    height: u32,
}

impl RecordingWriter {
    pub(crate) fn create(
        dir: &Path,
        rig: &StereoRig,
        with_pose: bool,
    ) -> Result<Self, RecordingError> {
        for sub in ["left", "right"] {
            let d = dir.join(sub);
            fs::create_dir_all(&d).map_err(io_error(&d))?;
        }
        write_rig(&dir.join("rig.json"), rig)?;
        let path = dir.join("frames.csv");
        let mut frames = fs::File::create(&path).map_err(io_error(&path))?;
        let header = if with_pose {
            tables::frames_header_with_pose()
        } else {
            tables::FRAMES_HEADER.to_string()
        };
        writeln!(frames, "{header}").map_err(io_error(&path))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            frames,
            durable: false,
            with_pose,
            width: rig.width,
            height: rig.height,
        })
    }

    /// From now on each frame is made durable by [`Self::sync`] (images are synced before they
    /// are named); the recording's directory, `rig.json` and header are synced now.
    pub(crate) fn into_durable(mut self) -> Result<Self, RecordingError> {
        self.durable = true;
        let rig = self.dir.join("rig.json");
        fs::File::open(&rig)
            .and_then(|f| f.sync_all())
            .map_err(io_error(&rig))?;
        self.sync()?;
        let parent = self.dir.parent().filter(|p| !p.as_os_str().is_empty());
        for d in [Some(self.dir.as_path()), parent].into_iter().flatten() {
            fs::File::open(d)
                .and_then(|f| f.sync_all())
                .map_err(io_error(d))?;
        }
        Ok(self)
    }

    pub(crate) fn write_frame(
        &mut self,
        entry: &FrameEntry,
        left: &[u8],
        right: &[u8],
    ) -> Result<(), RecordingError> {
        for (sub, pixels) in [("left", left), ("right", right)] {
            let path = self.dir.join(sub).join(image_name(entry.index));
            let png = encode_gray_png(pixels, self.width, self.height).map_err(|message| {
                RecordingError::Image {
                    path: path.clone(),
                    message,
                }
            })?;
            let tmp = path.with_extension("png.tmp");
            fs::write(&tmp, png).map_err(io_error(&tmp))?;
            if self.durable {
                // The data reaches the disk before the name does: a crash leaves the old name
                // (none) or the whole image, never a short one.
                fs::File::open(&tmp)
                    .and_then(|f| f.sync_data())
                    .map_err(io_error(&tmp))?;
            }
            fs::rename(&tmp, &path).map_err(io_error(&path))?;
        }
        let pose = if self.with_pose {
            Some(entry.world_from_rig.unwrap_or_else(Isometry3::identity))
        } else {
            None
        };
        let path = self.dir.join("frames.csv");
        // One write of the whole line: a process killed mid-frame leaves whole lines only.
        self.frames
            .write_all(tables::format_frame_row(entry.index, entry.t_s, pose.as_ref()).as_bytes())
            .map_err(io_error(&path))
    }

    /// Makes every frame written so far durable: the images' directory entries and
    /// `frames.csv` are synced. A frame is safe from power loss once this returns.
    pub(crate) fn sync(&mut self) -> Result<(), RecordingError> {
        for sub in ["left", "right"] {
            let d = self.dir.join(sub);
            fs::File::open(&d)
                .and_then(|f| f.sync_all())
                .map_err(io_error(&d))?;
        }
        let path = self.dir.join("frames.csv");
        self.frames.sync_data().map_err(io_error(&path))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mrptv_engine::synth::{Scenario, ScenarioSpec, Synthesizer};

    #[test]
    fn written_recording_reads_back_exactly() {
        let dir = tempfile::tempdir().expect("tmp");
        let spec = ScenarioSpec::new(Scenario::MovingHead);
        let rig = spec.rig.clone();
        let mut synth = Synthesizer::new(spec, 10, 1);
        let mut writer = RecordingWriter::create(dir.path(), &rig, true).expect("create");
        let mut written = Vec::new();
        for _ in 0..3 {
            let f = synth.next_frame();
            let entry = FrameEntry {
                index: f.index,
                t_s: f.t_s,
                world_from_rig: f.world_from_rig,
            };
            writer
                .write_frame(&entry, &f.left, &f.right)
                .expect("write");
            written.push((entry, f.left));
        }
        drop(writer);
        let rec = Recording::open(dir.path()).expect("open");
        assert_eq!(rec.rig, rig);
        for ((entry, left), read) in written.iter().zip(&rec.frames) {
            assert_eq!(entry.index, read.index);
            assert_eq!(entry.t_s, read.t_s);
            let (a, b) = (
                entry.world_from_rig.expect("pose"),
                read.world_from_rig.expect("pose"),
            );
            assert!((a.to_homogeneous() - b.to_homogeneous()).abs().max() < 1e-12);
            assert_eq!(&rec.load(read).expect("images").0, left);
        }
    }

    #[test]
    fn decreasing_time_and_bad_pose_name_the_line() {
        let dir = tempfile::tempdir().expect("tmp");
        let p = dir.path().join("frames.csv");
        fs::write(&p, "index,t_s\n0,0.5\n1,0.4\n").expect("write");
        let e = read_frames(&p).unwrap_err().to_string();
        assert!(
            e.ends_with("frames.csv line 3: t_s 0.4 does not increase (previous 0.5)"),
            "{e}"
        );
        let header = tables::frames_header_with_pose();
        fs::write(
            &p,
            format!("{header}\n0,0,2,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1\n"),
        )
        .expect("write");
        let e = read_frames(&p).unwrap_err().to_string();
        assert!(
            e.contains("line 2: world_from_rig: is not a rotation"),
            "{e}"
        );
    }

    #[test]
    fn malformed_rig_json_names_file_and_position() {
        let dir = tempfile::tempdir().expect("tmp");
        let p = dir.path().join("rig.json");
        fs::write(&p, "{ \"image_size\": [640, 480],\n \"K1\": oops }").expect("write");
        let e = read_rig(&p).unwrap_err().to_string();
        assert!(e.contains("rig.json") && e.contains("line 2"), "{e}");
    }

    #[test]
    fn non_png_and_colour_png_are_rejected() {
        assert!(decode_gray_png(b"not a png", 4, 4)
            .unwrap_err()
            .starts_with("not a readable PNG"));
        let mut rgb = Vec::new();
        image::ImageEncoder::write_image(
            image::codecs::png::PngEncoder::new(&mut rgb),
            &[0u8; 4 * 4 * 3],
            4,
            4,
            image::ExtendedColorType::Rgb8,
        )
        .expect("encode");
        assert!(decode_gray_png(&rgb, 4, 4)
            .unwrap_err()
            .starts_with("expected 8-bit grayscale"));
        for depth in [png::BitDepth::One, png::BitDepth::Two, png::BitDepth::Four] {
            let packed = sub_byte_gray_png(depth);
            assert!(
                decode_gray_png(&packed, 4, 4)
                    .unwrap_err()
                    .starts_with("expected 8-bit grayscale"),
                "{depth:?}"
            );
        }
        let gray = encode_gray_png(&[0u8; 16], 4, 4).expect("encode");
        assert!(decode_gray_png(&gray, 5, 4)
            .unwrap_err()
            .contains("image is 4x4, rig.json image_size is 5x4"));
    }

    /// A 4x4 grayscale PNG packed at fewer than 8 bits a pixel.
    pub(crate) fn sub_byte_gray_png(depth: png::BitDepth) -> Vec<u8> {
        let mut bytes = Vec::new();
        let mut encoder = png::Encoder::new(&mut bytes, 4, 4);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(depth);
        let row_bytes = (4 * depth as usize).div_ceil(8);
        let mut writer = encoder.write_header().expect("header");
        writer
            .write_image_data(&vec![0u8; row_bytes * 4])
            .expect("data");
        writer.finish().expect("finish");
        bytes
    }
}
