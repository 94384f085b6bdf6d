//! The binary messages of `protocol/`: a headset's stereo frame (what the server decodes from
//! any client) and a vector batch (what clients decode). Nothing may panic; a frame that
//! decodes must survive a round trip.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mrptv::protocol::{decode_batch, decode_frame, encode_frame};

fuzz_target!(|data: &[u8]| {
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
        assert!(batch.vectors.len() <= data.len() / 32, "no more vectors than bytes allow");
    }
});
