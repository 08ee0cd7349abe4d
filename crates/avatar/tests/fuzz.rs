//! Fuzzing what a run folder holds: the training configuration (JSON files, any subset of the
//! keys over a preset, and `--set KEY=VALUE` overrides) and a checkpoint's own files — the
//! training state (`state.json`), optimiser states (`optim_*.bpk`), the face Gaussians'
//! canonical base (`face_base.npz`) and the pose PCA (`pca.npz`). For thousands of mutations,
//! reading returns a value that validates (an optimiser that then steps) or an error naming
//! the file or key — no panic, no single allocation above 256 MiB. (Module files are fuzzed in
//! `f3g-nets`.)

use burn::optim::GradientsParams;
use burn::tensor::Device;
use f3g_avatar::infer::{Run, load_face_base, read_state};
use f3g_avatar::model::Setup;
use f3g_avatar::train::{TrainConfig, load_optim};
use f3g_nets::StyleUNetConfig;
use f3g_nets::adam::{FusedAdam, ModuleAdam};
use f3g_testkit::{
    AllocationGuard, Array, config, mutated, mutated_arrays, mutated_text, read_arrays,
    write_arrays,
};
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
    assert_eq!(
        TrainConfig::from_file(&path).unwrap().model.map_resolution,
        128
    );
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
        // Applied, a valid configuration; refused, an error that names the key, the value's
        // problem or the `--set` syntax.
        match TrainConfig::cpu().with_overrides(&sets) {
            Ok(c) => prop_assert!(c.validate().is_ok()),
            Err(e) => {
                let e = e.to_string();
                let named = sets.iter().any(|s| {
                    let key = s.split('=').next().unwrap_or(s);
                    e.contains(key.rsplit('.').next().unwrap_or(key))
                });
                prop_assert!(named || e.contains("--set") || e.contains("key=value"), "{}", e);
            }
        }
    }
}

const STATE: &str = r#"{"step": 120, "seconds": 35.5, "disc_steps": 40}"#;

/// A small network whose parameter ids are a function of `namespace` (an optimiser state
/// refers to parameters by id).
fn small_net(device: &Device, namespace: u64) -> f3g_nets::DualStyleUNet {
    net_of_width(device, namespace, 4)
}

fn net_of_width(device: &Device, namespace: u64, channels: usize) -> f3g_nets::DualStyleUNet {
    let net = StyleUNetConfig {
        input_size: 16,
        output_size: 16,
        channel_base: 32,
        max_channels: channels,
        style_dim: 4,
        middle_size: 4,
        ..StyleUNetConfig::cpu_face(3, false)
    }
    .init(1, device)
    .unwrap();
    f3g_nets::checkpoint::with_deterministic_ids(net, namespace)
}

fn step(
    optim: &mut ModuleAdam,
    net: f3g_nets::DualStyleUNet,
    device: &Device,
) -> f3g_nets::DualStyleUNet {
    let input = burn::tensor::Tensor::<4>::ones([1, 3, 16, 16], device);
    let loss = net
        .forward(input, None)
        .unwrap()
        .front
        .powi_scalar(2)
        .mean();
    let mut grads = loss.backward();
    let grads = GradientsParams::from_module(&mut grads, &net);
    optim.step(1e-3, net, grads)
}

/// The trainer's optimiser (Burn's `Adam` with PyTorch's ε, its records Burn's).
fn adam() -> ModuleAdam {
    FusedAdam {
        beta_1: 0.9,
        beta_2: 0.999,
        epsilon: 1e-8,
    }
    .init()
}

/// Adam's state after two steps of `small_net(_, 1)` (moments for every parameter).
static OPTIM_SEED: std::sync::LazyLock<Vec<u8>> = std::sync::LazyLock::new(|| {
    let device = Device::flex().autodiff();
    let mut optim = adam();
    let net = step(&mut optim, small_net(&device, 1), &device);
    step(&mut optim, net, &device);
    optim.to_record().into_bytes().unwrap().to_vec()
});

