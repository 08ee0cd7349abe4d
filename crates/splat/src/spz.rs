//! SPZ, Niantic's compressed Gaussian format, as `KHR_gaussian_splatting_compression_spz_2`
//! embeds it in glTF and as `.spz` files (Spark and Niantic's own tools read them). The
//! extension names SPZ 2.0.0, Niantic's library release, which writes file version 3; so does
//! this module, and it reads versions 2 and 3.
//!
//! The layout (Niantic's `load-spz.cc` at tag v2.0.0, MIT; read, not copied): a gzip stream of a
//! 16-byte header (`NGSP` magic, version, point count, SH degree, fractional bits, flags,
//! padding), then, each for all points in turn: positions as 24-bit signed fixed point
//! (`fractionalBits` = 12: a quarter millimetre), opacities as `sigmoid · 255`, the degree-0
//! coefficients as `f_dc · 0.15 · 255 + 127.5`, log-scales as `(s + 10) · 16`, rotations in 4
//! bytes ("smallest three": the index of the largest of x, y, z, w in the top 2 bits, then the
//! other three, each a sign bit and a 9-bit magnitude over `1/√2`, the largest made positive;
//! version 2 stored the x, y, z bytes of the quaternion with `w ≥ 0`, which loses precision
//! where `w` is small), and the higher SH coefficients (coefficient-major, colour innermost) as
//! `x · 128 + 128` rounded to 5 bits (degree 1) or 4 bits (higher degrees).
//!
//! Coordinates: SPZ stores right-up-back (three.js's), the glTF extension and f3g use glTF's
//! frame, which SPZ calls left-up-front; between them x and z change sign, and with them the
//! quaternion's x and z and the SH functions odd in x or z (the flips of Niantic's
//! `coordinateConverter`).

use std::io::{Read, Write};

use crate::{GaussianCloud, SplatError, sh};

const MAGIC: u32 = 0x5053_474e;
const HEADER: usize = 16;
/// Fractional bits of the fixed-point positions (Niantic's encoder always uses 12).
const FRACTIONAL_BITS: u8 = 12;
/// Niantic's decoder refuses more points than this; so does this one (a corrupt count would
/// otherwise ask for gigabytes).
const MAX_POINTS: usize = 10_000_000;
/// Degree-0 coefficients are stored with this scale, so colours a little beyond [0, 1] fit.
const COLOUR_SCALE: f32 = 0.15;
const FLAG_HAS_EXTENSIONS: u8 = 0x2;
/// How far a decoded opacity is kept from 0 and 1, whose logits are infinite.
const OPACITY_MARGIN: f32 = 1e-7;
/// Sign changes between glTF's frame (left-up-front) and SPZ's (right-up-back): x and z.
const FLIP_POSITION: [f32; 3] = [-1.0, 1.0, -1.0];
/// The quaternion's x, y, z under that change (`y·z, x·z, x·y` of the axis flips).
const FLIP_QUATERNION: [f32; 3] = [-1.0, 1.0, -1.0];
/// The higher SH functions' signs under that change, in 3DGS order (degree 1, 2, 3).
const FLIP_SH: [f32; 15] = [
    1.0, -1.0, -1.0, // y, z, x
    -1.0, -1.0, 1.0, 1.0, 1.0, // xy, yz, 3z²−1, xz, x²−y²
    1.0, 1.0, 1.0, -1.0, -1.0, -1.0,
    -1.0, // y(3x²−y²), xyz, y(5z²−1), z(…), x(…), z(…), x(…)
];

/// Steps per metre of the stored positions.
const POSITION_UNIT: f32 = (1u32 << FRACTIONAL_BITS) as f32;

/// The 24-bit fixed-point value stored for coordinate `x` (f3g's frame) on `axis`; 24 bits hold
/// ±2048 m at this precision, beyond which the value is clamped.
fn fixed_position(x: f32, axis: usize) -> i32 {
    (FLIP_POSITION[axis] * x * POSITION_UNIT)
        .round()
        .clamp(-8_388_608.0, 8_388_607.0) as i32
}

