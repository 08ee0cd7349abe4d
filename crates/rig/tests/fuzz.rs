//! Fuzzing the body-model and parameter readers with files from other tools: OBJ meshes,
//! glTF/GLB characters, Momentum `.model` transforms, `smpl_params.npz` and f3g's `.npz`
//! sequences. For thousands of mutations of a valid file each reader returns a well-formed
//! value or an error naming the file — no panic, no single allocation above 256 MiB. (The MHR
//! asset folder is fuzzed in `tests/mhr.rs`, which authors one.)

use std::path::Path;

use f3g_rig::obj::parse_obj;
use f3g_rig::{ModelSpec, Rig, RigParams, gltf, parse_model, sequence, smplx};
use f3g_testkit::{
    AllocationGuard, Array, config, mutated, mutated_arrays, mutated_text, write_arrays,
};
use proptest::prelude::*;

#[global_allocator]
static GUARD: AllocationGuard = AllocationGuard::new(256 << 20);

const OBJ: &str = "# a quad and a triangle\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n\
v 0.5 0.5 1\nvn 0 0 1\nvt 0 0\nf 1/1/1 2/1/1 3/1/1 4/1/1\nf -1 1 2\ng skirt\nf 5 2 3\n";

#[test]
fn the_valid_seed_parses_and_malformed_files_say_where() {
    let mesh = parse_obj(OBJ, Path::new("g.obj")).unwrap();
    assert_eq!(mesh.vertices.len(), 5);
    for (text, needle) in [
        ("v 0 0 nan\n", "finite"),
        ("v 0 0\n", "three"),
        ("v 0 0 0\nf 1 2 99999999999\n", "g.obj:2: face index"),
        ("v 0 0 0\nf 1 x 1\n", "g.obj:2"),
    ] {
        let e = parse_obj(text, Path::new("g.obj")).unwrap_err().to_string();
        assert!(
            e.contains(needle) && e.contains("g.obj"),
            "expected `{needle}` in: {e}"
        );
    }
}

const GLB: &[u8] = include_bytes!("data/pymomentum/char_a.glb");
const MODEL: &str = include_str!("data/pymomentum/char_a.model");

fn glb_rig() -> Rig {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.glb");
    std::fs::write(&path, GLB).unwrap();
    gltf::load(&path, None).unwrap()
}

/// A rig that loaded must be consistent, and its rest pose must pose.
fn check_rig(rig: &Rig) -> Result<(), TestCaseError> {
    prop_assert!(rig.validate().is_ok());
    if let Ok(posed) = rig.pose(&rig.zero_params()) {
        prop_assert_eq!(posed.vertices.len(), rig.mesh.vertices.len());
    }
    Ok(())
}

/// Two frames of `smpl_params.npz` (every array, optional ones included).
fn smpl_params() -> Vec<Array> {
    let ramp = |n: usize| -> Vec<f32> { (0..n).map(|i| (i as f32 * 0.01).sin()).collect() };
    let mut arrays: Vec<Array> = [
        ("transl", 3),
        ("global_orient", 3),
        ("body_pose", 63),
        ("jaw_pose", 3),
        ("leye_pose", 3),
        ("reye_pose", 3),
        ("left_hand_pose", 45),
        ("right_hand_pose", 45),
        ("expression", 10),
    ]
    .into_iter()
    .map(|(name, width)| Array::f32(name, &[2, width], &ramp(2 * width)))
    .collect();
    arrays.push(Array::f32("betas", &[1, 10], &ramp(10)));
    arrays
}

fn builtin_sequence(rig: &Rig) -> Vec<Array> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.npz");
    let mut frames = vec![rig.zero_params(), rig.zero_params()];
    frames[1].pose.iter_mut().for_each(|p| *p = 0.1);
    sequence::write(&path, rig, &frames).unwrap();
    f3g_testkit::read_arrays(&path)
}