fn face_base() -> Vec<Array> {
    let n = 6;
    let ramp = |k: usize| -> Vec<f32> { (0..n * k).map(|i| i as f32 * 0.1 - 0.3).collect() };
    vec![
        Array::f32("positions", &[n, 3], &ramp(3)),
        Array::f32("colours", &[n, 3], &ramp(3)),
        Array::f32("opacity_logits", &[n], &ramp(1)),
        Array::f32("log_scales", &[n, 3], &ramp(3)),
        Array::f32("quats", &[n, 4], &ramp(4)),
    ]
}

fn pca() -> Vec<Array> {
    let (k, d) = (3, 5);
    let ramp = |m: usize| -> Vec<f32> { (0..m).map(|i| (i as f32).cos()).collect() };
    vec![
        Array::f32("mean", &[d], &ramp(d)),
        Array::f32("components", &[k, d], &ramp(k * d)),
        Array::f32("stddev", &[k], &ramp(k)),
        Array::f32("sigma", &[1], &[2.0]),
    ]
}

/// A small model of the built-in human (face branch on) and its stored setup's folder.
static SETUP: std::sync::LazyLock<(f3g_avatar::model::ModelConfig, tempfile::TempDir)> =
    std::sync::LazyLock::new(|| {
        let mut model = TrainConfig::cpu().model;
        model.map_resolution = 32;
        model.template = f3g_avatar::model::TemplateChoice::Body;
        let dir = tempfile::tempdir().unwrap();
        Setup::new("builtin", &[0.0; 5], &model)
            .unwrap()
            .write(dir.path())
            .unwrap();
        (model, dir)
    });

#[test]
fn the_valid_setup_reads() {
    let (model, dir) = &*SETUP;
    let setup = Setup::read(dir.path(), model).unwrap();
    assert!(setup.face_count() > 0 && setup.body_count() > 0);
}

#[test]
fn the_valid_checkpoint_seeds_read() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("state.json"), STATE).unwrap();
    assert_eq!(read_state(dir.path()).unwrap().step, 120);
    let device = Device::flex().autodiff();
    let path = dir.path().join("optim.bpk");
    std::fs::write(&path, &*OPTIM_SEED).unwrap();
    let net = small_net(&device, 1);
    let mut optim = load_optim(adam(), &path, &net).unwrap();
    step(&mut optim, net, &device);
    // The state of another network (different parameter ids) is refused.
    let other = small_net(&device, 2);
    let e = load_optim(adam(), &path, &other).err().unwrap().to_string();
    assert!(e.contains("optim.bpk") && e.contains("no parameter"), "{e}");
    // A wider network with the same ids: Burn would load the state and panic at the next step.
    let wider = net_of_width(&device, 1, 8);
    let e = load_optim(adam(), &path, &wider).err().unwrap().to_string();
    assert!(
        e.contains("optim.bpk") && e.contains("its parameter is F32"),
        "{e}"
    );
    let path = dir.path().join("face_base.npz");
    write_arrays(&path, &face_base());
    assert_eq!(load_face_base(&path, 6).unwrap().len(), 6);
    write_arrays(&dir.path().join("pca.npz"), &pca());
    assert_eq!(Run::new(dir.path()).pca().unwrap().sigma, 2.0);
}

proptest! {
    #![proptest_config(config(2000))]

    #[test]
    fn mutated_train_states_read_or_error(text in mutated_text(STATE)) {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("state.json"), &text).unwrap();
        match read_state(dir.path()) {
            Ok(s) => prop_assert!(s.seconds.is_finite() && s.seconds >= 0.0),
            Err(e) => prop_assert!(e.to_string().contains("state.json"), "{}", e),
        }
    }

    #[test]
    fn mutated_face_bases_read_or_error(arrays in mutated_arrays(face_base())) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("face_base.npz");
        write_arrays(&path, &arrays);
        match load_face_base(&path, 6) {
            Ok(b) => prop_assert!(b.len() == 6 && b.positions.iter().all(|v| v.is_finite())),
            Err(e) => prop_assert!(e.to_string().contains("face_base.npz"), "{}", e),
        }
    }

    #[test]
    fn mutated_pose_pcas_read_or_error(arrays in mutated_arrays(pca())) {
        let dir = tempfile::tempdir().unwrap();
        write_arrays(&dir.path().join("pca.npz"), &arrays);
        match Run::new(dir.path()).pca() {
            Ok(p) => {
                prop_assert_eq!(p.components.len(), p.stddev.len() * p.mean.len());
                prop_assert!(p.components.iter().chain(&p.mean).chain(&p.stddev).all(|v| v.is_finite()));
            }
            Err(e) => prop_assert!(e.to_string().contains("pca.npz"), "{}", e),
        }
    }
}

