//! `f3g template` and `f3g posmaps` end to end.

use std::process::Command;

fn f3g() -> Command {
    Command::new(env!("CARGO_BIN_EXE_f3g"))
}

#[test]
fn builds_a_clothed_template_and_draws_its_maps() {
    let dir = tempfile::tempdir().unwrap();
    let out = f3g()
        .args(["template", "--clothes", "builtin:skirt", "--out", "t.npz"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("inpainted"));
    std::fs::write(
        dir.path().join("p.json"),
        r#"{"pose": {"jaw_rx": 0.3, "upperarm01.L_rz": 0.5}}"#,
    )
    .unwrap();
    let out = f3g()
        .args([
            "posmaps",
            "--template",
            "t.npz",
            "--out",
            "maps",
            "--resolution",
            "64",
            "--params",
            "p.json",
        ])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for name in [
        "canonical.png",
        "normals.png",
        "mask.png",
        "head.png",
        "posed.png",
        "head_posed.png",
    ] {
        let img = f3g_io::read_rgb(&dir.path().join("maps").join(name)).unwrap();
        assert!(img.data.iter().any(|&v| v > 0.0), "{name} is blank");
    }
    let (w, h) = f3g_io::image_size(&dir.path().join("maps/canonical.png")).unwrap();
    assert_eq!((w, h), (128, 64));
    // Again without --params: the posed pictures of the first run go, the user's file stays.
    let maps = dir.path().join("maps");
    std::fs::write(maps.join("notes.txt"), b"mine").unwrap();
    let again = f3g()
        .args(["posmaps", "--template", "t.npz", "--out", "maps"])
        .args(["--resolution", "64"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        again.status.success(),
        "{}",
        String::from_utf8_lossy(&again.stderr)
    );
    assert!(!maps.join("posed.png").exists() && maps.join("canonical.png").exists());
    assert_eq!(std::fs::read(maps.join("notes.txt")).unwrap(), b"mine");
}

#[test]
fn bad_meshes_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("empty.obj"), "# nothing\n").unwrap();
    let out = f3g()
        .args(["template", "--clothes", "empty.obj", "--out", "t.npz"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("empty.obj"));
    std::fs::write(
        dir.path().join("far.obj"),
        "v 10 0 0\nv 11 0 0\nv 10 1 0\nf 1 2 3\n",
    )
    .unwrap();
    let out = f3g()
        .args(["template", "--clothes", "far.obj", "--out", "t.npz"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("aligned with the canonical body"));
    assert!(!dir.path().join("t.npz").exists());
    std::fs::write(dir.path().join("broken.npz"), b"PK not really").unwrap();
    let out = f3g()
        .args(["posmaps", "--template", "broken.npz", "--out", "m"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("broken.npz"));
}

#[test]
fn reconstructs_the_skirt_of_a_synthetic_capture() {
    use f3g_template::canonical::CanonicalPose;
    use f3g_template::mesh::SurfaceQuery;
    let dir = tempfile::tempdir().unwrap();
    let run = |args: &[&str]| {
        let out = f3g().args(args).current_dir(dir.path()).output().unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        out
    };
    run(&[
        "synth",
        "--out",
        "cap",
        "--frames",
        "2",
        "--resolution",
        "256",
    ]);
    run(&[
        "template",
        "reconstruct",
        "--data",
        "cap",
        "--frame",
        "0",
        "--out",
        "garment.obj",
        "--hull",
        "hull.obj",
        "--resolution",
        "96",
    ]);
    // The hull is closed around the body with outward normals (positive signed volume, a
    // person's worth of it) and projects inside the masks.
    let ds = f3g_data::Dataset::open(&dir.path().join("cap"), None).unwrap();
    let hull = f3g_rig::obj::read_obj(&dir.path().join("hull.obj")).unwrap();
    let volume: f32 = hull
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| hull.vertices[i as usize]);
            a.dot(b.cross(c)) / 6.0
        })
        .sum();
    assert!((0.03..0.15).contains(&volume), "hull volume {volume} m³");
    for c in 0..ds.cameras.len() {
        let mask = ds.mask(c, 0).unwrap();
        let cam = &ds.cameras[c].camera;
        let inside = hull
            .vertices
            .iter()
            .filter(|v| {
                cam.project([v.x as f64, v.y as f64, v.z as f64])
                    .is_some_and(|(uv, _)| {
                        let (x, y) = (uv[0] as usize, uv[1] as usize);
                        x < mask.width && y < mask.height && mask.data[y * mask.width + x] > 0.2
                    })
            })
            .count();
        assert!(
            inside * 100 >= 97 * hull.vertices.len(),
            "camera {c}: {inside} of {}",
            hull.vertices.len()
        );
    }
    // The garment lies on the true skirt, in the canonical pose with the capture's shape.
    let human = f3g_rig::builtin::load().unwrap();
    let mut canonical = human
        .rig
        .canonical_params(&CanonicalPose::default())
        .unwrap();
    canonical.identity = ds.params[0].identity.clone();
    let posed = human.rig.pose(&canonical).unwrap();
    let skirt_part = human.part("skirt").unwrap();
    let keep: Vec<bool> = human.vertex_part.iter().map(|p| *p == skirt_part).collect();
    let (skirt, _) = f3g_template::template::submesh(
        &f3g_rig::Mesh {
            vertices: posed.vertices,
            triangles: human.rig.mesh.triangles.clone(),
        },
        &keep,
    );
    let query = SurfaceQuery::new(&skirt).unwrap();
    let garment = f3g_rig::obj::read_obj(&dir.path().join("garment.obj")).unwrap();
    assert!(
        garment.triangles.len() > 100,
        "{} triangles",
        garment.triangles.len()
    );
    let close = garment
        .vertices
        .iter()
        .filter(|v| query.closest(**v).distance < 0.03)
        .count();
    assert!(
        close * 100 >= 80 * garment.vertices.len(),
        "{close} of {} garment vertices within 3 cm of the skirt",
        garment.vertices.len()
    );
    // It feeds the template builder.
    let out = run(&["template", "--clothes", "garment.obj", "--out", "t.npz"]);
    assert!(String::from_utf8_lossy(&out.stdout).contains("body + garment"));
}