fn well_formed(frames: &[RigParams], rig: &Rig) -> bool {
    frames.iter().all(|f| {
        f.pose.len() == rig.num_pose_params()
            && f.identity.len() == rig.identity.len()
            && f.expression.len() == rig.expression.len()
            && f.pose.iter().chain(&f.identity).all(|v| v.is_finite())
    })
}

/// The fuzzer's find in the `gltf` crate: a primitive whose POSITION accessor does not exist
/// panics inside its validation (gltf-json 1.4.1); it must be an error naming the file.
#[test]
fn a_missing_position_accessor_is_an_error() {
    // Accessor 1 becomes 9 (there are 6), in place, so the GLB chunk sizes stay right.
    let key = b"\"POSITION\":1";
    let at = GLB.windows(key.len()).position(|w| w == key).unwrap();
    let mut bytes = GLB.to_vec();
    bytes[at + key.len() - 1] = b'9';
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.glb");
    std::fs::write(&path, &bytes).unwrap();
    let e = gltf::load(&path, None).err().unwrap().to_string();
    assert!(e.contains("c.glb") && e.contains("not a valid glTF"), "{e}");
}

/// `GLB` with its JSON chunk edited by `edit` (chunk and file lengths rewritten).
fn edited_glb(edit: impl FnOnce(&mut serde_json::Value)) -> Vec<u8> {
    let u32_at = |at: usize| u32::from_le_bytes(GLB[at..at + 4].try_into().unwrap()) as usize;
    let json_len = u32_at(12);
    let mut json: serde_json::Value = serde_json::from_slice(&GLB[20..20 + json_len]).unwrap();
    edit(&mut json);
    let mut text = serde_json::to_vec(&json).unwrap();
    while !text.len().is_multiple_of(4) {
        text.push(b' ');
    }
    let rest = &GLB[20 + json_len..];
    let mut out = GLB[..12].to_vec();
    out.extend((text.len() as u32).to_le_bytes());
    out.extend(&GLB[16..20]);
    out.extend(&text);
    out.extend(rest);
    let total = out.len() as u32;
    out[8..12].copy_from_slice(&total.to_le_bytes());
    out
}

/// A sparse accessor without a buffer view may set any `count`: the reader would produce that
/// many elements. 4·10⁹ positions must be refused before reading, naming the accessor.
#[test]
fn an_absurd_accessor_count_is_refused_before_reading() {
    let bytes = edited_glb(|json| {
        let position = &mut json["accessors"][1];
        position.as_object_mut().unwrap().remove("bufferView");
        position["count"] = serde_json::json!(4_000_000_000u64);
        position["sparse"] = serde_json::json!({
            "count": 1,
            "indices": {"bufferView": 0, "componentType": 5125},
            "values": {"bufferView": 1}
        });
    });
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.glb");
    std::fs::write(&path, &bytes).unwrap();
    let e = gltf::load(&path, None).err().unwrap().to_string();
    assert!(
        e.contains("c.glb") && e.contains("POSITION of primitive 0") && e.contains("4000000000"),
        "{e}"
    );
    // The same file with its real count loads: the edit is what is refused.
    let bytes = edited_glb(|_| {});
    std::fs::write(&path, &bytes).unwrap();
    gltf::load(&path, None).unwrap();
}

