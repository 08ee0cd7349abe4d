//! Fuzzing the parsers of files that come from other tools: 3DGS `.ply` (binary, and ASCII,
//! which must be refused) and camera JSON. For thousands of mutations of valid files, parsing
//! returns a cloud or an error: no panic, and no single allocation above 256 MiB however large
//! a count the file claims.

use f3g_splat::{Camera, GaussianCloud, SplatError, ply};
use f3g_testkit::{AllocationGuard, config, mutated, mutated_text};
use proptest::prelude::*;

#[global_allocator]
static GUARD: AllocationGuard = AllocationGuard::new(256 << 20);

/// A valid binary `.ply` of a few degree-1 Gaussians, as `write_ply` makes it.
fn valid_ply() -> Vec<u8> {
    let n = 4;
    let cloud = GaussianCloud {
        means: (0..3 * n).map(|i| i as f32 * 0.1).collect(),
        log_scales: vec![-3.0; 3 * n],
        quats: (0..n).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect(),
        opacity_logits: vec![0.5; n],
        sh: (0..n * 4 * 3).map(|i| (i % 7) as f32 * 0.05).collect(),
        sh_degree: 1,
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("valid.ply");
    ply::write_ply(&path, &cloud).unwrap();
    std::fs::read(path).unwrap()
}

const ASCII_PLY: &str = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n\
property float y\nproperty float z\nproperty float opacity\nend_header\n0 0 0 1\n1 1 1 0\n";

const CAMERA: &str = r#"{"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]],
"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 3], "width": 640, "height": 480,
"near": 0.01, "far": 100}"#;

#[test]
fn the_valid_seeds_parse() {
    assert_eq!(ply::parse_ply(&valid_ply()).unwrap().len(), 4);
    assert!(
        ply::parse_ply(ASCII_PLY.as_bytes())
            .unwrap_err()
            .contains("ascii")
    );
    let cam: Camera = serde_json::from_str(CAMERA).unwrap();
    cam.validate().unwrap();
}

/// Hand-made malformed files and what each must say.
#[test]
fn malformed_ply_corpus() {
    let valid = valid_ply();
    let header_len = valid.windows(10).position(|w| w == b"end_header").unwrap() + 11;
    let text = String::from_utf8_lossy(&valid[..header_len]).into_owned();
    let with_header = |header: String| {
        let mut b = header.into_bytes();
        b.extend_from_slice(&valid[header_len..]);
        b
    };
    let cases: Vec<(Vec<u8>, &str)> = vec![
        (valid[..header_len + 10].to_vec(), "truncated"),
        (
            with_header(text.replace("element vertex 4", "element vertex 99999999999999")),
            "99999999999999 vertices need",
        ),
        (
            with_header(text.replace("element vertex 4", "element vertex -4")),
            "bad vertex count",
        ),
        (
            with_header(text.replace("property float opacity", "property uchar opacity")),
            "opacity",
        ),
        (b"PLY\n".to_vec(), "end_header"),
        (b"".to_vec(), "end_header"),
    ];
    for (bytes, needle) in cases {
        let e = ply::parse_ply(&bytes).unwrap_err();
        assert!(e.contains(needle), "expected `{needle}` in: {e}");
    }
}

proptest! {
    #![proptest_config(config(3000))]

    #[test]
    fn mutated_ply_parses_or_errors(bytes in mutated(valid_ply())) {
        if let Ok(cloud) = ply::parse_ply(&bytes) {
            // Whatever it accepts is a consistent cloud: it validates, or (a mutated float) the
            // check names the first field with a NaN or infinity and its index.
            let fields = [
                ("means", &cloud.means),
                ("log_scales", &cloud.log_scales),
                ("quats", &cloud.quats),
                ("opacity_logits", &cloud.opacity_logits),
                ("sh", &cloud.sh),
            ];
            let first_non_finite = fields.into_iter().find_map(|(name, values)| {
                values.iter().position(|v| !v.is_finite()).map(|index| (name, index))
            });
            match (cloud.validate(), first_non_finite) {
                (Ok(()), None) => {}
                (Err(SplatError::NonFinite { name, index, .. }), Some(expected)) => {
                    prop_assert_eq!((name, index), expected)
                }
                (result, expected) => prop_assert!(
                    false,
                    "validate: {:?}; first non-finite value: {:?}",
                    result,
                    expected
                ),
            }
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }

    #[test]
    fn mutated_ascii_ply_is_refused(text in mutated_text(ASCII_PLY)) {
        // Still an ASCII file with a whole header: refused, saying so. Otherwise an error of its own, or (a
        // mutation that made a binary header) a cloud that validates.
        match ply::parse_ply(text.as_bytes()) {
            Err(e) if text.starts_with("ply\nformat ascii 1.0\n") && text.contains("\nend_header\n") => {
                prop_assert!(e.contains("ascii"), "{}", e)
            }
            Err(e) => prop_assert!(!e.is_empty()),
            Ok(cloud) => {
                prop_assert!(!text.contains("format ascii"));
                prop_assert!(cloud.validate().is_ok());
            }
        }
    }

    #[test]
    fn mutated_camera_json_parses_or_errors(text in mutated_text(CAMERA)) {
        // A camera that validates projects a point ahead of it to finite f32 pixels, which is
        // what the renderers compute with.
        if let Ok(cam) = serde_json::from_str::<Camera>(&text)
            && cam.validate().is_ok()
        {
            let c = cam.center();
            let ahead = [0, 1, 2].map(|k| c[k] + cam.r[2][k] * (cam.near + 1.0).min(cam.far));
            if let Some((uv, depth)) = cam.project(ahead) {
                prop_assert!(uv.iter().chain([&depth]).all(|v| (*v as f32).is_finite()));
            }
        }
    }
}
