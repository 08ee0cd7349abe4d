//! Fuzzing the template reader (`template.npz`, written by `f3g template` and read by every
//! later stage): for mutations of a valid file's arrays (dropped, renamed, reshaped, retyped,
//! poisoned with NaN or out-of-range indices), loading returns a consistent template or an
//! error naming the file — no panic, no single allocation above 256 MiB.

use f3g_rig::ModelSpec;
use f3g_template::TransferOptions;
use f3g_template::canonical::CanonicalPose;
use f3g_template::template::{LABEL_BODY, LABEL_GARMENT, Template};
use f3g_testkit::{AllocationGuard, Array, config, mutated_arrays, read_arrays, write_arrays};
use proptest::prelude::*;

#[global_allocator]
static GUARD: AllocationGuard = AllocationGuard::new(256 << 20);

/// The built-in human's template with the built-in skirt, as arrays.
static SEED: std::sync::LazyLock<Vec<Array>> = std::sync::LazyLock::new(|| {
    let model = ModelSpec::Builtin;
    let skirt = f3g_template::template::builtin_skirt(&CanonicalPose::default()).unwrap();
    let (t, _) = Template::build(
        &model.load().unwrap(),
        &CanonicalPose::default(),
        None,
        Some((skirt, std::path::Path::new("builtin:skirt"))),
        &TransferOptions::default(),
    )
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("template.npz");
    t.save(&path, &model.load().unwrap()).unwrap();
    read_arrays(&path)
});

fn consistent(t: &Template) -> bool {
    let v = t.mesh.vertices.len();
    t.skin.len() == v
        && t.vertex_label.len() == v
        && t.body_vertex.len() == v
        && t.vertex_label
            .iter()
            .all(|&l| l == LABEL_BODY || l == LABEL_GARMENT)
        && t.mesh.vertices.iter().all(|p| p.is_finite())
        && t.mesh.triangles.iter().flatten().all(|&i| (i as usize) < v)
        && t.canonical
            .pose
            .iter()
            .chain(&t.canonical.identity)
            .all(|x| x.is_finite())
        && t.canonical.expression.iter().all(|x| x.is_finite())
}

#[test]
fn the_valid_seed_loads() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("template.npz");
    write_arrays(&path, &SEED);
    let (t, _) = Template::load(&path).unwrap();
    assert!(consistent(&t));
    assert!(t.vertex_label.contains(&LABEL_GARMENT));
}

proptest! {
    #![proptest_config(config(300))]

    #[test]
    fn mutated_templates_load_or_error(arrays in mutated_arrays(SEED.clone())) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("template.npz");
        write_arrays(&path, &arrays);
        match Template::load(&path) {
            Ok((t, _)) => prop_assert!(consistent(&t), "an inconsistent template loaded"),
            Err(e) => prop_assert!(e.to_string().contains("template.npz"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }
}
