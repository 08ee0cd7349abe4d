//! The standard 3DGS `.ply` layout, which every Gaussian-splatting viewer reads.
//!
//! Binary little-endian, one `vertex` element with float properties, in this order:
//! `x y z nx ny nz f_dc_0..2 f_rest_0..(3(K−1)−1) opacity scale_0..2 rot_0..3`.
//! `f_rest` is channel-major (all red coefficients, then green, then blue), `opacity` is the
//! logit, `scale_*` are natural-log scales and `rot_*` is the quaternion (w, x, y, z).
//!
//! The reader accepts properties in any order, `float` or `double` for the ones it uses, any
//! other scalar properties (skipped), comments, and elements after `vertex`. Everything else
//! (ASCII or big-endian files, list properties in `vertex`, missing or mistyped properties,
//! truncated data) is an error naming the file and the problem.

use std::path::Path;

use crate::{GaussianCloud, SplatError, sh};

/// Writes `cloud` as a 3DGS `.ply`, atomically (temporary file, then rename).
pub fn write_ply(path: &Path, cloud: &GaussianCloud) -> Result<(), SplatError> {
    let err = |reason: String| SplatError::Ply {
        path: path.to_path_buf(),
        reason,
    };
    cloud.validate().map_err(|e| err(e.to_string()))?;
    let n = cloud.len();
    let k = cloud.sh_coeffs();
    let mut header = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n");
    let mut names: Vec<String> = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ]
    .map(String::from)
    .to_vec();
    names.extend((0..3 * (k - 1)).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    for name in &names {
        header.push_str(&format!("property float {name}\n"));
    }
    header.push_str("end_header\n");

    let mut bytes = header.into_bytes();
    bytes.reserve(n * names.len() * 4);
    let mut push = |v: f32| bytes.extend_from_slice(&v.to_le_bytes());
    for i in 0..n {
        cloud.means[3 * i..3 * i + 3].iter().for_each(|&v| push(v));
        (0..3).for_each(|_| push(0.0));
        let coeffs = &cloud.sh[i * k * 3..(i + 1) * k * 3];
        (0..3).for_each(|c| push(coeffs[c]));
        for c in 0..3 {
            for j in 1..k {
                push(coeffs[3 * j + c]);
            }
        }
        push(cloud.opacity_logits[i]);
        cloud.log_scales[3 * i..3 * i + 3]
            .iter()
            .for_each(|&v| push(v));
        cloud.quats[4 * i..4 * i + 4].iter().for_each(|&v| push(v));
    }

    f3g_io::write_atomic(path, &bytes).map_err(|e| err(e.reason))
}

/// Scalar property types of the PLY format.
#[derive(Clone, Copy, Debug, PartialEq)]
enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarType {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
}

struct Property {
    name: String,
    kind: ScalarType,
    offset: usize,
}

