//! MP4 video: frames encoded as H.264 (Cisco's OpenH264, built from source by the `openh264` crate, so no
//! system ffmpeg is needed) and muxed into an MP4 file (the `mp4` crate) that players, browsers and
//! ffprobe open.

use std::path::Path;

use image::RgbImage;
use mp4::{AvcConfig, MediaConfig, Mp4Config, Mp4Sample, Mp4Writer, TrackConfig, TrackType};
use openh264::encoder::{Encoder, EncoderConfig, FrameRate, RateControlMode};
use openh264::formats::{RgbSliceU8, YUVBuffer};
use openh264::OpenH264API;

use crate::error::{Error, Result};
use crate::output::image_out::frame_size;
use crate::whole_file::OutputFile;

/// Ticks per second of the video track's clock.
const TIMESCALE: u32 = 1000;

/// Writes `frames` (all of one size; odd sides are padded to even by repeating the last row or column,
/// as H.264's 4:2:0 sampling needs) as an H.264 MP4 showing each frame for `frame_ms` milliseconds.
pub fn save_mp4(path: &Path, frames: &[RgbImage], frame_ms: u32) -> Result<()> {
    let (w, h) = frame_size(path, frames)?;
    let fail = |e: &dyn std::fmt::Display| Error::write(path, e);
    let (even_w, even_h) = (w.next_multiple_of(2), h.next_multiple_of(2));
    if even_w > u32::from(u16::MAX) || even_h > u32::from(u16::MAX) || frame_ms == 0 {
        return Err(fail(&format!("cannot encode {w}×{h} frames of {frame_ms} ms")));
    }
    let fps = 1000.0 / frame_ms as f32;
    // Without rate control: every frame at the encoder's fixed quality, none skipped.
    let config = EncoderConfig::new()
        .max_frame_rate(FrameRate::from_hz(fps))
        .rate_control_mode(RateControlMode::Off)
        .skip_frames(false);
    let mut encoder = Encoder::with_api_config(OpenH264API::from_source(), config).map_err(|e| fail(&e))?;
    let (mut sps, mut pps) = (None, None);
    let mut samples = Vec::with_capacity(frames.len());
    for (k, frame) in frames.iter().enumerate() {
        let padded = pad_to_even(frame);
        let rgb = RgbSliceU8::new(padded.as_raw(), (even_w as usize, even_h as usize));
        let stream = encoder
            .encode(&YUVBuffer::from_rgb8_source(rgb))
            .map_err(|e| fail(&e))?;
        // The sample holds the frame's NAL units, each after its length (the MP4 form of H.264); the
        // parameter sets go into the track's header instead.
        let (mut bytes, mut sync) = (Vec::new(), false);
        for layer in (0..stream.num_layers()).filter_map(|l| stream.layer(l)) {
            for nal in (0..layer.nal_count()).filter_map(|n| layer.nal_unit(n)) {
                let unit = strip_start_code(nal);
                match unit.first().map(|b| b & 0x1f) {
                    Some(7) => sps = sps.or(Some(unit.to_vec())),
                    Some(8) => pps = pps.or(Some(unit.to_vec())),
                    Some(kind) => {
                        sync |= kind == 5;
                        bytes.extend_from_slice(&(unit.len() as u32).to_be_bytes());
                        bytes.extend_from_slice(unit);
                    }
                    None => {}
                }
            }
        }
        if bytes.is_empty() {
            return Err(fail(&format!("the encoder returned no picture for frame {k}")));
        }
        samples.push(Mp4Sample {
            start_time: k as u64 * u64::from(frame_ms),
            duration: frame_ms,
            rendering_offset: 0,
            is_sync: sync,
            bytes: bytes.into(),
        });
    }
    let (Some(seq_param_set), Some(pic_param_set)) = (sps, pps) else {
        return Err(fail(&"the encoder wrote no parameter sets"));
    };
    let brands = ["isom", "iso2", "avc1", "mp41"].map(|b| b.parse().expect("a four-character code"));
    let header = Mp4Config {
        major_brand: brands[0],
        minor_version: 512,
        compatible_brands: brands.to_vec(),
        timescale: TIMESCALE,
    };
    let mut mp4 = Mp4Writer::write_start(OutputFile::create(path)?, &header).map_err(|e| fail(&e))?;
    let track = TrackConfig {
        track_type: TrackType::Video,
        timescale: TIMESCALE,
        language: "und".to_string(),
        media_conf: MediaConfig::AvcConfig(AvcConfig {
            width: even_w as u16,
            height: even_h as u16,
            seq_param_set,
            pic_param_set,
        }),
    };
    mp4.add_track(&track).map_err(|e| fail(&e))?;
    for sample in &samples {
        mp4.write_sample(1, sample).map_err(|e| fail(&e))?;
    }
    mp4.write_end().map_err(|e| fail(&e))?;
    mp4.into_writer().finish()
}

