//! Fuzzing the motion readers with damaged files: for thousands of mutations of a valid BVH,
//! glTF animation, ASCII FBX, AMASS `.npz` and `.smpl` each reader returns a motion whose values are finite or an error
//! naming the file — no panic, no single allocation above 256 MiB. Besides byte-level
//! mutations, structure-aware edits reach the fields a reader must check before trusting
//! them: a glTF animation's channel targets, samplers, accessors, strides and key times, and
//! an FBX file's key values and times.

mod common;

use std::path::Path;

use f3g_testkit::{
    AllocationGuard, Array, config, mutated, mutated_arrays, mutated_text, write_arrays,
};
use proptest::prelude::*;
use serde_json::Value;

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
            let within = |t: &glam::Vec3| {
                t.length() * m.metres_per_unit <= f3g_motion::MAX_TRANSLATION_METRES
            };
            prop_assert!(m.root_translation.iter().all(within));
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

/// One edit of a glTF animation's document or buffer; indices are taken modulo the number of
/// channels, samplers, accessors, views or floats, values are picked to be wrong.
#[derive(Clone, Debug)]
enum GltfEdit {
    /// A channel's `target.node`.
    Node(usize, u64),
    /// A channel's `target.path`.
    Path(usize, &'static str),
    /// A channel's `sampler`.
    Sampler(usize, u64),
    /// A sampler's `input` (true) or `output` accessor.
    Accessor(usize, bool, u64),
    /// A sampler's `interpolation`.
    Interpolation(usize, &'static str),
    /// An accessor's `count`.
    Count(usize, u64),
    /// An accessor's `componentType`.
    ComponentType(usize, u64),
    /// An accessor's `type`.
    Type(usize, &'static str),
    /// An accessor's `normalized`.
    Normalized(usize, bool),
    /// A buffer view's `byteStride`.
    Stride(usize, u64),
    /// A key time of the shared time accessor.
    Time(usize, f32),
    /// A float of the buffer (rotations, translations, matrices).
    Float(usize, f32),
}

/// Floats a reader must doubt: non-finite, huge, negative, zero, and any.
fn bad_float() -> impl Strategy<Value = f32> {
    prop_oneof![
        Just(f32::NAN),
        Just(f32::INFINITY),
        Just(-1e30f32),
        Just(1e30f32),
        Just(0.0f32),
        -2.0f32..2.0,
        any::<f32>(),
    ]
}

fn gltf_edit() -> impl Strategy<Value = GltfEdit> {
    let index = || prop_oneof![0u64..30, Just(u32::MAX as u64), Just(u64::MAX)];
    prop_oneof![
        (any::<usize>(), index()).prop_map(|(c, n)| GltfEdit::Node(c, n)),
        (
            any::<usize>(),
            prop::sample::select(
                &[
                    "translation",
                    "rotation",
                    "scale",
                    "weights",
                    "rotations",
                    ""
                ][..]
            )
        )
            .prop_map(|(c, p)| GltfEdit::Path(c, p)),
        (any::<usize>(), index()).prop_map(|(c, s)| GltfEdit::Sampler(c, s)),
        (any::<usize>(), any::<bool>(), index()).prop_map(|(s, i, a)| GltfEdit::Accessor(s, i, a)),
        (
            any::<usize>(),
            prop::sample::select(&["LINEAR", "STEP", "CUBICSPLINE", "SPLINE"][..])
        )
            .prop_map(|(s, i)| GltfEdit::Interpolation(s, i)),
        (
            any::<usize>(),
            prop::sample::select(&[0u64, 1, 2, 3, 4, 66, 1 << 20, u32::MAX as u64, 1 << 40][..])
        )
            .prop_map(|(a, n)| GltfEdit::Count(a, n)),
        (
            any::<usize>(),
            prop::sample::select(&[5120u64, 5121, 5122, 5123, 5125, 5126, 0][..])
        )
            .prop_map(|(a, t)| GltfEdit::ComponentType(a, t)),
        (
            any::<usize>(),
            prop::sample::select(&["SCALAR", "VEC2", "VEC3", "VEC4", "MAT4", "VEC5"][..])
        )
            .prop_map(|(a, t)| GltfEdit::Type(a, t)),
        (any::<usize>(), any::<bool>()).prop_map(|(a, b)| GltfEdit::Normalized(a, b)),
        (
            any::<usize>(),
            prop::sample::select(&[0u64, 1, 4, 8, 12, 16, 252, 256][..])
        )
            .prop_map(|(v, s)| GltfEdit::Stride(v, s)),
        (any::<usize>(), bad_float()).prop_map(|(k, t)| GltfEdit::Time(k, t)),
        (any::<usize>(), bad_float()).prop_map(|(k, v)| GltfEdit::Float(k, v)),
    ]
}

/// f3g's own glTF motion as its JSON document and binary buffer.
fn gltf_parts() -> (Value, Vec<u8>) {
    let glb = f3g_motion::write_gltf(&common::walk(0, 3));
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let doc = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    (doc, glb[20 + json_len + 8..].to_vec())
}

/// Applies `edits` to the document and buffer of [`gltf_parts`].
fn edited_gltf(edits: &[GltfEdit]) -> (Value, Vec<u8>) {
    let (mut doc, mut bin) = gltf_parts();
    let len = |doc: &Value, key: &str| doc[key].as_array().map_or(1, |a| a.len().max(1));
    let anim = |doc: &Value, key: &str| {
        doc["animations"][0][key]
            .as_array()
            .map_or(1, |a| a.len().max(1))
    };
    for e in edits {
        match *e {
            GltfEdit::Node(c, n) => {
                let c = c % anim(&doc, "channels");
                doc["animations"][0]["channels"][c]["target"]["node"] = n.into();
            }
            GltfEdit::Path(c, p) => {
                let c = c % anim(&doc, "channels");
                doc["animations"][0]["channels"][c]["target"]["path"] = p.into();
            }
            GltfEdit::Sampler(c, s) => {
                let c = c % anim(&doc, "channels");
                doc["animations"][0]["channels"][c]["sampler"] = s.into();
            }
            GltfEdit::Accessor(s, input, a) => {
                let s = s % anim(&doc, "samplers");
                let key = if input { "input" } else { "output" };
                doc["animations"][0]["samplers"][s][key] = a.into();
            }
            GltfEdit::Interpolation(s, i) => {
                let s = s % anim(&doc, "samplers");
                doc["animations"][0]["samplers"][s]["interpolation"] = i.into();
            }
            GltfEdit::Count(a, n) => {
                let a = a % len(&doc, "accessors");
                doc["accessors"][a]["count"] = n.into();
            }
            GltfEdit::ComponentType(a, t) => {
                let a = a % len(&doc, "accessors");
                doc["accessors"][a]["componentType"] = t.into();
            }
            GltfEdit::Type(a, t) => {
                let a = a % len(&doc, "accessors");
                doc["accessors"][a]["type"] = t.into();
            }
            GltfEdit::Normalized(a, b) => {
                let a = a % len(&doc, "accessors");
                doc["accessors"][a]["normalized"] = b.into();
            }
            GltfEdit::Stride(v, s) => {
                let v = v % len(&doc, "bufferViews");
                doc["bufferViews"][v]["byteStride"] = s.into();
            }
            GltfEdit::Time(k, t) => {
                // Accessor 1 holds the key times every sampler shares (write_gltf's layout).
                let view = &doc["bufferViews"]
                    [doc["accessors"][1]["bufferView"].as_u64().unwrap_or(0) as usize];
                let start = view["byteOffset"].as_u64().unwrap_or(0) as usize;
                let at = start + 4 * (k % 3);
                if at + 4 <= bin.len() {
                    bin[at..at + 4].copy_from_slice(&t.to_le_bytes());
                }
            }
            GltfEdit::Float(k, v) => {
                let at = 4 * (k % (bin.len() / 4));
                bin[at..at + 4].copy_from_slice(&v.to_le_bytes());
            }
        }
    }
    (doc, bin)
}

/// An FBX key value or time a reader must doubt.
const FBX_NUMBERS: [&str; 12] = [
    "1e39",
    "-1e39",
    "1e30",
    "1000001",
    "-1000001",
    "nan",
    "inf",
    "-inf",
    "0",
    "-0",
    "359.5",
    "9223372036854775807",
];

/// f3g's own ASCII FBX motion with, for each edit `(curve, key, times, value)`, key `key` of
/// curve `curve` — its time (`times`) or its value — replaced by `value`.
fn edited_fbx(edits: &[(usize, usize, bool, &str)]) -> String {
    let mut text = f3g_motion::write_fbx(&common::walk(2, 3)).unwrap();
    for &(curve, key, times, value) in edits {
        let marker = if times {
            "KeyTime: *3 {\n\t\t\ta: "
        } else {
            "KeyValueFloat: *3 {\n\t\t\ta: "
        };
        let starts: Vec<usize> = text.match_indices(marker).map(|(i, _)| i).collect();
        let at = starts[curve % starts.len()] + marker.len();
        let end = at + text[at..].find('\n').unwrap();
        let mut keys: Vec<&str> = text[at..end].split(',').collect();
        let k = key % keys.len();
        keys[k] = value;
        let line = keys.join(",");
        text.replace_range(at..end, &line);
    }
    text
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
    fn edited_gltf_animations_read_or_error(edits in prop::collection::vec(gltf_edit(), 1..4)) {
        let (mut doc, bin) = edited_gltf(&edits);
        let dir = tempfile::tempdir().unwrap();
        doc["buffers"][0]["uri"] = "m.bin".into();
        std::fs::write(dir.path().join("m.bin"), &bin).unwrap();
        let path = dir.path().join("m.gltf");
        std::fs::write(&path, serde_json::to_vec(&doc).unwrap()).unwrap();
        check(f3g_motion::read(&path), "m.gltf")?;
    }

    #[test]
    fn edited_fbx_keys_parse_or_error(
        edits in prop::collection::vec(
            (any::<usize>(), any::<usize>(), any::<bool>(), prop::sample::select(&FBX_NUMBERS[..])),
            1..4,
        )
    ) {
        let text = edited_fbx(&edits);
        check(f3g_motion::parse_fbx(text.as_bytes(), Path::new("m.fbx")), "m.fbx")?;
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
