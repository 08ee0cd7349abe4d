//! Fuzzing the AvatarReX / THuman4.0 calibration reader: for thousands of mutations of a valid
//! file, reading returns cameras or an error naming the file — no panic, no single allocation
//! above 256 MiB — and whatever it accepts holds valid cameras.

use f3g_data::calibration::read_calibration;
use f3g_testkit::{AllocationGuard, config, mutated_text};
use proptest::prelude::*;

#[global_allocator]
static GUARD: AllocationGuard = AllocationGuard::new(256 << 20);

const CALIBRATION: &str = r#"{
 "cam00": {"K": [[1500.0, 0, 768], [0, 1500.0, 1024], [0, 0, 1]],
           "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "T": [0, -0.9, 3.2], "imgSize": [1536, 2048]},
 "cam01": {"K": [1400.0, 0, 760, 0, 1400.0, 1020, 0, 0, 1],
           "R": [0, 0, 1, 0, 1, 0, -1, 0, 0], "T": [0.1, -0.9, 3.0], "imgSize": [1536, 2048]}
}"#;

#[test]
fn the_valid_seed_reads() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("calibration_full.json");
    std::fs::write(&path, CALIBRATION).unwrap();
    assert_eq!(read_calibration(&path).unwrap().len(), 2);
}

/// Hand-made malformed calibrations and what each must say.
#[test]
fn malformed_calibration_corpus() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("calibration_full.json");
    for (text, needle) in [
        (
            CALIBRATION.replace("[1536, 2048]}", "[100000, 100000]}"),
            "too large",
        ),
        // 2³² + 1536: once truncated to 1536 and silently accepted.
        (
            CALIBRATION.replace("[1536, 2048]}", "[4294968832, 2048]}"),
            "imgSize",
        ),
        (
            CALIBRATION.replace("\"T\": [0, -0.9, 3.2]", "\"T\": [0, 3.2]"),
            "T",
        ),
        (
            CALIBRATION.replace("1500.0, 0, 768", "NaN, 0, 768"),
            "not valid JSON",
        ),
        (CALIBRATION.replace("\"K\"", "\"k\""), "K"),
        ("[]".to_string(), "object of cameras"),
    ] {
        std::fs::write(&path, &text).unwrap();
        let e = read_calibration(&path).unwrap_err().to_string();
        assert!(
            e.contains(needle) && e.contains("calibration_full.json"),
            "expected `{needle}` and the file in: {e}"
        );
    }
}

proptest! {
    #![proptest_config(config(2000))]

    #[test]
    fn mutated_calibrations_read_or_error(text in mutated_text(CALIBRATION)) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("calibration_full.json");
        std::fs::write(&path, &text).unwrap();
        match read_calibration(&path) {
            Ok(cameras) => {
                for c in cameras {
                    prop_assert!(c.camera.validate().is_ok());
                }
            }
            Err(e) => prop_assert!(e.to_string().contains("calibration_full.json"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }
}
