//! A body model added through the contract alone, and a run folder that needs nothing else:
//! a rigged glTF whose joints have names no table knows (`bone000`, …) becomes an avatar's
//! body model through its role map; the run keeps its setup, so after the glTF and the role map
//! are deleted and the run is moved, the avatar loads and renders the same image. A run folder
//! of another format is refused with an error naming it and saying what to do.

use std::path::Path;

use burn::tensor::Device;
use f3g_avatar::infer::{RUN_FORMAT, Run, RunInfo, TrainState, TrainedAvatar};
use f3g_avatar::model::{AvatarNets, ModelConfig, Setup};
use f3g_avatar::train::{TrainConfig, Trainer};
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
    m.template = f3g_avatar::model::TemplateChoice::Body;
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

    // Without its stored setup, the run would need the body model: it says to retrain.
    std::fs::remove_file(moved.join("setup.npz")).unwrap();
    let e = TrainedAvatar::load(&moved, &Device::flex())
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains(&moved.display().to_string())
            && e.contains("stored setup")
            && e.contains("retrain"),
        "{e}"
    );
}

/// `run.json` of the run in `dir` with its `format` set to `format` (removed for `None`, as
/// f3g wrote it before runs had a format).
fn set_format(dir: &Path, format: Option<u64>) {
    let path = dir.join("run.json");
    let mut info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let fields = info.as_object_mut().unwrap();
    match format {
        Some(f) => fields.insert("format".into(), f.into()),
        None => fields.remove("format"),
    };
    std::fs::write(&path, serde_json::to_string(&info).unwrap()).unwrap();
}

#[test]
fn a_run_folder_of_another_format_is_refused_naming_it_and_what_to_do() {
    let assets = tempfile::tempdir().unwrap();
    let model = format!("gltf:{}", anonymous_gltf(assets.path()).display());
    let runs = tempfile::tempdir().unwrap();
    let run = runs.path().join("old-run");
    make_run(&run, &model, &config());
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
    assert_eq!(written["format"], RUN_FORMAT);
    TrainedAvatar::load(&run, &Device::flex()).unwrap();

    let folder = run.display().to_string();
    for (format, says) in [
        (None, "retrain"),
        (Some(0), "retrain"),
        (Some(RUN_FORMAT + 1), "newer"),
    ] {
        set_format(&run, format);
        let e = TrainedAvatar::load(&run, &Device::flex())
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains(&folder) && e.contains(says), "{format:?}: {e}");
        // Resuming refuses it the same way, before it would look for the capture.
        let e = Trainer::resume(&run, None, &[Device::flex()])
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains(&folder) && e.contains(says), "{format:?}: {e}");
    }
}
