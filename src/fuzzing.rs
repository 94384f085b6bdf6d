//! The bodies of the fuzz targets in `fuzz/` (cargo-fuzz, libFuzzer), kept in the library so
//! `cargo test` replays the checked-in corpus and every input that ever failed
//! (`fuzz/regressions/`) through exactly the checks the fuzzer runs. Each takes any bytes and
//! panics only on a broken invariant.

use std::path::Path;

use crate::protocol::{
    decode_batch, decode_frame, encode_frame, parse_text, HeadsetMessage, ViewerMessage,
    HEADSET_TYPES, VIEWER_TYPES,
};
use crate::recording::{decode_gray_png, parse_frames, parse_rig};
use mrptv_engine::geometry::StereoRig;
use mrptv_engine::Pipeline;

/// `mrptv serve`'s default `--max-image-size`: larger hellos never reach the pipeline.
const MAX_IMAGE_SIDE: u32 = 4096;

/// The binary messages: a headset's stereo frame (what the server decodes from any client) and
/// a vector batch (what clients decode). A frame that decodes survives a round trip.
pub fn frame_decoder(data: &[u8]) {
    if let Ok(frame) = decode_frame(data) {
        assert!(frame.t_s.is_finite(), "a decoded timestamp is finite");
        let again = encode_frame(&frame).expect("a decoded frame encodes");
        let back = decode_frame(&again).expect("a re-encoded frame decodes");
        assert_eq!(back.frame_index, frame.frame_index);
        assert_eq!(back.t_s.to_bits(), frame.t_s.to_bits());
        assert_eq!(back.encoding, frame.encoding);
        assert_eq!((back.left, back.right), (frame.left, frame.right));
        match (back.world_from_rig, frame.world_from_rig) {
            (None, None) => assert_eq!(again, data, "without a pose, byte for byte"),
            (Some(a), Some(b)) => {
                let d = (a.to_homogeneous() - b.to_homogeneous()).abs().max();
                assert!(d < 1e-9, "pose survives the round trip: {d}");
            }
            _ => panic!("pose lost or invented"),
        }
    }
    if let Ok(batch) = decode_batch(data) {
        assert!(
            batch.vectors.len() <= data.len() / 32,
            "no more vectors than bytes allow"
        );
    }
}

/// A client's text messages, then what the server builds from a hello it accepts: the rig
/// (calibration checks, rectification) and the pipeline.
pub fn hello_parser(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let _ = parse_text::<ViewerMessage>(text, VIEWER_TYPES);
    let Ok(HeadsetMessage::Hello(hello)) = parse_text::<HeadsetMessage>(text, HEADSET_TYPES) else {
        return;
    };
    let Ok(rig) = StereoRig::from_file(&hello.rig) else {
        return;
    };
    if rig.width <= MAX_IMAGE_SIDE && rig.height <= MAX_IMAGE_SIDE {
        let _ = Pipeline::new(rig, hello.config.unwrap_or_default());
    }
}

/// What the offline commands read from a recording directory; the first byte picks the file:
/// `frames.csv`, `rig.json`, a PNG image (after a 4-byte size) or `mrptv.toml`.
pub fn recording_reader(data: &[u8]) {
    let Some((&which, rest)) = data.split_first() else {
        return;
    };
    match which % 4 {
        0 => {
            if let Ok(frames) = parse_frames(Path::new("frames.csv"), rest) {
                assert!(frames
                    .windows(2)
                    .all(|w| w[0].index < w[1].index && w[0].t_s < w[1].t_s));
                assert!(frames.iter().all(|f| f.t_s.is_finite()));
            }
        }
        1 => {
            if let Ok(text) = std::str::from_utf8(rest) {
                let _ = parse_rig(Path::new("rig.json"), text);
            }
        }
        2 => {
            // The rig's size (two bytes a side, kept small), then the file: a PNG is never
            // decoded beyond the size the rig declares.
            if rest.len() < 4 {
                return;
            }
            let w = u32::from(u16::from_le_bytes([rest[0], rest[1]]) % 1024);
            let h = u32::from(u16::from_le_bytes([rest[2], rest[3]]) % 1024);
            if let Ok(pixels) = decode_gray_png(&rest[4..], w, h) {
                assert_eq!(pixels.len(), (w * h) as usize);
            }
        }
        _ => {
            if let Ok(text) = std::str::from_utf8(rest) {
                let _ = crate::config::parse(Path::new("mrptv.toml"), text);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every input kept for `target`: its corpus and the inputs that once failed.
    fn kept_inputs(target: &str) -> Vec<(String, Vec<u8>)> {
        let fuzz = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
        let mut inputs = Vec::new();
        for dir in [
            fuzz.join("corpus").join(target),
            fuzz.join("regressions").join(target),
        ] {
            let Ok(entries) = std::fs::read_dir(&dir) else {
                continue;
            };
            for entry in entries.flatten() {
                let path = entry.path();
                inputs.push((
                    path.display().to_string(),
                    std::fs::read(&path).expect("readable"),
                ));
            }
        }
        inputs
    }

    fn replay(target: &str, check: fn(&[u8])) {
        let inputs = kept_inputs(target);
        assert!(inputs.len() >= 3, "{target}: a corpus is checked in");
        for (name, data) in inputs {
            if std::panic::catch_unwind(|| check(&data)).is_err() {
                panic!("{name} fails {target} again");
            }
        }
    }

    #[test]
    fn the_frame_decoder_corpus_and_regressions_pass() {
        replay("frame_decoder", frame_decoder);
    }

    #[test]
    fn the_hello_parser_corpus_and_regressions_pass() {
        replay("hello_parser", hello_parser);
    }

    #[test]
    fn the_recording_reader_corpus_and_regressions_pass() {
        replay("recording_reader", recording_reader);
    }
}
