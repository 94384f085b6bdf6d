//! What `mrptv process` and `replay` read from a recording directory: `frames.csv`, `rig.json`,
//! the PNG images and `mrptv.toml`. The first byte picks the file; nothing may panic, and a PNG
//! is never decoded beyond the size the rig declares.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use mrptv::recording::{decode_gray_png, parse_frames, parse_rig};

fuzz_target!(|data: &[u8]| {
    let Some((&which, rest)) = data.split_first() else {
        return;
    };
    match which % 4 {
        0 => {
            if let Ok(frames) = parse_frames(Path::new("frames.csv"), rest) {
                assert!(frames.windows(2).all(|w| w[0].index < w[1].index && w[0].t_s < w[1].t_s));
                assert!(frames.iter().all(|f| f.t_s.is_finite()));
            }
        }
        1 => {
            if let Ok(text) = std::str::from_utf8(rest) {
                let _ = parse_rig(Path::new("rig.json"), text);
            }
        }
        2 => {
            // The rig's size first (two bytes a side, kept small), then the file.
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
                let _ = mrptv::config::parse(Path::new("mrptv.toml"), text);
            }
        }
    }
});
