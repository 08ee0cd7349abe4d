//! Videos: frames as H.264 in an MP4 file, which every browser, player and editor opens (the
//! animation, the evaluation's side-by-side views, the demo's report).
//!
//! Encoding is Cisco's OpenH264 (the `openh264` crate builds it from the source it ships: a C++
//! compiler, no system library), constant-quality rate control, an intra frame every second;
//! muxing is the `mp4` crate's (one AVC track, its SPS and PPS in the sample description,
//! samples as length-prefixed NAL units, millisecond timestamps). H.264's 4:2:0 colour needs
//! even sizes and the encoder at least 16 pixels a side, so frames are padded to that by
//! repeating their last row and column.

use std::io::Cursor;
use std::path::Path;

use f3g_io::Image;
use openh264::encoder::{Encoder, EncoderConfig, FrameRate, IntraFramePeriod, QpRange};
use openh264::formats::{RgbSliceU8, YUVBuffer, YUVSource};

use crate::AvatarError;

/// The encoder's quantiser range: 18 is visually lossless for renders like these, 30 the
/// coarsest it may choose.
const QUANTISER: QpRange = QpRange::new(12, 24);
/// MP4 ticks per second.
const TIMESCALE: u32 = 1000;

/// The size a frame is encoded at: even (4:2:0 colour) and at least the encoder's 16 pixels.
fn coded_size(width: usize, height: usize) -> (usize, usize) {
    (
        width.next_multiple_of(2).max(16),
        height.next_multiple_of(2).max(16),
    )
}

/// `frame` as 8-bit RGB padded to its coded size with its last row and column.
fn even_rgb(frame: &Image) -> (Vec<u8>, usize, usize) {
    let (w, h) = coded_size(frame.width, frame.height);
    let mut rgb = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let i =
                (y.min(frame.height - 1) * frame.width + x.min(frame.width - 1)) * frame.channels;
            for c in 0..3 {
                let v = frame.data[i + c.min(frame.channels - 1)];
                rgb.push((v.clamp(0.0, 1.0) * 255.0).round() as u8);
            }
        }
    }
    (rgb, w, h)
}

/// An H.264 video built a frame at a time: only the encoded frames are held, so long
/// evaluations stream their frames through it.
pub struct VideoWriter {
    encoder: Encoder,
    fps: f32,
    size: Option<(usize, usize)>,
    parameter_sets: (Option<Vec<u8>>, Option<Vec<u8>>),
    /// Each frame's length-prefixed NAL units and whether it is an IDR frame.
    samples: Vec<(Vec<u8>, bool)>,
}

impl VideoWriter {
    /// A video at `fps` frames per second.
    pub fn new(fps: f32) -> Result<Self, String> {
        if !(fps.is_finite() && fps > 0.0) {
            return Err(format!("frame rate {fps}, expected a positive number"));
        }
        let config = EncoderConfig::new()
            .max_frame_rate(FrameRate::from_hz(fps))
            .qp(QUANTISER)
            .intra_frame_period(IntraFramePeriod::from_num_frames(fps.ceil() as u32));
        let encoder = Encoder::with_api_config(openh264::OpenH264API::from_source(), config)
            .map_err(|e| format!("starting the H.264 encoder: {e}"))?;
        Ok(Self {
            encoder,
            fps,
            size: None,
            parameter_sets: (None, None),
            samples: Vec::new(),
        })
    }

    /// Encodes the next frame; every frame has the first one's size.
    pub fn push(&mut self, frame: &Image) -> Result<(), String> {
        let size = (frame.width, frame.height);
        if *self.size.get_or_insert(size) != size {
            return Err("the frames of a video differ in size".into());
        }
        if frame.width > 4096 || frame.height > 4096 || frame.width == 0 || frame.height == 0 {
            return Err(format!(
                "frames of {}×{}: H.264 here takes 1 to 4096 pixels a side",
                frame.width, frame.height
            ));
        }
        let (rgb, w, h) = even_rgb(frame);
        let yuv = YUVBuffer::from_rgb8_source(RgbSliceU8::new(&rgb, (w, h)));
        let stream = self
            .encoder
            .encode(&yuv)
            .map_err(|e| format!("encoding a frame: {e}"))?;
        // Annex B NAL units; the parameter sets go to the track's description, the rest to the
        // sample with 4-byte lengths.
        let (mut sample, mut sync) = (Vec::new(), false);
        for nal in openh264::nal_units(&stream.to_vec()) {
            let nal = nal
                .strip_prefix(&[0, 0, 0, 1][..])
                .or(nal.strip_prefix(&[0, 0, 1][..]))
                .unwrap_or(nal);
            match nal.first().map(|b| b & 0x1f) {
                Some(7) => self.parameter_sets.0 = Some(nal.to_vec()),
                Some(8) => self.parameter_sets.1 = Some(nal.to_vec()),
                Some(t) => {
                    sync |= t == 5;
                    sample.extend_from_slice(&(nal.len() as u32).to_be_bytes());
                    sample.extend_from_slice(nal);
                }
                None => {}
            }
        }
        self.samples.push((sample, sync));
        Ok(())
    }

