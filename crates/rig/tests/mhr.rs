//! MHR loading from an asset folder: a small character is authored here, written in the MHR
//! formats (ASCII FBX in centimetres, `.model`, corrective `.npz` files), loaded, and posed; the
//! result must equal an independent evaluation of the authored data (FK with FBX Euler XYZ,
//! LBS, blend shapes, the corrective MLP). The official assets cannot be downloaded here; this
//! checks every piece of the loader against what the formats specify. The same folder seeds
//! the loader's fuzz tests (mutated FBX, `.model` and corrective files).
// The reference evaluation indexes matrices the way the formulas are written.
#![allow(clippy::needless_range_loop)]

use std::fmt::Write;
use std::path::Path;

use f3g_io::NpyValues::{F32, I64};
use f3g_rig::mhr;
use f3g_testkit::{
    AllocationGuard, config, mutated_arrays, mutated_text, read_arrays, write_arrays,
};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[global_allocator]
static GUARD: AllocationGuard = AllocationGuard::new(256 << 20);

type M4 = [[f64; 4]; 4];

fn mul(a: &M4, b: &M4) -> M4 {
    let mut c = [[0.0; 4]; 4];
    for i in 0..4 {
        for j in 0..4 {
            c[i][j] = (0..4).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    c
}

fn rot(axis: usize, a: f64) -> M4 {
    let (s, c) = a.sin_cos();
    let mut m = [[0.0; 4]; 4];
    m[3][3] = 1.0;
    let (i, j) = [(1, 2), (2, 0), (0, 1)][axis];
    m[axis][axis] = 1.0;
    m[i][i] = c;
    m[j][j] = c;
    m[i][j] = -s;
    m[j][i] = s;
    m
}

/// `Rz · Ry · Rx` (FBX eEulerXYZ and Momentum's order), radians.
fn euler(x: f64, y: f64, z: f64) -> M4 {
    mul(&mul(&rot(2, z), &rot(1, y)), &rot(0, x))
}

fn translation(t: [f64; 3], s: f64) -> M4 {
    let mut m = [[0.0; 4]; 4];
    for i in 0..3 {
        m[i][i] = s;
        m[i][3] = t[i];
    }
    m[3][3] = 1.0;
    m
}

fn inverse_rigid(m: &M4) -> M4 {
    let mut r = [[0.0; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            r[i][j] = m[j][i];
        }
        r[i][3] = -(0..3).map(|k| m[k][i] * m[k][3]).sum::<f64>();
    }
    r[3][3] = 1.0;
    r
}

fn apply(m: &M4, p: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| (0..3).map(|k| m[i][k] * p[k]).sum::<f64>() + m[i][3])
}

struct Bone {
    name: &'static str,
    parent: Option<usize>,
    offset_cm: [f64; 3],
    rotation_deg: [f64; 3],
}

const BONES: [Bone; 5] = [
    Bone {
        name: "root",
        parent: None,
        offset_cm: [0.0, 100.0, 0.0],
        rotation_deg: [10.0, 20.0, 30.0],
    },
    Bone {
        name: "spine",
        parent: Some(0),
        offset_cm: [0.0, 20.0, 0.0],
        rotation_deg: [5.0, -10.0, 15.0],
    },
    Bone {
        name: "l",
        parent: Some(1),
        offset_cm: [15.0, 5.0, 0.0],
        rotation_deg: [0.0, 0.0, -40.0],
    },
    Bone {
        name: "r",
        parent: Some(1),
        offset_cm: [-15.0, 5.0, 0.0],
        rotation_deg: [0.0, 0.0, 40.0],
    },
    Bone {
        name: "head",
        parent: Some(1),
        offset_cm: [0.0, 25.0, 3.0],
        rotation_deg: [-5.0, 0.0, 0.0],
    },
];
const V: usize = 12;
const SHAPES: usize = 47;
const HIDDEN: usize = 6;
const MODEL: &str = "Momentum Model Definition V1.0\n[ParameterTransform]\nroot.tx = 1.0*root_tx\nroot.ty = 1.0*root_ty\nroot.rx = 1.0*root_rx\nroot.ry = 1.0*root_ry\nspine.rz = 1.0*spine_rz\nl.rz = 1.0*l_rz\nl.ry = 0.5*l_rz + 1.0*l_ry\nr.rz = -1.0*l.rz + 1.0*r_rz\nhead.rx = 1.0*head_rx\nhead.sc = 1.0*head_scale\n";

struct Authored {
    vertices_cm: Vec<[f64; 3]>,
    triangles: Vec<[usize; 3]>,
    weights: Vec<Vec<(usize, f64)>>,
    shapes_cm: Vec<Vec<(usize, [f64; 3])>>,
    sparse: Vec<(usize, usize, f64)>,
    dense_cm: Vec<f64>,
}

fn author(seed: u64) -> Authored {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let rest = bind_pose();
    let vertices_cm = (0..V)
        .map(|i| {
            let c = rest[i % BONES.len()];
            [
                c[0][3] + rng.random_range(-8.0..8.0),
                c[1][3] + rng.random_range(-8.0..8.0),
                c[2][3] + rng.random_range(-8.0..8.0),
            ]
        })
        .collect();
    let triangles = (0..V - 2).map(|i| [i, i + 1, i + 2]).collect();
    let weights = (0..V)
        .map(|i| {
            let a = i % BONES.len();
            let b = (i + 1) % BONES.len();
            let w = rng.random_range(0.2..0.8);
            vec![(a, w), (b, 1.0 - w)]
        })
        .collect();
    let shapes_cm = (0..SHAPES)
        .map(|s| {
            vec![
                (
                    s % V,
                    [
                        rng.random_range(-2.0..2.0),
                        rng.random_range(-2.0..2.0),
                        rng.random_range(-2.0..2.0),
                    ],
                ),
                ((s * 5 + 3) % V, [0.5, -1.0, 0.25]),
            ]
        })
        .collect();
    let features = 6 * (BONES.len() - 2);
    let sparse = (0..20)
        .map(|_| {
            (
                rng.random_range(0..HIDDEN),
                rng.random_range(0..features),
                rng.random_range(-3.0..3.0),
            )
        })
        .collect();
    let dense_cm = (0..HIDDEN * V * 3)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    Authored {
        vertices_cm,
        triangles,
        weights,
        shapes_cm,
        sparse,
        dense_cm,
    }
}

/// World transforms of the bones at the bind (rest) pose, centimetres.
fn bind_pose() -> Vec<M4> {
    let mut world: Vec<M4> = Vec::new();
    for b in &BONES {
        let [x, y, z] = b.rotation_deg.map(f64::to_radians);
        let local = mul(&translation(b.offset_cm, 1.0), &euler(x, y, z));
        world.push(b.parent.map_or(local, |p| mul(&world[p], &local)));
    }
    world
}

fn fbx_matrix(m: &M4) -> String {
    // FBX stores 4×4 matrices column by column.
    (0..4)
        .flat_map(|c| (0..4).map(move |r| m[r][c]))
        .map(|v| format!("{v:.12}"))
        .collect::<Vec<_>>()
        .join(",")
}

fn list(values: impl IntoIterator<Item = String>) -> String {
    let v: Vec<String> = values.into_iter().collect();
    format!("*{} {{\n\t\t\ta: {}\n\t\t}}", v.len(), v.join(","))
}

fn write_fbx(path: &Path, a: &Authored) {
    let mut f = String::new();
    writeln!(f, "; FBX 7.4.0 project file\nFBXHeaderExtension:  {{\n\tFBXHeaderVersion: 1003\n\tFBXVersion: 7400\n}}").unwrap();
    writeln!(f, "GlobalSettings:  {{\n\tVersion: 1000\n\tProperties70:  {{\n\t\tP: \"UpAxis\", \"int\", \"Integer\", \"\",1\n\t\tP: \"UpAxisSign\", \"int\", \"Integer\", \"\",1\n\t\tP: \"FrontAxis\", \"int\", \"Integer\", \"\",2\n\t\tP: \"FrontAxisSign\", \"int\", \"Integer\", \"\",1\n\t\tP: \"CoordAxis\", \"int\", \"Integer\", \"\",0\n\t\tP: \"CoordAxisSign\", \"int\", \"Integer\", \"\",1\n\t\tP: \"UnitScaleFactor\", \"double\", \"Number\", \"\",1\n\t}}\n}}").unwrap();
    writeln!(f, "Objects:  {{").unwrap();
    let mut connections = Vec::new();
    // Geometry and its model.
    let verts = a
        .vertices_cm
        .iter()
        .flat_map(|v| v.map(|x| format!("{x:.9}")));
    let polys = a.triangles.iter().flat_map(|t| {
        [
            t[0].to_string(),
            t[1].to_string(),
            (-(t[2] as i64) - 1).to_string(),
        ]
    });
    writeln!(f, "\tGeometry: 100, \"Geometry::body\", \"Mesh\" {{\n\t\tVertices: {}\n\t\tPolygonVertexIndex: {}\n\t\tGeometryVersion: 124\n\t}}", list(verts), list(polys)).unwrap();
    writeln!(
        f,
        "\tModel: 200, \"Model::body\", \"Mesh\" {{\n\t\tVersion: 232\n\t}}"
    )
    .unwrap();
    connections.push((200, 0));
    connections.push((100, 200));
    // Bones.
    for (i, b) in BONES.iter().enumerate() {
        let id = 1000 + i;
        writeln!(
            f,
            "\tModel: {id}, \"Model::{}\", \"LimbNode\" {{\n\t\tVersion: 232\n\t\tProperties70:  {{\n\t\t\tP: \"Lcl Translation\", \"Lcl Translation\", \"\", \"A\",{},{},{}\n\t\t\tP: \"Lcl Rotation\", \"Lcl Rotation\", \"\", \"A\",{},{},{}\n\t\t}}\n\t}}",
            b.name, b.offset_cm[0], b.offset_cm[1], b.offset_cm[2], b.rotation_deg[0], b.rotation_deg[1], b.rotation_deg[2]
        )
        .unwrap();
        writeln!(f, "\tNodeAttribute: {}, \"NodeAttribute::{}\", \"LimbNode\" {{\n\t\tTypeFlags: \"Skeleton\"\n\t}}", 1500 + i, b.name).unwrap();
        connections.push((1500 + i, id));
        connections.push((id, b.parent.map_or(0, |p| 1000 + p)));
    }
    // Skin and clusters.
    writeln!(
        f,
        "\tDeformer: 300, \"Deformer::skin\", \"Skin\" {{\n\t\tVersion: 101\n\t}}"
    )
    .unwrap();
    connections.push((300, 100));
    let bind = bind_pose();
    for (j, world) in bind.iter().enumerate() {
        let members: Vec<(usize, f64)> = a
            .weights
            .iter()
            .enumerate()
            .flat_map(|(v, ws)| {
                ws.iter()
                    .filter(|(b, _)| *b == j)
                    .map(move |(_, w)| (v, *w))
            })
            .collect();
        writeln!(
            f,
            "\tDeformer: {}, \"SubDeformer::cluster_{j}\", \"Cluster\" {{\n\t\tVersion: 100\n\t\tIndexes: {}\n\t\tWeights: {}\n\t\tTransform: {}\n\t\tTransformLink: {}\n\t}}",
            400 + j,
            list(members.iter().map(|m| m.0.to_string())),
            list(members.iter().map(|m| format!("{:.12}", m.1))),
            list([fbx_matrix(&inverse_rigid(world))]),
            list([fbx_matrix(world)]),
        )
        .unwrap();
        connections.push((400 + j, 300));
        connections.push((1000 + j, 400 + j));
    }
    // Blend shapes.
    writeln!(
        f,
        "\tDeformer: 500, \"Deformer::shapes\", \"BlendShape\" {{\n\t\tVersion: 100\n\t}}"
    )
    .unwrap();
    connections.push((500, 100));
    for (s, offsets) in a.shapes_cm.iter().enumerate() {
        writeln!(f, "\tDeformer: {}, \"SubDeformer::shape{s}\", \"BlendShapeChannel\" {{\n\t\tVersion: 100\n\t\tDeformPercent: 0\n\t\tFullWeights: *1 {{\n\t\t\ta: 100\n\t\t}}\n\t}}", 600 + s).unwrap();
        writeln!(
            f,
            "\tGeometry: {}, \"Geometry::shape{s}\", \"Shape\" {{\n\t\tVersion: 100\n\t\tIndexes: {}\n\t\tVertices: {}\n\t}}",
            700 + s,
            list(offsets.iter().map(|o| o.0.to_string())),
            list(offsets.iter().flat_map(|o| o.1.map(|x| format!("{x:.9}"))))
        )
        .unwrap();
        connections.push((600 + s, 500));
        connections.push((700 + s, 600 + s));
    }
    writeln!(f, "}}\nConnections:  {{").unwrap();
    for (child, parent) in connections {
        writeln!(f, "\tC: \"OO\",{child},{parent}").unwrap();
    }
    writeln!(f, "}}").unwrap();
    std::fs::write(path, f).unwrap();
}

fn write_assets(dir: &Path, a: &Authored) {
    write_fbx(&dir.join("lod1.fbx"), a);
    std::fs::write(dir.join(mhr::MODEL_FILE), MODEL).unwrap();
    let k = a.sparse.len();
    let indices: Vec<i64> = a
        .sparse
        .iter()
        .map(|s| s.0 as i64)
        .chain(a.sparse.iter().map(|s| s.1 as i64))
        .collect();
    let weights: Vec<f32> = a.sparse.iter().map(|s| s.2 as f32).collect();
    f3g_io::write_npz(
        &dir.join("corrective_activation.npz"),
        &[
            ("0.sparse_indices", &[2, k], I64(&indices)),
            ("0.sparse_weight", &[k], F32(&weights)),
        ],
    )
    .unwrap();
    let dense: Vec<f32> = a.dense_cm.iter().map(|&v| v as f32).collect();
    f3g_io::write_npz(
        &dir.join("corrective_blendshapes_lod1.npz"),
        &[("corrective_blendshapes", &[HIDDEN, V, 3], F32(&dense))],
    )
    .unwrap();
}

/// The authored character evaluated directly, in metres.
fn expected(
    a: &Authored,
    names: &[String],
    pose: &[f32],
    identity: &[f32],
    expression: &[f32],
) -> Vec<[f64; 3]> {
    let p = |n: &str| {
        names
            .iter()
            .position(|x| x == n)
            .map_or(0.0, |i| pose[i] as f64)
    };
    // Joint parameters from the .model (translations in cm).
    let mut params = [[0.0f64; 7]; BONES.len()];
    params[0][0] = p("root_tx");
    params[0][1] = p("root_ty");
    params[0][3] = p("root_rx");
    params[0][4] = p("root_ry");
    params[1][5] = p("spine_rz");
    params[2][5] = p("l_rz");
    params[2][4] = 0.5 * p("l_rz") + p("l_ry");
    params[3][5] = -p("l_rz") + p("r_rz");
    params[4][3] = p("head_rx");
    params[4][6] = p("head_scale");
    let mut world: Vec<M4> = Vec::new();
    let mut pose_rotations = Vec::new();
    for (b, q) in BONES.iter().zip(&params) {
        let [x, y, z] = b.rotation_deg.map(f64::to_radians);
        let pose_rotation = euler(q[3], q[4], q[5]);
        let t = [
            b.offset_cm[0] + q[0],
            b.offset_cm[1] + q[1],
            b.offset_cm[2] + q[2],
        ];
        let local = mul(
            &mul(&mul(&translation(t, 1.0), &euler(x, y, z)), &pose_rotation),
            &translation([0.0; 3], q[6].exp2()),
        );
        world.push(b.parent.map_or(local, |p| mul(&world[p], &local)));
        pose_rotations.push(pose_rotation);
    }
    let bind = bind_pose();
    let skinning: Vec<M4> = world
        .iter()
        .zip(&bind)
        .map(|(w, b)| mul(w, &inverse_rigid(b)))
        .collect();
    // Correctives: 6-D features of bones 2.., sparse layer, ReLU, dense layer.
    let features: Vec<f64> = pose_rotations[2..]
        .iter()
        .flat_map(|r| {
            [
                r[0][0] - 1.0,
                r[1][0],
                r[2][0],
                r[0][1],
                r[1][1] - 1.0,
                r[2][1],
            ]
        })
        .collect();
    let mut hidden = [0.0f64; HIDDEN];
    for &(o, i, w) in &a.sparse {
        hidden[o] += w * features[i];
    }
    (0..V)
        .map(|v| {
            let mut rest = a.vertices_cm[v];
            for (s, offsets) in a.shapes_cm.iter().enumerate() {
                let c = if s < 45 {
                    identity[s]
                } else {
                    expression[s - 45]
                } as f64;
                for (vi, o) in offsets {
                    if *vi == v {
                        for k in 0..3 {
                            rest[k] += c * o[k];
                        }
                    }
                }
            }
            for (h, value) in hidden.iter().enumerate() {
                for k in 0..3 {
                    rest[k] += value.max(0.0) * a.dense_cm[(h * V + v) * 3 + k];
                }
            }
            let mut out = [0.0; 3];
            for &(j, w) in &a.weights[v] {
                let p = apply(&skinning[j], rest);
                for k in 0..3 {
                    out[k] += w * p[k];
                }
            }
            out.map(|x| x * 0.01)
        })
        .collect()
}

#[test]
fn loads_and_poses_like_the_authored_character() {
    let dir = tempfile::tempdir().unwrap();
    let a = author(3);
    write_assets(dir.path(), &a);
    let rig = mhr::load(dir.path(), 1).unwrap();
    // Written to a rig file and read back, it is the same model (every check below runs on
    // the copy: Momentum parameters, MLP correctives and inverse bind matrices survive).
    f3g_rig::file::write(&rig, &dir.path().join("rig.npz")).unwrap();
    let rig = f3g_rig::file::read(&dir.path().join("rig.npz")).unwrap();
    assert_eq!(rig.skeleton.len(), BONES.len());
    assert_eq!((rig.identity.len(), rig.expression.len()), (45, 2));
    let bind = bind_pose();
    for (j, rest) in rig.skeleton.rest(None).iter().enumerate() {
        for k in 0..3 {
            assert!(
                (rest.translation[k] as f64 - bind[j][k][3] * 0.01).abs() < 1e-6,
                "joint {j}"
            );
        }
    }
    let names = rig.pose_param_names();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for _ in 0..5 {
        let mut p = rig.zero_params();
        for (i, n) in names.iter().enumerate() {
            p.pose[i] = if n.ends_with("_tx") || n.ends_with("_ty") {
                rng.random_range(-5.0..5.0)
            } else {
                rng.random_range(-0.8..0.8)
            };
        }
        p.identity
            .iter_mut()
            .for_each(|c| *c = rng.random_range(-1.0..1.0));
        p.expression
            .iter_mut()
            .for_each(|c| *c = rng.random_range(-1.0..1.0));
        let posed = rig.pose(&p).unwrap();
        let want = expected(&a, &names, &p.pose, &p.identity, &p.expression);
        for (got, w) in posed.vertices.iter().zip(&want) {
            for k in 0..3 {
                assert!((got[k] as f64 - w[k]).abs() < 1e-5, "{got:?} vs {w:?}");
            }
        }
    }
}

#[test]
fn missing_and_bad_files_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let e = mhr::load(dir.path(), 1).unwrap_err().to_string();
    assert!(e.contains("lod1.fbx") && e.contains("missing"), "{e}");
    let a = author(4);
    write_assets(dir.path(), &a);
    std::fs::write(
        dir.path().join(mhr::MODEL_FILE),
        "Momentum Model Definition V1.0\n[ParameterTransform]\nknee.rx = 1.0*k\n",
    )
    .unwrap();
    let e = mhr::load(dir.path(), 1).unwrap_err().to_string();
    assert!(
        e.contains("compact_v6_1.model:3: unknown joint `knee`"),
        "{e}"
    );
    write_assets(dir.path(), &a);
    f3g_io::write_npz(
        &dir.path().join("corrective_blendshapes_lod1.npz"),
        &[(
            "corrective_blendshapes",
            &[HIDDEN, V + 1, 3],
            F32(&vec![0.0; HIDDEN * (V + 1) * 3]),
        )],
    )
    .unwrap();
    let e = mhr::load(dir.path(), 1).unwrap_err().to_string();
    assert!(e.contains("`corrective_blendshapes`"), "{e}");
    std::fs::write(dir.path().join("lod1.fbx"), b"not an fbx").unwrap();
    let e = mhr::load(dir.path(), 1).unwrap_err().to_string();
    assert!(
        e.contains("lod1.fbx") && e.contains("cannot read FBX"),
        "{e}"
    );
}