proptest! {
    #![proptest_config(config(200))]

    /// A run's `setup.npz` (its body model and template stay valid): every mutation reads to
    /// a setup whose tables agree with the rig and the template, or is an error naming it.
    #[test]
    fn mutated_setups_read_or_error(arrays in mutated_arrays(read_arrays(&SETUP.1.path().join("setup.npz")))) {
        let (model, valid) = &*SETUP;
        let dir = tempfile::tempdir().unwrap();
        for name in ["body_model.npz", "template.npz"] {
            std::fs::copy(valid.path().join(name), dir.path().join(name)).unwrap();
        }
        write_arrays(&dir.path().join("setup.npz"), &arrays);
        match Setup::read(dir.path(), model) {
            Ok(setup) => {
                let (j, n) = (setup.rig.skeleton.len(), setup.body_count());
                prop_assert_eq!(setup.body_log_scales.len(), n);
                prop_assert!(setup.maps.skin.joints.iter().flatten().all(|&x| (x as usize) < j));
                if let Some(h) = &setup.head {
                    prop_assert!(h.sources.iter().flatten().all(|s| s.0 < n));
                }
            }
            Err(e) => prop_assert!(e.to_string().contains("setup.npz"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }
}

proptest! {
    #![proptest_config(config(300))]

    /// The same network (same parameter ids) loads every mutation that passes the checks, and
    /// then steps.
    #[test]
    fn mutated_optimiser_states_load_and_step_or_error(bytes in mutated(OPTIM_SEED.clone())) {
        let device = Device::flex().autodiff();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("optim.bpk");
        std::fs::write(&path, &bytes).unwrap();
        let net = small_net(&device, 1);
        match load_optim(adam(), &path, &net) {
            Ok(mut optim) => {
                step(&mut optim, net, &device);
            }
            Err(e) => prop_assert!(e.to_string().contains("optim.bpk"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }
}

/// A small avatar file: two joints, five Gaussians, two correctives.
fn small_avatar_file() -> Vec<u8> {
    small_avatar_file_as(f3g_avatar::infer::avatar_file::Encoding::Float)
}

/// [`small_avatar_file`] in `encoding`.
fn small_avatar_file_as(encoding: f3g_avatar::infer::avatar_file::Encoding) -> Vec<u8> {
    use f3g_rig::{Joint, Mesh, Parameterization, Rig, Roles, Skeleton, SkinWeights};
    use glam::{Quat, Vec3};
    let joint = |name: &str, parent: Option<usize>| Joint {
        name: name.into(),
        parent,
        offset: Vec3::new(0.0, 0.5, 0.0),
        pre_rotation: Quat::IDENTITY,
    };
    let skin = SkinWeights::from_lists(&vec![vec![(0, 0.5), (1, 0.5)]; 3], 2).unwrap();
    let rig = Rig {
        name: "small".into(),
        skeleton: Skeleton::new(vec![joint("a", None), joint("b", Some(0))]).unwrap(),
        parameterization: Parameterization::AxisAngle,
        mesh: Mesh {
            vertices: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
            triangles: vec![[0, 1, 2]],
        },
        identity: Default::default(),
        expression: Default::default(),
        skin,
        correctives: None,
        joint_model: None,
        inverse_bind: None,
        roles: Roles::default(),
        surface: vec![true; 3],
    };
    let n = 5;
    let ramp = |k: usize, scale: f32| -> Vec<f32> {
        (0..k).map(|i| (i as f32 * 0.37).sin() * scale).collect()
    };
    let baked = f3g_avatar::infer::bake::BakedAvatar {
        canonical: rig.zero_params(),
        rig,
        means: ramp(3 * n, 0.5),
        quats: (0..n).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect(),
        log_scales: vec![-4.0; 3 * n],
        opacity_logits: ramp(n, 1.0),
        sh: ramp(4 * 3 * n, 0.3),
        sh_degree: 1,
        skin_joints: vec![[0, 1, 0, 0]; n],
        skin_weights: vec![[0.5, 0.5, 0.0, 0.0]; n],
        correctives: ramp(2 * n * f3g_avatar::infer::bake::CORRECTIVE_VALUES, 0.01),
        feature_joints: vec![1],
        feature_used: vec![0, 4, 8],
        feature_mean: vec![0.0; 3],
        feature_map: ramp(6, 1.0),
        expression_names: Vec::new(),
        expressions: Vec::new(),
        head_vertices: vec![2],
        face_padding: 1.3,
        face_crop_size: 64,
        step: 7,
        shading: Some(f3g_avatar::infer::bake::BakedShading {
            coefficients: ramp(27, 1.0),
            normals: (0..n).flat_map(|_| [0.0, 0.6, 0.8]).collect(),
        }),
    };
    f3g_avatar::infer::avatar_file::to_bytes(&baked, encoding).unwrap()
}

#[test]
fn the_small_avatar_file_reads() {
    let avatar = f3g_avatar::infer::avatar_file::from_bytes(&small_avatar_file()).unwrap();
    assert_eq!(
        (avatar.len(), avatar.corrective_count(), avatar.step),
        (5, 2, 7)
    );
    avatar.posed(&avatar.rig.zero_params()).unwrap();
}

/// The small avatar file with its JSON document edited.
fn with_document(edit: impl FnOnce(&mut serde_json::Value)) -> Vec<u8> {
    let mut file = f3g_rig::glb::GlbFile::parse(&small_avatar_file()).unwrap();
    edit(&mut file.document);
    file.to_bytes()
}

/// The small avatar file with element `element` of the accessor at `pointer` (a JSON pointer
/// to its index) set to `value`.
fn with_float(pointer: &str, element: usize, value: f32) -> Vec<u8> {
    with_floats(pointer, &[(element, value)])
}

/// [`with_float`] for several elements.
fn with_floats(pointer: &str, edits: &[(usize, f32)]) -> Vec<u8> {
    let mut bytes = small_avatar_file();
    let file = f3g_rig::glb::GlbFile::parse(&bytes).unwrap();
    let doc = &file.document;
    let accessor = &doc["accessors"][doc.pointer(pointer).unwrap().as_u64().unwrap() as usize];
    let view = &doc["bufferViews"][accessor["bufferView"].as_u64().unwrap() as usize];
    let offset =
        view["byteOffset"].as_u64().unwrap_or(0) + accessor["byteOffset"].as_u64().unwrap_or(0);
    // The binary chunk's data follow the 12-byte header, the JSON chunk and an 8-byte header.
    let json = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    for &(element, value) in edits {
        let at = 12 + 8 + json + 8 + offset as usize + 4 * element;
        bytes[at..at + 4].copy_from_slice(&value.to_le_bytes());
    }
    bytes
}

/// What a player or `eval` would take as it is, refused with the field named: a face padding
/// that crops nothing (a perfect score) or everything (a hang), values out of their range, a
/// node cycle, a buffer larger than the file, non-finite inverse-bind matrices, no Gaussians
/// extension.
#[test]
fn avatar_files_out_of_range_are_refused_naming_the_field() {
    let primitive = "/meshes/0/primitives/0";
    let attribute = |name: &str| format!("{primitive}/attributes/{name}");
    let cases: Vec<(Vec<u8>, &str)> = vec![
        (
            with_document(|d| d["extensions"]["F3G_avatar"]["facePadding"] = (-5.0).into()),
            "facePadding",
        ),
        (
            with_document(|d| d["extensions"]["F3G_avatar"]["facePadding"] = 0.into()),
            "facePadding",
        ),
        (
            with_document(|d| d["extensions"]["F3G_avatar"]["facePadding"] = 1e6.into()),
            "facePadding",
        ),
        (
            with_document(|d| d["extensions"]["F3G_avatar"]["faceCropSize"] = 0.into()),
            "faceCropSize",
        ),
        (
            with_document(|d| {
                let child = d["nodes"][0]["children"][0].clone();
                d["nodes"][child.as_u64().unwrap() as usize]["children"] = serde_json::json!([0]);
            }),
            "cycle",
        ),
        (
            with_document(|d| d["buffers"][0]["byteLength"] = (1u64 << 40).into()),
            "buffer 0",
        ),
        (
            with_document(|d| {
                d.pointer_mut(&format!("{primitive}/extensions"))
                    .unwrap()
                    .as_object_mut()
                    .unwrap()
                    .remove("KHR_gaussian_splatting");
            }),
            "KHR_gaussian_splatting",
        ),
        (
            with_float(&attribute("KHR_gaussian_splatting:OPACITY"), 2, 5.0),
            "OPACITY of Gaussian 2",
        ),
        (
            with_float(&attribute("KHR_gaussian_splatting:SCALE"), 4, -1.0),
            "SCALE of Gaussian 1",
        ),
        (
            with_floats(
                &attribute("KHR_gaussian_splatting:ROTATION"),
                &[(12, 0.0), (13, 0.0), (14, 0.0), (15, 0.0)],
            ),
            "ROTATION of Gaussian 3",
        ),
        (
            with_float("/skins/0/inverseBindMatrices", 5, f32::NAN),
            "inverse-bind",
        ),
        (
            with_float(
                &format!("{primitive}/extensions/F3G_world_shading/normal"),
                7,
                3.0,
            ),
            "F3G_world_shading.normal of Gaussian 2",
        ),
        (
            with_document(|d| {
                d.pointer_mut(&format!("{primitive}/extensions/F3G_world_shading"))
                    .unwrap()["coefficients"] = serde_json::json!([1.0, 2.0]);
            }),
            "F3G_world_shading.coefficients",
        ),
    ];
    for (bytes, field) in cases {
        match f3g_avatar::infer::avatar_file::from_bytes(&bytes) {
            Ok(_) => panic!("accepted an avatar file that should fail on `{field}`"),
            Err(e) => assert!(e.contains(field), "expected `{field}` in: {e}"),
        }
    }
}

/// The JSON fields of the avatar file that a mutation of its bytes rarely reaches intact:
/// sizes, offsets, indices, the node graph and the extensions' numbers.
const AVATAR_FIELDS: [&str; 15] = [
    "/extensions/F3G_avatar/facePadding",
    "/extensions/F3G_avatar/faceCropSize",
    "/extensions/F3G_avatar/bodyModel/bufferView",
    "/extensions/F3G_avatar/headVertices",
    "/buffers/0/byteLength",
    "/bufferViews/0/byteOffset",
    "/bufferViews/1/byteLength",
    "/accessors/0/count",
    "/accessors/1/bufferView",
    "/nodes/0/children/0",
    "/skins/0/joints/1",
    "/skins/0/inverseBindMatrices",
    "/meshes/0/primitives/0/extensions/F3G_pose_correctives/count",
    "/meshes/0/primitives/0/attributes/JOINTS_0",
    "/meshes/0/primitives/0/extensions/F3G_world_shading/normal",
];

/// The compressed small avatar reads back as the float one within the quantisation: its
/// Gaussians from the SPZ payload, its correctives and normals from the packed arrays.
#[test]
fn the_compressed_small_avatar_file_reads_as_the_float_one() {
    use f3g_avatar::infer::avatar_file::{Encoding, from_bytes};
    let float = from_bytes(&small_avatar_file()).unwrap();
    let bytes = small_avatar_file_as(Encoding::Compressed);
    let compressed = from_bytes(&bytes).unwrap();
    let close = |a: &[f32], b: &[f32], tolerance: f32, what: &str| {
        assert_eq!(a.len(), b.len(), "{what}");
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() <= tolerance, "{what}: {x} against {y}");
        }
    };
    close(&float.means, &compressed.means, 2e-4, "means");
    close(
        &float.log_scales,
        &compressed.log_scales,
        1.0 / 32.0,
        "log-scales",
    );
    close(
        &float.correctives,
        &compressed.correctives,
        0.01 / 127.0 + 1e-7,
        "correctives",
    );
    close(
        &float.feature_map,
        &compressed.feature_map,
        0.0,
        "feature map",
    );
    let (a, b) = (float.shading.unwrap(), compressed.shading.clone().unwrap());
    close(&a.normals, &b.normals, 0.01, "normals");
    assert_eq!(compressed.skin_joints, float.skin_joints);
    close(
        &float.skin_weights.concat(),
        &compressed.skin_weights.concat(),
        // Rounded, and the largest takes the rounding's remainder.
        1.0 / 255.0,
        "skin weights",
    );
    let file = f3g_rig::glb::GlbFile::parse(&bytes).unwrap();
    // POSITION's bounds describe the positions as stored (glTF requires them exact).
    let position = file.document["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
        .as_u64()
        .unwrap() as usize;
    for (c, bound) in ["min", "max"].into_iter().enumerate() {
        let pick = |a: f32, b: f32| if c == 0 { a.min(b) } else { a.max(b) };
        let expected: Vec<f64> = (0..3)
            .map(|axis| {
                let start = if c == 0 {
                    f32::INFINITY
                } else {
                    f32::NEG_INFINITY
                };
                compressed
                    .means
                    .iter()
                    .skip(axis)
                    .step_by(3)
                    .fold(start, |m, &v| pick(m, v)) as f64
            })
            .collect();
        assert_eq!(
            file.document["accessors"][position][bound],
            serde_json::json!(expected),
            "{bound}"
        );
    }
    assert_eq!(
        file.document["extensionsRequired"],
        serde_json::json!([
            "KHR_gaussian_splatting_compression_spz_2",
            "F3G_packed_arrays"
        ])
    );
    let posed = compressed.posed(&compressed.rig.zero_params());
    assert!(posed.is_ok(), "{:?}", posed.err());
}

proptest! {
    #![proptest_config(config(1000))]

    /// A compressed avatar `.glb` (SPZ and deflated arrays inside): every mutation reads to an
    /// avatar that poses, or is an error naming the file.
    #[test]
    fn mutated_compressed_avatar_files_read_or_error(
        bytes in mutated(small_avatar_file_as(f3g_avatar::infer::avatar_file::Encoding::Compressed)),
    ) {
        match f3g_avatar::infer::avatar_file::from_bytes(&bytes) {
            Ok(avatar) => {
                let posed = avatar.posed(&avatar.rig.zero_params());
                prop_assert!(posed.is_ok(), "{:?}", posed.err());
            }
            Err(e) => prop_assert!(!e.is_empty()),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }

    /// An avatar `.glb`: every mutation reads to an avatar that poses, or is an error naming
    /// the file.
    #[test]
    fn mutated_avatar_files_read_or_error(bytes in mutated(small_avatar_file())) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("avatar.glb");
        std::fs::write(&path, &bytes).unwrap();
        match f3g_avatar::infer::avatar_file::read(&path) {
            Ok(avatar) => {
                let posed = avatar.posed(&avatar.rig.zero_params());
                prop_assert!(posed.is_ok(), "{:?}", posed.err());
            }
            Err(e) => prop_assert!(e.to_string().contains("avatar.glb"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }

    /// Structure-aware: one field of the glTF document or the extensions set to any number
    /// (negative, zero, huge, fractional): the file reads to an avatar that poses, or is an
    /// error.
    #[test]
    fn avatar_files_with_a_field_changed_read_or_error(
        field in proptest::sample::select(AVATAR_FIELDS.to_vec()),
        value in prop_oneof![
            Just(-1.0f64), Just(0.0), Just(0.5), Just(1e6), Just(4294967296.0), Just(1e300),
            -10.0f64..10.0, 0.0f64..100.0,
        ],
    ) {
        let bytes = with_document(|d| {
            if let Some(v) = d.pointer_mut(field) {
                *v = if value.fract() == 0.0 && (0.0..1e18).contains(&value) {
                    (value as u64).into()
                } else {
                    value.into()
                };
            }
        });
        if let Ok(avatar) = f3g_avatar::infer::avatar_file::from_bytes(&bytes) {
            let posed = avatar.posed(&avatar.rig.zero_params());
            prop_assert!(posed.is_ok(), "{:?}", posed.err());
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }
}