/// Reads a 3DGS `.ply` file.
pub fn read_ply(path: &Path) -> Result<GaussianCloud, SplatError> {
    let bytes = std::fs::read(path).map_err(|e| SplatError::Ply {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    parse_ply(&bytes).map_err(|reason| SplatError::Ply {
        path: path.to_path_buf(),
        reason,
    })
}

/// Parses the bytes of a 3DGS `.ply`; the error says what is wrong (without the path).
pub fn parse_ply(bytes: &[u8]) -> Result<GaussianCloud, String> {
    const END: &[u8] = b"end_header";
    let header_end = bytes
        .windows(END.len())
        .position(|w| w == END)
        .ok_or("no `end_header` line: not a PLY file or the header is truncated")?;
    let data_start = bytes[header_end..]
        .iter()
        .position(|&b| b == b'\n')
        .map(|p| header_end + p + 1)
        .ok_or("header ends without a newline after `end_header`")?;
    let header =
        std::str::from_utf8(&bytes[..header_end]).map_err(|_| "the header is not valid text")?;
    let mut lines = header.lines().map(str::trim).filter(|l| !l.is_empty());
    if lines.next() != Some("ply") {
        return Err("the file does not start with `ply`".into());
    }

    let mut format_ok = false;
    let mut vertex_count: Option<usize> = None;
    let mut in_vertex = false;
    let mut props: Vec<Property> = Vec::new();
    let mut stride = 0;
    for line in lines {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["format", "binary_little_endian", _] => format_ok = true,
            ["format", other, ..] => {
                return Err(format!(
                    "format `{other}` is not supported, expected binary_little_endian"
                ));
            }
            ["comment", ..] | ["obj_info", ..] => {}
            ["element", name, count] => {
                if vertex_count.is_some() {
                    in_vertex = false;
                    continue;
                }
                if *name != "vertex" {
                    return Err(format!("the first element is `{name}`, expected `vertex`"));
                }
                vertex_count = Some(
                    count
                        .parse()
                        .map_err(|_| format!("bad vertex count `{count}`"))?,
                );
                in_vertex = true;
            }
            ["property", "list", ..] if in_vertex => {
                return Err(format!(
                    "list property in `vertex` is not supported: `{line}`"
                ));
            }
            ["property", kind, name] if in_vertex => {
                let kind = ScalarType::parse(kind)
                    .ok_or_else(|| format!("unknown property type `{kind}` for `{name}`"))?;
                props.push(Property {
                    name: name.to_string(),
                    kind,
                    offset: stride,
                });
                stride += kind.size();
            }
            ["property", ..] if !in_vertex && vertex_count.is_some() => {}
            _ => return Err(format!("unexpected header line `{line}`")),
        }
    }
    if !format_ok {
        return Err("missing `format` line".into());
    }
    let n = vertex_count.ok_or("no `element vertex` in the header")?;

    let find = |name: &str| -> Result<&Property, String> {
        let p = props
            .iter()
            .find(|p| p.name == name)
            .ok_or_else(|| format!("missing property `{name}`"))?;
        match p.kind {
            ScalarType::F32 | ScalarType::F64 => Ok(p),
            other => Err(format!(
                "property `{name}` has type {other:?}, expected float or double"
            )),
        }
    };
    let rest_count = props
        .iter()
        .filter(|p| p.name.starts_with("f_rest_"))
        .count();
    if rest_count % 3 != 0 {
        return Err(format!(
            "{rest_count} `f_rest_*` properties is not a multiple of 3"
        ));
    }
    let k = rest_count / 3 + 1;
    let degree = sh::degree_for(k)
        .ok_or_else(|| format!("{rest_count} `f_rest_*` properties: expected 0, 9, 24 or 45"))?;
    let column = |prefix: &str, count: usize| -> Result<Vec<&Property>, String> {
        (0..count).map(|i| find(&format!("{prefix}{i}"))).collect()
    };
    let xyz = [find("x")?, find("y")?, find("z")?];
    let dc = column("f_dc_", 3)?;
    let rest = column("f_rest_", rest_count)?;
    let opacity = find("opacity")?;
    let scale = column("scale_", 3)?;
    let rot = column("rot_", 4)?;

    let needed = n.checked_mul(stride).ok_or("vertex count overflows")?;
    let data = &bytes[data_start..];
    if data.len() < needed {
        return Err(format!(
            "truncated: {n} vertices need {needed} bytes of data, found {}",
            data.len()
        ));
    }
    let read = |row: usize, p: &Property| -> f32 {
        let at = row * stride + p.offset;
        match p.kind {
            ScalarType::F64 => {
                f64::from_le_bytes(data[at..at + 8].try_into().expect("8 bytes")) as f32
            }
            _ => f32::from_le_bytes(data[at..at + 4].try_into().expect("4 bytes")),
        }
    };
    let mut cloud = GaussianCloud {
        means: Vec::with_capacity(3 * n),
        log_scales: Vec::with_capacity(3 * n),
        quats: Vec::with_capacity(4 * n),
        opacity_logits: Vec::with_capacity(n),
        sh: Vec::with_capacity(3 * k * n),
        sh_degree: degree,
    };
    for i in 0..n {
        cloud.means.extend(xyz.iter().map(|p| read(i, p)));
        cloud.sh.extend(dc.iter().map(|p| read(i, p)));
        for j in 1..k {
            cloud
                .sh
                .extend((0..3).map(|c| read(i, rest[c * (k - 1) + j - 1])));
        }
        cloud.opacity_logits.push(read(i, opacity));
        cloud.log_scales.extend(scale.iter().map(|p| read(i, p)));
        cloud.quats.extend(rot.iter().map(|p| read(i, p)));
    }
    Ok(cloud)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(n: usize, degree: usize) -> GaussianCloud {
        let k = sh::num_coeffs(degree);
        let f = |i: usize| (i as f32 * 0.37).sin();
        GaussianCloud {
            means: (0..3 * n).map(f).collect(),
            log_scales: (0..3 * n).map(|i| f(i + 100) - 3.0).collect(),
            quats: (0..4 * n).map(|i| f(i + 200)).collect(),
            opacity_logits: (0..n).map(|i| f(i + 300)).collect(),
            sh: (0..3 * k * n).map(|i| f(i + 400)).collect(),
            sh_degree: degree,
        }
    }

    #[test]
    fn round_trip_every_degree() {
        let dir = tempfile::tempdir().unwrap();
        for degree in 0..=3 {
            let c = cloud(17, degree);
            let path = dir.path().join(format!("d{degree}.ply"));
            write_ply(&path, &c).unwrap();
            assert_eq!(read_ply(&path).unwrap(), c);
        }
    }

    #[test]
    fn layout_is_the_3dgs_one() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.ply");
        let c = cloud(2, 1);
        write_ply(&path, &c).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let text = String::from_utf8_lossy(&bytes);
        let props: Vec<&str> = text
            .lines()
            .filter_map(|l| l.strip_prefix("property float "))
            .collect();
        assert_eq!(props.len(), 3 + 3 + 3 + 9 + 1 + 3 + 4);
        assert_eq!(
            &props[..10],
            [
                "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "f_rest_0"
            ]
        );
        assert_eq!(
            &props[18..],
            [
                "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"
            ]
        );
        // f_rest is channel-major: f_rest_0..2 are the red degree-1 coefficients of vertex 0.
        let data = &bytes[bytes.len() - 2 * 26 * 4..];
        let value = |i: usize| f32::from_le_bytes(data[4 * i..4 * i + 4].try_into().unwrap());
        assert_eq!(value(9), c.sh[3]); // red, coefficient 1
        assert_eq!(value(10), c.sh[6]); // red, coefficient 2
        assert_eq!(value(12), c.sh[4]); // green, coefficient 1
    }

    fn header(props: &[(&str, &str)], n: usize) -> Vec<u8> {
        let mut h = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n");
        for (t, name) in props {
            h.push_str(&format!("property {t} {name}\n"));
        }
        h.push_str("end_header\n");
        h.into_bytes()
    }

    fn minimal_props() -> Vec<(&'static str, &'static str)> {
        [
            "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
            "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        ]
        .iter()
        .map(|n| ("float", *n))
        .collect()
    }

    #[test]
    fn accepts_doubles_extra_properties_and_any_order() {
        let mut props = minimal_props();
        props.reverse();
        props[0] = ("double", "rot_3");
        props.push(("uchar", "red"));
        let mut bytes = header(&props, 1);
        for (t, name) in &props {
            let v: f64 = if *name == "rot_3" { 0.25 } else { 1.0 };
            match *t {
                "double" => bytes.extend_from_slice(&v.to_le_bytes()),
                "uchar" => bytes.push(7),
                _ => bytes.extend_from_slice(&(v as f32).to_le_bytes()),
            }
        }
        let c = parse_ply(&bytes).unwrap();
        assert_eq!(c.sh_degree, 0);
        assert_eq!(c.quats, vec![1.0, 1.0, 1.0, 0.25]);
    }

    #[test]
    fn malformed_files_are_rejected_with_the_reason() {
        let props = minimal_props();
        let full = {
            let mut b = header(&props, 2);
            b.extend(std::iter::repeat_n(0u8, 2 * props.len() * 4));
            b
        };
        assert!(parse_ply(&full).is_ok());
        let truncated = &full[..full.len() - 3];
        assert!(parse_ply(truncated).unwrap_err().contains("truncated"));
        let missing: Vec<_> = props.iter().copied().filter(|p| p.1 != "opacity").collect();
        assert!(
            parse_ply(&header(&missing, 0))
                .unwrap_err()
                .contains("missing property `opacity`")
        );
        let mut wrong = props.clone();
        wrong[0] = ("int", "x");
        assert!(
            parse_ply(&header(&wrong, 0))
                .unwrap_err()
                .contains("`x` has type")
        );
        let ascii = String::from_utf8(header(&props, 0))
            .unwrap()
            .replace("binary_little_endian", "ascii");
        assert!(parse_ply(ascii.as_bytes()).unwrap_err().contains("ascii"));
        assert!(
            parse_ply(b"PK\x03\x04 not a ply")
                .unwrap_err()
                .contains("end_header")
        );
        let mut rest = props.clone();
        rest.push(("float", "f_rest_0"));
        assert!(
            parse_ply(&header(&rest, 0))
                .unwrap_err()
                .contains("multiple of 3")
        );
        let list = String::from_utf8(header(&props, 0))
            .unwrap()
            .replace("end_header", "property list uchar int idx\nend_header");
        assert!(
            parse_ply(list.as_bytes())
                .unwrap_err()
                .contains("list property")
        );
    }

    #[test]
    fn write_rejects_invalid_clouds() {
        let dir = tempfile::tempdir().unwrap();
        let mut c = cloud(3, 0);
        c.means[4] = f32::NAN;
        let e = write_ply(&dir.path().join("x.ply"), &c)
            .unwrap_err()
            .to_string();
        assert!(e.contains("means") && e.contains("non-finite"), "{e}");
        assert!(!dir.path().join("x.ply").exists());
    }
}
