//! H.264 for hl2ss's compressed visible-light streams (`mrptv hl2ss --codec h264`) and for
//! measuring what a bitrate costs (`mrptv demo --h264-mbps`): 8-bit grayscale frames in and out
//! of Annex-B access units, through Cisco's OpenH264. hl2ss encodes the VLC image as the luma of
//! an NV12 frame with neutral chroma; so does [`H264Encoder`], and `H264Decoder` returns the
//! luma.

use openh264::decoder::Decoder;
use openh264::encoder::{
    BitRate, Encoder, EncoderConfig, FrameRate, IntraFramePeriod, Profile, RateControlMode,
    UsageType,
};
use openh264::formats::{YUVSlices, YUVSource};
use openh264::{OpenH264API, Timestamp};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VideoError {
    #[error("H.264 encoder: {0}")]
    Encoder(String),
    #[error("H.264 decoder: {0}")]
    Decoder(String),
    #[error("H.264 picture is {got_width}x{got_height}, the stream's images are {width}x{height}")]
    Size {
        got_width: usize,
        got_height: usize,
        width: usize,
        height: usize,
    },
}

/// Encodes grayscale frames as hl2ss's H.264 stream does: constrained baseline, a target bitrate,
/// an IDR (with its SPS and PPS) every `gop_frames`.
pub struct H264Encoder {
    encoder: Encoder,
    width: usize,
    height: usize,
    chroma: Vec<u8>,
    frame_interval_ms: f64,
    frames: u64,
}

impl H264Encoder {
    pub fn new(
        width: u32,
        height: u32,
        bitrate_bps: u32,
        frame_rate_hz: f32,
        gop_frames: u32,
    ) -> Result<Self, VideoError> {
        let config = EncoderConfig::new()
            .bitrate(BitRate::from_bps(bitrate_bps))
            .max_frame_rate(FrameRate::from_hz(frame_rate_hz))
            // The default (quality) mode ignores the bitrate.
            .rate_control_mode(RateControlMode::Bitrate)
            .profile(Profile::Baseline)
            .usage_type(UsageType::CameraVideoRealTime)
            // Every frame is measured: none may be dropped to hold the rate.
            .skip_frames(false)
            .intra_frame_period(IntraFramePeriod::from_num_frames(gop_frames.max(1)))
            .num_threads(1);
        let encoder = Encoder::with_api_config(OpenH264API::from_source(), config)
            .map_err(|e| VideoError::Encoder(e.to_string()))?;
        let (w, h) = (width as usize, height as usize);
        Ok(Self {
            encoder,
            width: w,
            height: h,
            chroma: vec![128; w.div_ceil(2) * h.div_ceil(2)],
            frame_interval_ms: 1e3 / f64::from(frame_rate_hz.max(1.0)),
            frames: 0,
        })
    }

    /// One frame (`width * height` bytes) as an Annex-B access unit.
    pub fn encode(&mut self, gray: &[u8]) -> Result<Vec<u8>, VideoError> {
        let (w, h) = (self.width, self.height);
        let half = w.div_ceil(2);
        let yuv = YUVSlices::new((gray, &self.chroma, &self.chroma), (w, h), (w, half, half));
        let at = Timestamp::from_millis((self.frames as f64 * self.frame_interval_ms) as u64);
        self.frames += 1;
        let stream = self
            .encoder
            .encode_at(&yuv, at)
            .map_err(|e| VideoError::Encoder(e.to_string()))?;
        Ok(stream.to_vec())
    }
}

/// Decodes an H.264 stream access unit by access unit, into grayscale frames of a known size.
pub(crate) struct H264Decoder {
    decoder: Decoder,
    width: usize,
    height: usize,
}

impl H264Decoder {
    pub(crate) fn new(width: u32, height: u32) -> Result<Self, VideoError> {
        Ok(Self {
            decoder: Decoder::new().map_err(|e| VideoError::Decoder(e.to_string()))?,
            width: width as usize,
            height: height as usize,
        })
    }

    /// The picture of one access unit; `None` while the stream has given none yet (it must
    /// start with an IDR and its parameter sets, as hl2ss's does on connecting).
    pub(crate) fn decode(&mut self, access_unit: &[u8]) -> Result<Option<Vec<u8>>, VideoError> {
        let Some(yuv) = self
            .decoder
            .decode(access_unit)
            .map_err(|e| VideoError::Decoder(e.to_string()))?
        else {
            return Ok(None);
        };
        let (w, h) = yuv.dimensions();
        if (w, h) != (self.width, self.height) {
            return Err(VideoError::Size {
                got_width: w,
                got_height: h,
                width: self.width,
                height: self.height,
            });
        }
        // Rows are padded: the stride is not the width.
        let stride = yuv.strides().0;
        let luma = yuv.y();
        let mut gray = Vec::with_capacity(w * h);
        for row in 0..h {
            gray.extend_from_slice(&luma[row * stride..row * stride + w]);
        }
        Ok(Some(gray))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_survive_the_codec_with_their_particles_in_place() {
        let (w, h) = (160usize, 96usize);
        let frame = |shift: f64| -> Vec<u8> {
            (0..h)
                .flat_map(|y| (0..w).map(move |x| (x, y)))
                .map(|(x, y)| {
                    let d2 = (x as f64 - 40.0 - shift).powi(2) + (y as f64 - 50.0).powi(2);
                    (20.0 + 160.0 * (-d2 / 4.0).exp()) as u8
                })
                .collect()
        };
        let mut encoder =
            H264Encoder::new(w as u32, h as u32, 2_000_000, 30.0, 30).expect("encoder");
        let mut decoder = H264Decoder::new(w as u32, h as u32).expect("decoder");
        for k in 0..10 {
            let original = frame(2.0 * k as f64);
            let unit = encoder.encode(&original).expect("encodes");
            assert!(
                !unit.is_empty() && unit.len() < w * h,
                "{} bytes",
                unit.len()
            );
            let back = decoder
                .decode(&unit)
                .expect("decodes")
                .expect("a picture per unit");
            let peak = |img: &[u8]| (0..w * h).max_by_key(|&i| img[i]).expect("pixels");
            assert_eq!(peak(&back) % w, peak(&original) % w, "frame {k}");
        }
        // A decoder for another size refuses the stream with both sizes named.
        let mut other = H264Decoder::new(320, 240).expect("decoder");
        let mut encoder =
            H264Encoder::new(w as u32, h as u32, 2_000_000, 30.0, 30).expect("encoder");
        let unit = encoder.encode(&frame(0.0)).expect("encodes");
        let e = other.decode(&unit).expect_err("refused");
        assert!(e.to_string().contains("160x96"), "{e}");
    }
}
