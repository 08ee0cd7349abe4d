//! Fuzzing the AvatarReX / THuman4.0 calibration reader and the keypoint readers (OpenPose,
//! COCO): for thousands of mutations of a valid file, reading returns its contents or an error
//! naming the file — no panic, no single allocation above 256 MiB — and whatever it accepts is
//! valid (cameras that validate; finite keypoints with confidences in [0, 1]).

use f3g_data::calibration::read_calibration;
use f3g_data::fit::Keypoint;
use f3g_data::keypoints::{read_coco, read_openpose};
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

const OPENPOSE: &str = r#"{"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d":
 [10, 20, 0.9, 11, 21, 0.8, 12, 22, 0.7, 13, 23, 0.6, 14, 24, 0.5, 15, 25, 0.4, 16, 26, 0.3,
  17, 27, 0.2, 18, 28, 0.1, 19, 29, 1, 20, 30, 1, 21, 31, 1, 22, 32, 1, 23, 33, 1, 24, 34, 1,
  25, 35, 1, 26, 36, 1, 27, 37, 1, 28, 38, 1, 29, 39, 1, 30, 40, 1, 31, 41, 1, 32, 42, 1,
  33, 43, 1, 34, 44, 1]}]}"#;

const COCO: &str = r#"{"images": [{"id": 4, "file_name": "cam00/00000003.jpg"}],
 "annotations": [{"image_id": 4, "score": 0.9, "keypoints": [1, 2, 2, 3, 4, 2, 5, 6, 1, 7, 8, 0,
  9, 10, 2, 11, 12, 2, 13, 14, 2, 15, 16, 2, 17, 18, 2, 19, 20, 2, 21, 22, 2, 23, 24, 2, 25, 26, 2,
  27, 28, 2, 29, 30, 2, 31, 32, 2, 33, 34, 2]}]}"#;

fn valid(points: &[Keypoint]) -> bool {
    points
        .iter()
        .all(|p| p.pixel.is_finite() && (0.0..=1.0).contains(&p.confidence))
}

#[test]
fn the_valid_keypoint_seeds_read() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("k.json");
    std::fs::write(&path, OPENPOSE).unwrap();
    assert_eq!(read_openpose(&path).unwrap().len(), 15);
    std::fs::write(&path, COCO).unwrap();
    assert_eq!(read_coco(&path).unwrap()[&3].len(), 14);
}

proptest! {
    #![proptest_config(config(1000))]

    #[test]
    fn mutated_keypoint_files_read_or_error(
        openpose in mutated_text(OPENPOSE),
        coco in mutated_text(COCO),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("k.json");
        std::fs::write(&path, &openpose).unwrap();
        match read_openpose(&path) {
            Ok(points) => prop_assert!(valid(&points)),
            Err(e) => prop_assert!(e.to_string().contains("k.json"), "{}", e),
        }
        std::fs::write(&path, &coco).unwrap();
        match read_coco(&path) {
            Ok(frames) => prop_assert!(frames.values().all(|p| valid(p))),
            Err(e) => prop_assert!(e.to_string().contains("k.json"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }
}
