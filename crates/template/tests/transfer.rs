//! Robust skin-weight transfer on the built-in human.

use f3g_rig::{Mesh, ModelSpec};
use f3g_template::canonical::CanonicalPose;
use f3g_template::mesh::{SurfaceQuery, clean};
use f3g_template::template::submesh;
use f3g_template::{TransferOptions, transfer_weights};
use glam::Vec3;

struct Body {
    mesh: Mesh,
    skin: f3g_rig::SkinWeights,
    joints: usize,
}

fn canonical_body() -> Body {
    let model = ModelSpec::Builtin;
    let rig = model.load().unwrap();
    let params = rig.canonical_params(&CanonicalPose::default()).unwrap();
    let posed = rig.pose(&params).unwrap();
    let (mesh, kept) = submesh(
        &Mesh {
            vertices: posed.vertices,
            triangles: rig.mesh.triangles.clone(),
        },
        &rig.surface,
    );
    Body {
        mesh,
        skin: rig.skin.select(&kept),
        joints: rig.skeleton.len(),
    }
}

#[test]
fn the_body_itself_gets_its_own_weights() {
    let b = canonical_body();
    let t = transfer_weights(
        &b.mesh,
        &b.skin,
        b.joints,
        &b.mesh,
        &TransferOptions::default(),
    )
    .unwrap();
    assert!(t.matched.iter().all(|m| *m));
    let (got, want) = (t.skin.to_dense(b.joints), b.skin.to_dense(b.joints));
    let worst = got
        .iter()
        .zip(&want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(worst < 1e-4, "largest weight difference {worst}");
}

#[test]
fn an_offset_garment_inherits_nearby_weights_and_inpaints_the_rest_smoothly() {
    let b = canonical_body();
    // A garment: the torso and thighs of the body, pushed out along the normals by an amount
    // growing downwards (tight at the chest, loose at the hem) like a dress.
    let normals = f3g_rig::vertex_normals(&b.mesh.vertices, &b.mesh.triangles);
    let keep: Vec<bool> = b
        .mesh
        .vertices
        .iter()
        .map(|v| v.y > -0.45 && v.y < 0.45 && v.x.abs() < 0.22)
        .collect();
    let (mut garment, kept) = submesh(&b.mesh, &keep);
    for (v, &k) in garment.vertices.iter_mut().zip(&kept) {
        let loose = ((0.2 - v.y) / 0.65).clamp(0.0, 1.0);
        *v += normals[k] * (0.005 + 0.25 * loose * loose);
    }
    clean(&mut garment, std::path::Path::new("garment")).unwrap();
    let options = TransferOptions::default();
    let t = transfer_weights(&b.mesh, &b.skin, b.joints, &garment, &options).unwrap();
    let matched = t.matched.iter().filter(|m| **m).count();
    let inpainted = t.matched.len() - matched - t.fallback;
    assert!(
        matched > 200 && inpainted > 200,
        "matched {matched}, inpainted {inpainted}"
    );

    let query = SurfaceQuery::new(&b.mesh).unwrap();
    let dense = t.skin.to_dense(b.joints);
    let row = |v: usize| &dense[v * b.joints..(v + 1) * b.joints];
    for (v, &m) in t.matched.iter().enumerate() {
        let w = row(v);
        assert!(
            w.iter().all(|x| *x >= 0.0) && (w.iter().sum::<f32>() - 1.0).abs() < 1e-4,
            "vertex {v}"
        );
        if m {
            // Matched vertices carry the closest body point's weights.
            let hit = query.closest(garment.vertices[v]);
            let tri = b.mesh.triangles[hit.triangle as usize];
            let expected = b.skin.mix(&[
                (tri[0] as usize, hit.bary[0]),
                (tri[1] as usize, hit.bary[1]),
                (tri[2] as usize, hit.bary[2]),
            ]);
            for (j, x) in expected {
                if x > 0.02 {
                    assert!(
                        (w[j] - x).abs() < 0.02,
                        "vertex {v} joint {j}: {} vs {x}",
                        w[j]
                    );
                }
            }
        }
    }
    // Inpainted weights are smooth: over the edges touching inpainted vertices, their
    // Dirichlet energy is far below that of the raw closest-point weights, and inside the
    // inpainted region a vertex differs little from the mean of its neighbours.
    let closest: Vec<f32> = garment
        .vertices
        .iter()
        .flat_map(|&p| {
            let hit = query.closest(p);
            let tri = b.mesh.triangles[hit.triangle as usize];
            let mut w = vec![0.0f32; b.joints];
            for (j, x) in b.skin.mix(&[
                (tri[0] as usize, hit.bary[0]),
                (tri[1] as usize, hit.bary[1]),
                (tri[2] as usize, hit.bary[2]),
            ]) {
                w[j] += x;
            }
            w
        })
        .collect();
    let mut neighbours = vec![std::collections::BTreeSet::new(); garment.vertices.len()];
    for tri in &garment.triangles {
        for k in 0..3 {
            neighbours[tri[k] as usize].insert(tri[(k + 1) % 3] as usize);
            neighbours[tri[(k + 1) % 3] as usize].insert(tri[k] as usize);
        }
    }
    let energy = |w: &[f32]| -> f32 {
        let mut e = 0.0;
        for (v, n) in neighbours.iter().enumerate() {
            for &u in n {
                if u > v && (!t.matched[v] || !t.matched[u]) {
                    e += (0..b.joints)
                        .map(|j| (w[v * b.joints + j] - w[u * b.joints + j]).powi(2))
                        .sum::<f32>();
                }
            }
        }
        e
    };
    let (e_inpainted, e_closest) = (energy(&dense), energy(&closest));
    assert!(
        e_inpainted < 0.5 * e_closest,
        "energy {e_inpainted} vs closest-point {e_closest}"
    );
    let mut worst = 0.0f32;
    for (v, n) in neighbours.iter().enumerate() {
        if t.matched[v] || n.is_empty() || n.iter().any(|&u| t.matched[u]) {
            continue;
        }
        let mean: Vec<f32> = (0..b.joints)
            .map(|j| n.iter().map(|&u| row(u)[j]).sum::<f32>() / n.len() as f32)
            .collect();
        worst = worst.max(row(v).iter().zip(&mean).map(|(a, m)| (a - m).abs()).sum());
    }
    assert!(
        worst < 0.25,
        "an interior inpainted vertex differs from its neighbours by {worst} (L1)"
    );
}

#[test]
fn a_mesh_far_from_the_body_is_rejected() {
    let b = canonical_body();
    let far = Mesh {
        vertices: b
            .mesh
            .vertices
            .iter()
            .map(|v| *v + Vec3::new(3.0, 0.0, 0.0))
            .collect(),
        triangles: b.mesh.triangles.clone(),
    };
    let e = transfer_weights(
        &b.mesh,
        &b.skin,
        b.joints,
        &far,
        &TransferOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("aligned with the canonical body"), "{e}");
}
