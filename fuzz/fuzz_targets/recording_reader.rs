//! What `mrptv process` and `replay` read from a recording directory: `frames.csv`, `rig.json`,
//! the PNG images and `mrptv.toml`. The first byte picks the file; nothing may panic, and a PNG
//! is never decoded beyond the size the rig declares.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| mrptv::fuzzing::recording_reader(data));
