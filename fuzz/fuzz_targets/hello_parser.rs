//! A client's text messages (`hello` with its calibration and config, and the viewer requests),
//! then what the server builds from a hello it accepts: the rig (calibration checks,
//! rectification) and the pipeline. Nothing may panic or allocate without bound.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| mrptv::fuzzing::hello_parser(data));