/// Coordinate `x` on `axis` as [`decode`] reads it back from what [`encode`] stores: what a
/// glTF `POSITION` accessor's bounds must describe, without decoding the payload.
pub fn stored_position(x: f32, axis: usize) -> f32 {
    FLIP_POSITION[axis] * fixed_position(x, axis) as f32 / POSITION_UNIT
}

fn to_byte(x: f32) -> u8 {
    x.round().clamp(0.0, 255.0) as u8
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// SH coefficient quantisation to `bits` bits: buckets of `2^(8 − bits)` on `x · 128 + 128`.
fn quantise_sh(x: f32, bits: u32) -> u8 {
    let bucket = 1i32 << (8 - bits);
    let q = (x * 128.0).round() as i32 + 128;
    ((q + bucket / 2) / bucket * bucket).clamp(0, 255) as u8
}

/// The SPZ bytes (gzip-compressed, version 2) of `cloud`, whose coordinates are f3g's (glTF's).
pub fn encode(cloud: &GaussianCloud) -> Result<Vec<u8>, SplatError> {
    cloud.validate()?;
    let n = cloud.len();
    if n > MAX_POINTS {
        return Err(SplatError::Shape {
            name: "means",
            got: vec![n, 3],
            expected: format!("at most {MAX_POINTS} Gaussians in an SPZ file"),
        });
    }
    let k = cloud.sh_coeffs();
    let rest = k - 1;
    let mut out = Vec::with_capacity(HEADER + n * (20 + 3 * rest));
    out.extend_from_slice(&MAGIC.to_le_bytes());
    out.extend_from_slice(&3u32.to_le_bytes());
    out.extend_from_slice(&(n as u32).to_le_bytes());
    out.extend_from_slice(&[cloud.sh_degree as u8, FRACTIONAL_BITS, 0, 0]);
    for (i, &x) in cloud.means.iter().enumerate() {
        out.extend_from_slice(&fixed_position(x, i % 3).to_le_bytes()[..3]);
    }
    out.extend(
        cloud
            .opacity_logits
            .iter()
            .map(|&o| to_byte(sigmoid(o) * 255.0)),
    );
    for g in 0..n {
        for c in 0..3 {
            let dc = cloud.sh[g * k * 3 + c];
            out.push(to_byte(dc * (COLOUR_SCALE * 255.0) + 0.5 * 255.0));
        }
    }
    out.extend(cloud.log_scales.iter().map(|&s| to_byte((s + 10.0) * 16.0)));
    for q in cloud.quats.chunks_exact(4) {
        // f3g's (w, x, y, z) to SPZ's (x, y, z, w) in its frame, unit length.
        let length = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        let xyzw = [
            FLIP_QUATERNION[0] * q[1] / length,
            FLIP_QUATERNION[1] * q[2] / length,
            FLIP_QUATERNION[2] * q[3] / length,
            q[0] / length,
        ];
        out.extend_from_slice(&pack_smallest_three(xyzw).to_le_bytes());
    }
    for g in 0..n {
        for j in 1..k {
            let bits = if j <= 3 { 5 } else { 4 };
            for c in 0..3 {
                let x = FLIP_SH[j - 1] * cloud.sh[(g * k + j) * 3 + c];
                out.push(quantise_sh(x, bits));
            }
        }
    }
    let mut gzip = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    gzip.write_all(&out)
        .and_then(|_| gzip.finish())
        .map_err(|e| SplatError::Option {
            name: "spz",
            reason: format!("compressing: {e}"),
        })
}

/// Writes `cloud` as an `.spz` file, atomically (as [`crate::ply::write_ply`] writes `.ply`).
pub fn write_spz(path: &std::path::Path, cloud: &GaussianCloud) -> Result<(), SplatError> {
    let err = |reason: String| SplatError::Spz {
        path: path.to_path_buf(),
        reason,
    };
    let bytes = encode(cloud).map_err(|e| err(e.to_string()))?;
    f3g_io::write_atomic(path, &bytes).map_err(|e| err(e.reason))
}

/// Reads SPZ bytes (versions 2 and 3) into Gaussians in f3g's (glTF's) coordinates. Every
/// size is checked against the header before anything is allocated for it.
pub fn decode(bytes: &[u8]) -> Result<GaussianCloud, String> {
    let mut gzip = flate2::read::GzDecoder::new(bytes);
    let mut header = [0u8; HEADER];
    gzip.read_exact(&mut header)
        .map_err(|e| format!("not SPZ data (gzip: {e})"))?;
    let word = |at: usize| u32::from_le_bytes(header[at..at + 4].try_into().unwrap());
    if word(0) != MAGIC {
        return Err("not SPZ data (no NGSP magic after decompression)".into());
    }
    let version = word(4);
    if !(2..=3).contains(&version) {
        return Err(format!("SPZ version {version}, this reader reads 2 and 3"));
    }
    let n = word(8) as usize;
    if n > MAX_POINTS {
        return Err(format!(
            "SPZ header says {n} points, at most {MAX_POINTS} are read"
        ));
    }
    let degree = header[12] as usize;
    if degree > 3 {
        return Err(format!("SPZ SH degree {degree}, expected 0 to 3"));
    }
    let fractional = header[13];
    if fractional > 23 {
        return Err(format!(
            "SPZ fractional bits {fractional}, expected at most 23"
        ));
    }
    if header[14] & FLAG_HAS_EXTENSIONS != 0 {
        return Err("SPZ extensions (header flag 0x2) are not supported".into());
    }
    let k = sh::num_coeffs(degree);
    let rotation_bytes = if version >= 3 { 4 } else { 3 };
    let expected = n * (9 + 1 + 3 + 3 + rotation_bytes + 3 * (k - 1));
    let body = f3g_io::read_at_most(&mut gzip, expected).map_err(|e| format!("SPZ data: {e}"))?;
    if body.len() != expected {
        return Err(format!(
            "SPZ data holds {} bytes after its header, {n} points of SH degree {degree} take {expected}",
            body.len()
        ));
    }
    let (positions, body) = body.split_at(9 * n);
    let (alphas, body) = body.split_at(n);
    let (colours, body) = body.split_at(3 * n);
    let (scales, body) = body.split_at(3 * n);
    let (rotations, sh_bytes) = body.split_at(rotation_bytes * n);
    let unit = 1.0 / (1u32 << fractional) as f32;
    let means = positions
        .chunks_exact(3)
        .enumerate()
        .map(|(i, b)| {
            let fixed = i32::from_le_bytes([b[0], b[1], b[2], 0]) << 8 >> 8;
            FLIP_POSITION[i % 3] * fixed as f32 * unit
        })
        .collect();
    // A byte of 0 or 255 is an opacity of exactly 0 or 1 (Niantic's decoder gives infinite
    // logits): kept finite a hair inside, as f3g's glTF reader keeps stored opacities.
    let opacity_logits = alphas
        .iter()
        .map(|&a| {
            let o = (a as f32 / 255.0).clamp(OPACITY_MARGIN, 1.0 - OPACITY_MARGIN);
            (o / (1.0 - o)).ln()
        })
        .collect();
    let log_scales = scales.iter().map(|&s| s as f32 / 16.0 - 10.0).collect();
    let mut quats = Vec::with_capacity(4 * n);
    for r in rotations.chunks_exact(rotation_bytes) {
        let q = if version >= 3 {
            smallest_three(r)
        } else {
            let xyz = [0, 1, 2].map(|a| r[a] as f32 / 127.5 - 1.0);
            let w = (1.0 - xyz.iter().map(|v| v * v).sum::<f32>())
                .max(0.0)
                .sqrt();
            [xyz[0], xyz[1], xyz[2], w]
        };
        quats.extend_from_slice(&[
            q[3],
            FLIP_QUATERNION[0] * q[0],
            FLIP_QUATERNION[1] * q[1],
            FLIP_QUATERNION[2] * q[2],
        ]);
    }
    let mut sh_values = vec![0.0f32; n * k * 3];
    for g in 0..n {
        for c in 0..3 {
            sh_values[g * k * 3 + c] = (colours[3 * g + c] as f32 / 255.0 - 0.5) / COLOUR_SCALE;
        }
        for j in 1..k {
            for c in 0..3 {
                let byte = sh_bytes[(g * (k - 1) + j - 1) * 3 + c];
                sh_values[(g * k + j) * 3 + c] = FLIP_SH[j - 1] * (byte as f32 - 128.0) / 128.0;
            }
        }
    }
    let cloud = GaussianCloud {
        means,
        log_scales,
        quats,
        opacity_logits,
        sh: sh_values,
        sh_degree: degree,
    };
    cloud.validate().map_err(|e| format!("SPZ data: {e}"))?;
    Ok(cloud)
}

/// A unit quaternion (x, y, z, w) in version 3's 32 bits (module docs): `q` and `−q` are the
/// same rotation, so the largest component is made positive and only its index is stored.
fn pack_smallest_three(q: [f32; 4]) -> u32 {
    let largest = (0..4)
        .max_by(|&a, &b| q[a].abs().total_cmp(&q[b].abs()))
        .unwrap_or(3);
    let negate = q[largest] < 0.0;
    let mut word = largest as u32;
    for (i, &v) in q.iter().enumerate() {
        if i != largest {
            let sign = ((v < 0.0) != negate) as u32;
            let magnitude =
                (511.0 * v.abs() / std::f32::consts::FRAC_1_SQRT_2 + 0.5).min(511.0) as u32;
            word = (word << 10) | (sign << 9) | magnitude;
        }
    }
    word
}

/// Version 3's quaternion: the index of the largest component (2 bits), then the other three
/// as sign + 9-bit magnitude over `1/√2`; returns (x, y, z, w) in SPZ's frame.
fn smallest_three(r: &[u8]) -> [f32; 4] {
    let mut word = u32::from_le_bytes([r[0], r[1], r[2], r[3]]);
    let largest = (word >> 30) as usize;
    let mut q = [0.0f32; 4];
    let mut squares = 0.0;
    for i in (0..4).rev() {
        if i == largest {
            continue;
        }
        let magnitude = (word & 511) as f32 / 511.0 * std::f32::consts::FRAC_1_SQRT_2;
        q[i] = if (word >> 9) & 1 == 1 {
            -magnitude
        } else {
            magnitude
        };
        squares += q[i] * q[i];
        word >>= 10;
    }
    q[largest] = (1.0 - squares).max(0.0).sqrt();
    q
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(n: usize, degree: usize, seed: u32) -> GaussianCloud {
        let k = sh::num_coeffs(degree);
        let mut state = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            state as f32 / u32::MAX as f32 * 2.0 - 1.0
        };
        GaussianCloud {
            means: (0..3 * n).map(|_| next() * 2.0).collect(),
            log_scales: (0..3 * n).map(|_| next() * 3.0 - 5.0).collect(),
            quats: (0..4 * n).map(|_| next()).collect(),
            opacity_logits: (0..n).map(|_| next() * 4.0).collect(),
            sh: (0..n * k * 3).map(|_| next() * 0.9).collect(),
            sh_degree: degree,
        }
    }

    /// Every value comes back within its quantisation step, in f3g's frame.
    #[test]
    fn values_come_back_within_their_quantisation_step() {
        for degree in 0..=3 {
            let a = cloud(300, degree, degree as u32);
            let b = decode(&encode(&a).unwrap()).unwrap();
            assert_eq!(b.len(), a.len());
            assert_eq!(b.sh_degree, degree);
            for (i, (x, y)) in a.means.iter().zip(&b.means).enumerate() {
                assert!((x - y).abs() <= 0.5 / 4096.0 + 1e-6, "{x} {y}");
                assert_eq!(stored_position(*x, i % 3), *y);
            }
            for (x, y) in a.log_scales.iter().zip(&b.log_scales) {
                assert!((x - y).abs() <= 0.5 / 16.0 + 1e-5, "{x} {y}");
            }
            for (x, y) in a.opacity_logits.iter().zip(&b.opacity_logits) {
                assert!((sigmoid(*x) - sigmoid(*y)).abs() <= 0.5 / 255.0 + 1e-6);
            }
            for (p, q) in a.quats.chunks_exact(4).zip(b.quats.chunks_exact(4)) {
                let norm = p.iter().map(|v| v * v).sum::<f32>().sqrt();
                let dot: f32 = p.iter().zip(q).map(|(x, y)| x * y).sum::<f32>() / norm;
                // Three components within 1/1446 each: the rotation within about 0.1°.
                assert!(dot.abs() > 0.99999, "{p:?} {q:?}");
            }
            let k = sh::num_coeffs(degree);
            for (i, (x, y)) in a.sh.iter().zip(&b.sh).enumerate() {
                let step = match (i / 3) % k {
                    0 => 0.5 / (COLOUR_SCALE * 255.0),
                    // Half a bucket, and the rounding to 1/128 before it.
                    1..=3 => 4.5 / 128.0,
                    _ => 8.5 / 128.0,
                };
                assert!((x - y).abs() <= step + 1e-5, "coefficient {i}: {x} {y}");
            }
        }
    }

    /// The stored frame is SPZ's right-up-back: x and z change sign, y does not (a reader that
    /// skipped the change would see the avatar turned half round).
    #[test]
    fn positions_are_stored_right_up_back() {
        let mut a = cloud(1, 0, 7);
        a.means = vec![1.0, 2.0, 3.0];
        let mut raw = Vec::new();
        flate2::read::GzDecoder::new(&encode(&a).unwrap()[..])
            .read_to_end(&mut raw)
            .unwrap();
        let at = |i: usize| {
            i32::from_le_bytes([
                raw[HEADER + 3 * i],
                raw[HEADER + 3 * i + 1],
                raw[HEADER + 3 * i + 2],
                0,
            ]) << 8
                >> 8
        };
        assert_eq!([at(0), at(1), at(2)], [-4096, 8192, -12288]);
    }

    /// A rotation about y keeps its sense in both frames: its quaternion's y survives, the
    /// flips leave it unchanged, and a rotation about x comes back about x.
    #[test]
    fn rotations_keep_their_axis() {
        let mut a = cloud(2, 0, 3);
        let h = std::f32::consts::FRAC_1_SQRT_2;
        a.quats = vec![h, 0.0, h, 0.0, h, h, 0.0, 0.0];
        let b = decode(&encode(&a).unwrap()).unwrap();
        for (x, y) in a.quats.iter().zip(&b.quats) {
            assert!((x - y).abs() < 2e-3, "{:?}", b.quats);
        }
    }

    #[test]
    fn corrupt_data_is_an_error_not_a_panic() {
        let bytes = encode(&cloud(50, 2, 1)).unwrap();
        assert!(decode(&bytes[..bytes.len() / 2]).is_err());
        assert!(decode(b"not gzip").is_err());
        // A header that promises more points than the data holds.
        let mut raw = Vec::new();
        flate2::read::GzDecoder::new(&bytes[..])
            .read_to_end(&mut raw)
            .unwrap();
        raw[8..12].copy_from_slice(&51u32.to_le_bytes());
        let mut gzip = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        gzip.write_all(&raw).unwrap();
        let error = decode(&gzip.finish().unwrap()).unwrap_err();
        assert!(error.contains("51 points"), "{error}");
        raw[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        let mut gzip = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        gzip.write_all(&raw).unwrap();
        assert!(
            decode(&gzip.finish().unwrap())
                .unwrap_err()
                .contains("at most")
        );
    }

    /// Version 3's smallest-three quaternion, packed by hand as Niantic's encoder does:
    /// (x, y, z, w) = (0.6, 0, 0, −0.8) has w largest (index 3, top bits), is negated so that w
    /// is positive (every other sign bit flips, the zeros' too), and stores x, y, z from the
    /// high bits down.
    #[test]
    fn version_three_quaternions_follow_niantics_bit_layout() {
        let magnitude = (511.0 * 0.6 / std::f32::consts::FRAC_1_SQRT_2 + 0.5) as u32;
        let word = (3u32 << 30) | (1 << 29) | (magnitude << 20) | (1 << 19) | (1 << 9);
        assert_eq!(pack_smallest_three([0.6, 0.0, 0.0, -0.8]), word);
        let q = smallest_three(&word.to_le_bytes());
        assert!((q[0] + 0.6).abs() < 2e-3 && q[1] == 0.0 && q[2] == 0.0);
        assert!((q[3] - 0.8).abs() < 2e-3, "{q:?}");
    }
}