/// The authored asset folder's files, read back to seed the fuzz tests.
struct Seed {
    fbx: String,
    activation: Vec<f3g_testkit::Array>,
    blendshapes: Vec<f3g_testkit::Array>,
}

static SEED: std::sync::LazyLock<Seed> = std::sync::LazyLock::new(|| {
    let dir = tempfile::tempdir().unwrap();
    write_assets(dir.path(), &author(5));
    Seed {
        fbx: std::fs::read_to_string(dir.path().join("lod1.fbx")).unwrap(),
        activation: read_arrays(&dir.path().join("corrective_activation.npz")),
        blendshapes: read_arrays(&dir.path().join("corrective_blendshapes_lod1.npz")),
    }
});

/// Loads the folder after `edit` replaced one file: a rig that loads must be consistent and
/// pose at rest; an error must name a file of the folder.
fn load_edited(edit: impl FnOnce(&Path)) -> Result<(), TestCaseError> {
    let dir = tempfile::tempdir().unwrap();
    write_assets(dir.path(), &author(5));
    edit(dir.path());
    match mhr::load(dir.path(), 1) {
        Ok(rig) => {
            prop_assert!(rig.validate().is_ok());
            let _ = rig.pose(&rig.zero_params());
        }
        Err(e) => {
            let e = e.to_string();
            prop_assert!(
                ["lod1.fbx", ".model", "corrective_"]
                    .iter()
                    .any(|f| e.contains(f)),
                "{}",
                e
            );
        }
    }
    prop_assert!(GUARD.largest() <= 256 << 20);
    Ok(())
}

proptest! {
    #![proptest_config(config(300))]

    #[test]
    fn mutated_fbx_loads_or_errors(text in mutated_text(&SEED.fbx)) {
        load_edited(|dir| std::fs::write(dir.join("lod1.fbx"), &text).unwrap())?;
    }

    #[test]
    fn mutated_model_files_load_or_error(text in mutated_text(MODEL)) {
        load_edited(|dir| std::fs::write(dir.join(mhr::MODEL_FILE), &text).unwrap())?;
    }

    #[test]
    fn mutated_activations_load_or_error(arrays in mutated_arrays(SEED.activation.clone())) {
        load_edited(|dir| write_arrays(&dir.join("corrective_activation.npz"), &arrays))?;
    }

    #[test]
    fn mutated_corrective_shapes_load_or_error(arrays in mutated_arrays(SEED.blendshapes.clone())) {
        load_edited(|dir| write_arrays(&dir.join("corrective_blendshapes_lod1.npz"), &arrays))?;
    }
}