#[test]
fn the_valid_model_and_parameter_seeds_read() {
    let rig = glb_rig();
    parse_model(MODEL, &rig.skeleton, Path::new("c.model")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("smpl_params.npz");
    write_arrays(&path, &smpl_params());
    let p = smplx::read_params(&path).unwrap();
    assert_eq!((p.frames, p.num_expression()), (2, 10));
    // The fuzzer's find: `betas` of shape (0, B) indexed an empty array (a panic).
    let mut no_betas = smpl_params();
    *no_betas.last_mut().unwrap() = Array::f32("betas", &[0, 10], &[]);
    write_arrays(&path, &no_betas);
    let e = smplx::read_params(&path).unwrap_err().to_string();
    assert!(e.contains("smpl_params.npz") && e.contains("betas"), "{e}");
    let builtin = ModelSpec::Builtin.load().unwrap();
    let path = dir.path().join("s.npz");
    write_arrays(&path, &builtin_sequence(&builtin));
    assert_eq!(sequence::read(&path, &builtin).unwrap().len(), 2);
}

proptest! {
    #![proptest_config(config(1000))]

    #[test]
    fn mutated_glb_loads_or_errors(bytes in mutated(GLB.to_vec())) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.glb");
        std::fs::write(&path, &bytes).unwrap();
        match gltf::load(&path, None) {
            Ok(rig) => check_rig(&rig)?,
            Err(e) => prop_assert!(e.to_string().contains("c.glb"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }

    #[test]
    fn mutated_model_files_parse_or_error(text in mutated_text(MODEL)) {
        static SKELETON: std::sync::LazyLock<f3g_rig::Skeleton> =
            std::sync::LazyLock::new(|| glb_rig().skeleton);
        if let Err(e) = parse_model(&text, &SKELETON, Path::new("c.model")) {
            prop_assert!(e.to_string().contains("c.model"), "{}", e);
        }
    }

    #[test]
    fn mutated_smpl_params_read_or_error(arrays in mutated_arrays(smpl_params())) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("smpl_params.npz");
        write_arrays(&path, &arrays);
        match smplx::read_params(&path) {
            Ok(p) => {
                for i in 0..p.frames {
                    prop_assert_eq!(p.pose(i).len(), 3 + 63 + 9 + 90 + 3);
                }
                prop_assert!(p.betas.iter().chain(&p.transl).all(|v| v.is_finite()));
            }
            Err(e) => prop_assert!(e.to_string().contains("smpl_params.npz"), "{}", e),
        }
    }

    #[test]
    fn mutated_sequences_read_or_error(arrays in mutated_arrays(builtin_sequence(&BUILTIN))) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.npz");
        write_arrays(&path, &arrays);
        match sequence::read(&path, &BUILTIN) {
            Ok(frames) => prop_assert!(well_formed(&frames, &BUILTIN)),
            Err(e) => prop_assert!(e.to_string().contains("s.npz"), "{}", e),
        }
    }
}

static BUILTIN: std::sync::LazyLock<Rig> =
    std::sync::LazyLock::new(|| ModelSpec::Builtin.load().unwrap());

/// A small rig file: the glTF fixture's rig (Momentum parameters, inverse bind matrices), as
/// arrays.
fn rig_file() -> Vec<f3g_testkit::Array> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rig.npz");
    f3g_rig::file::write(&glb_rig(), &path).unwrap();
    f3g_testkit::read_arrays(&path)
}

proptest! {
    #![proptest_config(config(1000))]

    /// A run's `body_model.npz`: every mutation reads to a rig that validates and poses, or
    /// is an error naming the file.
    #[test]
    fn mutated_rig_files_read_or_error(arrays in mutated_arrays(rig_file())) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rig.npz");
        write_arrays(&path, &arrays);
        match f3g_rig::file::read(&path) {
            Ok(rig) => {
                prop_assert!(rig.validate().is_ok());
                prop_assert!(rig.pose(&rig.zero_params()).is_ok());
            }
            Err(e) => prop_assert!(e.to_string().contains("rig.npz"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }
}

proptest! {
    #![proptest_config(config(3000))]

    #[test]
    fn mutated_obj_parses_or_errors(text in mutated_text(OBJ)) {
        if let Ok(mesh) = parse_obj(&text, Path::new("g.obj")) {
            let n = mesh.vertices.len() as u32;
            prop_assert!(mesh.triangles.iter().flatten().all(|&i| i < n));
            prop_assert!(mesh.vertices.iter().all(|v| v.is_finite()));
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }
}