/// `nal` without its Annex B start code (00 00 01 or 00 00 00 01).
fn strip_start_code(nal: &[u8]) -> &[u8] {
    match nal {
        [0, 0, 0, 1, rest @ ..] | [0, 0, 1, rest @ ..] => rest,
        _ => nal,
    }
}

/// `frame` with even sides: the last row or column repeated where a side is odd.
fn pad_to_even(frame: &RgbImage) -> RgbImage {
    let (w, h) = frame.dimensions();
    if w % 2 == 0 && h % 2 == 0 {
        return frame.clone();
    }
    RgbImage::from_fn(w.next_multiple_of(2), h.next_multiple_of(2), |x, y| {
        *frame.get_pixel(x.min(w - 1), y.min(h - 1))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use openh264::decoder::Decoder;

    /// A frame whose left half is a color that moves with `k` and whose right half is gray.
    fn frame(w: u32, h: u32, k: u32) -> RgbImage {
        RgbImage::from_fn(w, h, |x, _| {
            if x < w / 2 {
                image::Rgb([(40 * k) as u8, 200, 60])
            } else {
                image::Rgb([128, 128, 128])
            }
        })
    }

    #[test]
    fn an_mp4_holds_every_frame_and_decodes_to_the_pictures() {
        let path = std::env::temp_dir().join(format!("nerfjit-video-{}.mp4", std::process::id()));
        let frames: Vec<RgbImage> = (0..5).map(|k| frame(47, 30, k)).collect();
        save_mp4(&path, &frames, 50).unwrap();
        let file = std::fs::File::open(&path).unwrap();
        let size = file.metadata().unwrap().len();
        let mut reader = mp4::Mp4Reader::read_header(std::io::BufReader::new(file), size).unwrap();
        let track = reader.tracks().get(&1).unwrap();
        assert_eq!((track.width(), track.height()), (48, 30), "padded to even");
        assert_eq!(track.sample_count(), 5);
        assert_eq!(reader.duration().as_millis(), 250);
        let sps = track.sequence_parameter_set().unwrap().to_vec();
        let pps = track.picture_parameter_set().unwrap().to_vec();
        // Decode every sample (as Annex B, the parameter sets before the first) and keep the last picture.
        let mut decoder = Decoder::new().unwrap();
        let annex_b = |unit: &[u8]| [&[0, 0, 0, 1], unit].concat();
        let mut packet = [annex_b(&sps), annex_b(&pps)].concat();
        let (mut pictures, mut last) = (0, vec![0u8; 48 * 30 * 3]);
        for id in 1..=5 {
            let sample = reader.read_sample(1, id).unwrap().unwrap();
            let mut rest = &sample.bytes[..];
            while rest.len() > 4 {
                let n = u32::from_be_bytes(rest[..4].try_into().unwrap()) as usize;
                packet.extend(annex_b(&rest[4..4 + n]));
                rest = &rest[4 + n..];
            }
            if let Some(yuv) = decoder.decode(&packet).unwrap() {
                yuv.write_rgb8(&mut last);
                pictures += 1;
            }
            packet.clear();
        }
        assert_eq!(pictures, 5, "pictures decoded");
        let want = frame(47, 30, 4);
        let (left, right) = (&last[(10 * 48 + 5) * 3..][..3], &last[(10 * 48 + 40) * 3..][..3]);
        let close = |got: &[u8], want: &image::Rgb<u8>| {
            got.iter()
                .zip(want.0)
                .all(|(a, b)| (i32::from(*a) - i32::from(b)).abs() <= 12)
        };
        assert!(close(left, want.get_pixel(5, 10)), "left {left:?}");
        assert!(close(right, want.get_pixel(40, 10)), "right {right:?}");
        std::fs::remove_file(&path).unwrap();
    }
}
