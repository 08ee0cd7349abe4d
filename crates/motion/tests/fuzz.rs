//! Fuzzing the motion readers with damaged files: for thousands of mutations of a valid BVH,
//! glTF animation, ASCII FBX, AMASS `.npz` and `.smpl` each reader returns a motion whose values are finite or an error
//! naming the file — no panic, no single allocation above 256 MiB.

mod common;

use std::path::Path;

use f3g_testkit::{
    AllocationGuard, Array, config, mutated, mutated_arrays, mutated_text, write_arrays,
};
use proptest::prelude::*;

#[global_allocator]
static GUARD: AllocationGuard = AllocationGuard::new(256 << 20);

fn bvh() -> String {
    f3g_motion::write_bvh(&common::walk(1, 3)).unwrap()
}

fn check(
    result: Result<f3g_motion::Motion, f3g_motion::MotionError>,
    name: &str,
) -> Result<(), TestCaseError> {
    match result {
        Ok(m) => {
            prop_assert!(m.rotations.iter().all(|q| q.is_finite()));
            prop_assert!(m.root_translation.iter().all(|t| t.is_finite()));
            prop_assert_eq!(m.rotations.len(), m.frames() * m.skeleton.len());
            prop_assert!(m.fps > 0.0 && m.fps.is_finite());
        }
        Err(e) => prop_assert!(e.to_string().contains(name), "{}", e),
    }
    prop_assert!(GUARD.largest() <= 256 << 20);
    Ok(())
}

fn amass() -> Vec<Array> {
    let frames = 3;
    vec![
        Array::f32("poses", &[frames, 156], &vec![0.1; frames * 156]),
        Array::f32("trans", &[frames, 3], &vec![0.5; frames * 3]),
        Array::f32("betas", &[16], &[0.0; 16]),
        Array::f32("mocap_framerate", &[], &[60.0]),
    ]
}

fn smpl() -> Vec<Array> {
    let frames = 2;
    vec![
        Array::f32("frameRate", &[], &[30.0]),
        Array::f32("bodyTranslation", &[frames, 3], &vec![0.0; frames * 3]),
        Array::f32("bodyPose", &[frames, 22, 3], &vec![0.1; frames * 66]),
        Array::f32("headPose", &[frames, 3, 3], &vec![0.0; frames * 9]),
        Array::f32(
            "expressionParameters",
            &[frames, 10],
            &vec![0.0; frames * 10],
        ),
    ]
}

proptest! {
    #![proptest_config(config(1000))]

    #[test]
    fn mutated_bvh_parses_or_errors(text in mutated_text(&bvh())) {
        check(f3g_motion::parse_bvh(text.as_bytes(), Path::new("m.bvh")), "m.bvh")?;
    }

    #[test]
    fn mutated_gltf_reads_or_errors(bytes in mutated(f3g_motion::write_gltf(&common::walk(0, 3)))) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.glb");
        std::fs::write(&path, &bytes).unwrap();
        check(f3g_motion::read(&path), "m.glb")?;
    }

    #[test]
    fn mutated_fbx_parses_or_errors(text in mutated_text(&f3g_motion::write_fbx(&common::walk(2, 3)).unwrap())) {
        check(f3g_motion::parse_fbx(text.as_bytes(), Path::new("m.fbx")), "m.fbx")?;
    }

    #[test]
    fn mutated_amass_reads_or_errors(arrays in mutated_arrays(amass())) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.npz");
        write_arrays(&path, &arrays);
        check(f3g_motion::read(&path), "m.npz")?;
    }

    #[test]
    fn mutated_smpl_reads_or_errors(arrays in mutated_arrays(smpl())) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.smpl");
        write_arrays(&path, &arrays);
        check(f3g_motion::read(&path), "m.smpl")?;
    }
}
