//! Fuzzing the OBJ reader (garments and meshes from other tools): for thousands of mutations
//! of a valid file, parsing returns a mesh whose faces index its vertices, or an error naming
//! the file and line — no panic, no single allocation above 256 MiB.

use std::path::Path;

use f3g_rig::obj::parse_obj;
use f3g_testkit::{AllocationGuard, config, mutated_text};
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
