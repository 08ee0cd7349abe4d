//! A body model added through the contract alone, and a run folder that needs nothing else:
//! a rigged glTF whose joints have names no table knows (`bone000`, …) becomes an avatar's
//! body model through its role map; the run keeps its setup, so after the glTF and the role map
//! are deleted and the run is moved, the avatar loads and renders the same image.

use std::path::Path;

use burn::tensor::Device;
use f3g_avatar::model::AvatarNets;
use f3g_avatar::run::{Run, RunInfo, TrainState};
use f3g_avatar::setup::Setup;
use f3g_avatar::trained::TrainedAvatar;
use f3g_avatar::{ModelConfig, TrainConfig};
use f3g_rig::{Rig, RoleMap, Skeleton};
use f3g_splat::Camera;

/// The built-in human with every joint renamed `boneNNN`, written as a glTF with a role map.
fn anonymous_gltf(dir: &Path) -> std::path::PathBuf {
    let rig = f3g_rig::builtin::load().unwrap().rig;
    let joints = rig
        .skeleton
        .joints()
        .iter()
        .enumerate()
        .map(|(i, j)| f3g_rig::Joint {
            name: format!("bone{i:03}"),
            ..j.clone()
        })
        .collect();
    let anonymous = Rig {
        skeleton: Skeleton::new(joints).unwrap(),
        ..rig.clone()
    };
    let path = dir.join("character.glb");
    f3g_rig::gltf::write(&anonymous, &path).unwrap();
    let map = RoleMap(
        rig.roles
            .iter()
            .map(|(role, j)| (role, format!("bone{j:03}")))
            .collect(),
    );
    std::fs::write(RoleMap::beside(&path), serde_json::to_string(&map).unwrap()).unwrap();
    path
}

/// A small model on the glTF's bare body, with the face branch.
fn config() -> TrainConfig {
    let mut c = TrainConfig::cpu();
    let m: &mut ModelConfig = &mut c.model;
    m.template = f3g_avatar::config::TemplateChoice::Body;
    m.map_resolution = 32;
    m.body_net.input_size = 16;
    m.body_net.output_size = 32;
    m.body_net.max_channels = 8;
    m.body_net.channel_base = 128;
    m.body_net.style_dim = 8;
    m.body_net.middle_size = 4;
    m.face_net.input_size = 16;
    m.face_net.output_size = 16;
    m.face_net.max_channels = 8;
    m.face_net.channel_base = 64;
    m.face_net.style_dim = 8;
    m.face_net.middle_size = 4;
    c.validate().unwrap();
    c
}

/// A run folder as `f3g train` leaves it, with untrained networks as its checkpoint.
fn make_run(dir: &Path, model: &str, config: &TrainConfig) {
    let setup = Setup::new(model, &[], &config.model).unwrap();
    let run = Run::new(dir);
    run.write_config(config).unwrap();
    run.write_info(&RunInfo {
        data: dir.join("no-capture"),
        model: model.into(),
        identity: Vec::new(),
        train_cameras: vec![0],
        train_frames: vec![0],
    })
    .unwrap();
    setup.write(dir).unwrap();
    let device = Device::flex();
    let nets = AvatarNets::new(&config.model, config.seed, &setup, &device).unwrap();
    let checkpoint = dir.join("checkpoints/step-000000001");
    std::fs::create_dir_all(&checkpoint).unwrap();
    f3g_nets::checkpoint::save(nets, &checkpoint.join("nets.bpk")).unwrap();
    let state = TrainState {
        step: 1,
        seconds: 0.0,
        disc_steps: 0,
        device: String::new(),
        replicas: 1,
    };
    std::fs::write(
        checkpoint.join("state.json"),
        serde_json::to_string(&state).unwrap(),
    )
    .unwrap();
    std::fs::write(dir.join("checkpoints/latest"), "step-000000001").unwrap();
}

fn render(run: &Path) -> Vec<f32> {
    let avatar = TrainedAvatar::load(run, &Device::flex()).unwrap();
    let mut params = avatar.setup.rig.zero_params();
    // Turn the head (its role's joint, found through the role map) to the side.
    let head = avatar.setup.rig.role(f3g_rig::Role::Head).unwrap();
    avatar
        .setup
        .rig
        .set_rotation(&mut params, head, 4, 0.4)
        .unwrap();
    let camera = Camera::look_at(
        [0.0, 0.3, 3.0],
        [0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        200.0,
        96,
        128,
    );
    avatar
        .render(&params, &camera, [1.0; 3], false)
        .unwrap()
        .data
}

#[test]
fn a_gltf_body_model_through_its_role_map_and_a_run_that_needs_nothing_else() {
    let assets = tempfile::tempdir().unwrap();
    let glb = anonymous_gltf(assets.path());
    let model = format!("gltf:{}", glb.display());
    let runs = tempfile::tempdir().unwrap();
    let original = runs.path().join("run");
    make_run(&original, &model, &config());
    let before = render(&original);
    assert!(
        before.iter().any(|&v| v < 0.9),
        "the avatar covers part of the image"
    );

    // Move the run and delete the body model's files.
    let moved = runs.path().join("elsewhere/run");
    std::fs::create_dir_all(moved.parent().unwrap()).unwrap();
    std::fs::rename(&original, &moved).unwrap();
    drop(assets);
    assert!(!glb.exists());
    assert_eq!(render(&moved), before);

    // Without its stored setup, the run would need the body model, and says so.
    std::fs::remove_file(moved.join(f3g_avatar::setup_file::TABLES)).unwrap();
    let e = TrainedAvatar::load(&moved, &Device::flex())
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("keeps no setup") && e.contains("--resume"),
        "{e}"
    );
}