    /// Writes the MP4 file to `path`, atomically.
    pub fn write(self, path: &Path) -> Result<(), AvatarError> {
        let bytes = self.finish().map_err(|e| AvatarError::file(path, e))?;
        Ok(f3g_io::write_atomic(path, &bytes)?)
    }

    /// The MP4 file's bytes.
    pub fn finish(self) -> Result<Vec<u8>, String> {
        let (Some((w, h)), (Some(sps), Some(pps))) = (self.size, self.parameter_sets) else {
            return Err("a video needs at least one frame".into());
        };
        let mux = |e: mp4::Error| format!("writing the MP4 container: {e}");
        let mut writer = mp4::Mp4Writer::write_start(
            Cursor::new(Vec::new()),
            &mp4::Mp4Config {
                major_brand: str::parse("isom").map_err(mux)?,
                minor_version: 512,
                compatible_brands: ["isom", "iso2", "avc1", "mp41"]
                    .iter()
                    .map(|b| str::parse(b))
                    .collect::<Result<_, _>>()
                    .map_err(mux)?,
                timescale: TIMESCALE,
            },
        )
        .map_err(mux)?;
        writer
            .add_track(&mp4::TrackConfig {
                track_type: mp4::TrackType::Video,
                timescale: TIMESCALE,
                language: "und".into(),
                media_conf: mp4::MediaConfig::AvcConfig(mp4::AvcConfig {
                    width: coded_size(w, h).0 as u16,
                    height: coded_size(w, h).1 as u16,
                    seq_param_set: sps,
                    pic_param_set: pps,
                }),
            })
            .map_err(mux)?;
        let fps = f64::from(self.fps);
        let tick = |i: usize| (i as f64 * f64::from(TIMESCALE) / fps).round() as u64;
        for (i, (sample, sync)) in self.samples.into_iter().enumerate() {
            writer
                .write_sample(
                    1,
                    &mp4::Mp4Sample {
                        start_time: tick(i),
                        duration: (tick(i + 1) - tick(i)) as u32,
                        rendering_offset: 0,
                        is_sync: sync,
                        bytes: sample.into(),
                    },
                )
                .map_err(mux)?;
        }
        writer.write_end().map_err(mux)?;
        Ok(writer.into_writer().into_inner())
    }
}

/// Writes `frames` as an H.264 MP4 video at `fps`, atomically.
pub fn write_mp4(path: &Path, frames: &[Image], fps: f32) -> Result<(), AvatarError> {
    let mut video = VideoWriter::new(fps).map_err(|e| AvatarError::file(path, e))?;
    for frame in frames {
        video.push(frame).map_err(|e| AvatarError::file(path, e))?;
    }
    video.write(path)
}

