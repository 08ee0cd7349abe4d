//! Fuzzing the training configuration: JSON files (any subset of the keys over a preset) and
//! `--set KEY=VALUE` overrides. For thousands of mutations, reading returns a configuration
//! that validates or an error naming the file or key — no panic, no single allocation above
//! 256 MiB.

use f3g_avatar::TrainConfig;
use f3g_testkit::{AllocationGuard, config, mutated_text};
use proptest::prelude::*;

#[global_allocator]
static GUARD: AllocationGuard = AllocationGuard::new(256 << 20);

const CONFIG: &str = r#"{"preset": "cpu", "map_resolution": 128, "steps": {"body": 50,
"joint": 20}, "body_net": {"input_size": 32, "output_size": 64, "max_channels": 16},
"losses": {"lpips": 0.2, "r1_interval": 8}, "lr": 0.002, "face_crop_size": 64,
"discriminator": {"resolution": 64}, "band_radius": 1.5, "body_layout": "three"}"#;

const SETS: &str = "steps.joint=500 lr=0.002 body_net.max_channels=16 face_branch=false \
face_losses=false lpips_net=vgg map_resolution=512 losses.offset=0.01";

#[test]
fn the_valid_seeds_read() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("config.json");
    std::fs::write(&path, CONFIG).unwrap();
    assert_eq!(TrainConfig::from_file(&path).unwrap().map_resolution, 128);
    let sets: Vec<String> = SETS.split(' ').map(String::from).collect();
    assert_eq!(
        TrainConfig::cpu()
            .with_overrides(&sets)
            .unwrap()
            .steps
            .joint,
        500
    );
}

proptest! {
    #![proptest_config(config(2000))]

    #[test]
    fn mutated_config_files_read_or_error(text in mutated_text(CONFIG)) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("config.json");
        std::fs::write(&path, &text).unwrap();
        match TrainConfig::from_file(&path) {
            Ok(c) => prop_assert!(c.validate().is_ok()),
            Err(e) => prop_assert!(e.to_string().contains("config.json"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }

    #[test]
    fn mutated_overrides_apply_or_error(text in mutated_text(SETS)) {
        let sets: Vec<String> = text.split(' ').map(String::from).collect();
        if let Ok(c) = TrainConfig::cpu().with_overrides(&sets) {
            prop_assert!(c.validate().is_ok());
        }
    }
}
