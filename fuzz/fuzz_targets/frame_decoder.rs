//! The binary messages of `protocol/`: a headset's stereo frame (what the server decodes from
//! any client) and a vector batch (what clients decode). Nothing may panic; a frame that
//! decodes must survive a round trip.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| mrptv::fuzzing::frame_decoder(data));