/// Decodes an MP4 video's first H.264 track back into frames (RGB in [0, 1]) and its frame
/// rate: how tests check what [`write_mp4`] wrote, and a way to read any such video.
pub fn read_mp4(bytes: &[u8]) -> Result<(Vec<Image>, f32), String> {
    let what = |e: mp4::Error| format!("not a readable MP4 file: {e}");
    let mut reader =
        mp4::Mp4Reader::read_header(Cursor::new(bytes), bytes.len() as u64).map_err(what)?;
    let (id, track) = reader
        .tracks()
        .iter()
        .find(|(_, t)| t.media_type().ok() == Some(mp4::MediaType::H264))
        .ok_or("the MP4 file has no H.264 track")?;
    let id = *id;
    let seconds = track.duration().as_secs_f64();
    let mut annex_b = Vec::new();
    for set in [
        track.sequence_parameter_set(),
        track.picture_parameter_set(),
    ] {
        annex_b.extend_from_slice(&[0, 0, 0, 1]);
        annex_b.extend_from_slice(set.map_err(what)?);
    }
    let count = reader.sample_count(id).map_err(what)?;
    for s in 1..=count {
        let Some(sample) = reader.read_sample(id, s).map_err(what)? else {
            continue;
        };
        let mut rest = &sample.bytes[..];
        while rest.len() >= 4 {
            let n = u32::from_be_bytes([rest[0], rest[1], rest[2], rest[3]]) as usize;
            let nal = rest
                .get(4..4 + n)
                .ok_or("a sample's NAL unit runs past its end")?;
            annex_b.extend_from_slice(&[0, 0, 0, 1]);
            annex_b.extend_from_slice(nal);
            rest = &rest[4 + n..];
        }
    }
    let mut decoder = openh264::decoder::Decoder::new()
        .map_err(|e| format!("starting the H.264 decoder: {e}"))?;
    let mut frames = Vec::new();
    let mut keep = |yuv: &openh264::decoder::DecodedYUV<'_>| {
        let (w, h) = yuv.dimensions();
        let mut rgb = vec![0u8; w * h * 3];
        yuv.write_rgb8(&mut rgb);
        frames.push(Image {
            width: w,
            height: h,
            channels: 3,
            data: rgb.iter().map(|&v| v as f32 / 255.0).collect(),
        });
    };
    for nal in openh264::nal_units(&annex_b) {
        if let Some(yuv) = decoder
            .decode(nal)
            .map_err(|e| format!("decoding H.264: {e}"))?
        {
            keep(&yuv);
        }
    }
    for yuv in decoder
        .flush_remaining()
        .map_err(|e| format!("decoding H.264: {e}"))?
    {
        keep(&yuv);
    }
    let fps = if seconds > 0.0 {
        (count as f64 / seconds) as f32
    } else {
        0.0
    };
    Ok((frames, fps))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The MP4 bytes of `frames` (all of one size) at `fps`.
    fn mp4_bytes(frames: &[Image], fps: f32) -> Result<Vec<u8>, String> {
        let mut video = VideoWriter::new(fps)?;
        for frame in frames {
            video.push(frame)?;
        }
        video.finish()
    }

    /// A moving gradient, odd-sized: what goes in comes out, frame by frame, within H.264's
    /// loss, at its frame rate; the odd size is padded by one pixel.
    #[test]
    fn frames_come_back_from_the_video() {
        let (w, h, n) = (63, 45, 12);
        let frames: Vec<Image> = (0..n)
            .map(|t| Image {
                width: w,
                height: h,
                channels: 3,
                data: (0..w * h)
                    .flat_map(|i| {
                        let (x, y) = ((i % w) as f32 / w as f32, (i / w) as f32 / h as f32);
                        [x, y, 0.5 + 0.4 * (6.0 * x + t as f32 * 0.5).sin() * y]
                    })
                    .collect(),
            })
            .collect();
        let bytes = mp4_bytes(&frames, 8.0).unwrap();
        assert_eq!(&bytes[4..8], b"ftyp");
        let (back, fps) = read_mp4(&bytes).unwrap();
        assert_eq!(back.len(), n);
        assert!((fps - 8.0).abs() < 0.1, "{fps}");
        for (a, b) in frames.iter().zip(&back) {
            assert_eq!((b.width, b.height), (64, 46));
            let mut error = 0.0;
            for y in 0..h {
                for x in 0..w {
                    for c in 0..3 {
                        error +=
                            (a.data[(y * w + x) * 3 + c] - b.data[(y * 64 + x) * 3 + c]).powi(2);
                    }
                }
            }
            let psnr = -10.0 * (error / (w * h * 3) as f32).log10();
            assert!(psnr > 33.0, "{psnr} dB");
        }
    }

    #[test]
    fn bad_frames_are_errors() {
        let image = |w, h| Image {
            width: w,
            height: h,
            channels: 3,
            data: vec![0.5; w * h * 3],
        };
        assert!(mp4_bytes(&[], 8.0).is_err());
        let error = mp4_bytes(&[image(32, 32), image(34, 32)], 8.0).unwrap_err();
        assert!(error.contains("size"), "{error}");
        assert!(mp4_bytes(&[image(32, 32)], 0.0).is_err());
        assert!(mp4_bytes(&[image(0, 32)], 8.0).is_err());
        // A tiny frame is padded to the encoder's 16 pixels.
        let (tiny, _) = read_mp4(&mp4_bytes(&[image(5, 3)], 8.0).unwrap()).unwrap();
        assert_eq!((tiny[0].width, tiny[0].height), (16, 16));
        assert!(read_mp4(b"not a video").is_err());
    }
}
