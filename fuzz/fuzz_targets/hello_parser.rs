//! A client's text messages (`hello` with its calibration and config, and the viewer requests),
//! then what the server builds from a hello it accepts: the rig (calibration checks,
//! rectification) and the pipeline. Nothing may panic or allocate without bound.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mrptv::geometry::StereoRig;
use mrptv::protocol::{parse_text, HeadsetMessage, ViewerMessage, HEADSET_TYPES, VIEWER_TYPES};
use mrptv::ptv::Pipeline;

/// `mrptv serve`'s default --max-image-size: larger hellos never reach the pipeline.
const MAX_IMAGE_SIDE: u32 = 4096;

fuzz_target!(|data: &[u8]| {
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
});
