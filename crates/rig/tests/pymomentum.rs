//! The Momentum-style rig against pymomentum (golden data from `tools/pymomentum_golden.py`,
//! produced with pymomentum-cpu 0.1.114): characters saved by pymomentum as glTF + `.model`,
//! posed here with random model parameters, must match pymomentum's `skin_points` and skeleton
//! states.

use std::path::PathBuf;

use f3g_rig::gltf;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/pymomentum")
        .join(name)
}

#[test]
fn skinning_matches_pymomentum_on_random_parameters() {
    for name in ["char_a", "char_b"] {
        let rig = gltf::load(
            &data(&format!("{name}.glb")),
            Some(&data(&format!("{name}.model"))),
        )
        .unwrap();
        let mut golden = f3g_io::Npz::open(&data(&format!("{name}_golden.npz"))).unwrap();
        let names: Vec<u8> = golden
            .i64("parameter_names")
            .unwrap()
            .1
            .into_iter()
            .map(|b| b as u8)
            .collect();
        let names: Vec<String> = String::from_utf8(names)
            .unwrap()
            .lines()
            .map(String::from)
            .collect();
        assert_eq!(rig.pose_param_names(), names);
        let (shape, params) = golden.f32("params").unwrap();
        let (_, vertices) = golden.f32("vertices").unwrap();
        let (_, joints) = golden.f32("joint_positions").unwrap();
        let (cases, p) = (shape[0], shape[1]);
        let (v, j) = (vertices.len() / cases / 3, joints.len() / cases / 3);
        let mut worst = 0.0f32;
        for c in 0..cases {
            let mut rp = rig.zero_params();
            rp.pose = params[c * p..(c + 1) * p].to_vec();
            let posed = rig.pose(&rp).unwrap();
            for (k, joint) in posed.joints.iter().enumerate() {
                let want = glam::Vec3::from_slice(&joints[(c * j + k) * 3..]);
                worst = worst.max((joint.translation - want).abs().max_element());
            }
            for (k, got) in posed.vertices.iter().enumerate() {
                let want = glam::Vec3::from_slice(&vertices[(c * v + k) * 3..]);
                worst = worst.max((*got - want).abs().max_element());
            }
        }
        // Positions are ~1 m; float32 on both sides.
        assert!(worst < 2e-5, "{name}: largest difference {worst} m");
    }
}

#[test]
fn the_momentum_extension_carries_the_weights() {
    // Without the .model file, the FB_momentum extension gives the same parameters and
    // weights (it drops constant offsets, as Momentum itself does).
    let with_model = gltf::load(&data("char_a.glb"), Some(&data("char_a.model"))).unwrap();
    let from_extension = gltf::load(&data("char_a.glb"), None).unwrap();
    assert_eq!(
        from_extension.pose_param_names(),
        with_model.pose_param_names()
    );
    let (f3g_rig::Parameterization::Momentum(a), f3g_rig::Parameterization::Momentum(b)) = (
        &with_model.parameterization,
        &from_extension.parameterization,
    ) else {
        panic!("momentum parameterisations expected")
    };
    let mut wa: Vec<_> = a
        .entries
        .iter()
        .map(|e| (e.0, e.1, (e.2 * 1e5).round() as i64))
        .collect();
    let mut wb: Vec<_> = b
        .entries
        .iter()
        .map(|e| (e.0, e.1, (e.2 * 1e5).round() as i64))
        .collect();
    // The .model's joint reference expands to per-parameter terms, as the extension stores them.
    let merge = |w: &mut Vec<(u32, u32, i64)>| {
        w.sort();
        w.dedup_by(|x, y| {
            if x.0 == y.0 && x.1 == y.1 {
                y.2 += x.2;
                true
            } else {
                false
            }
        });
    };
    merge(&mut wa);
    merge(&mut wb);
    assert_eq!(wa, wb);
}
