//! Every bad motion input is an error naming the file and what is wrong: never a panic, a
//! hang, a read of anything but a regular file beside a `.gltf`, or an unbounded read
//! (issue #44, item 7). Each case is a valid motion with one thing broken.

mod common;

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use f3g_motion::{Motion, MotionError, parse_bvh, parse_fbx, read};
use f3g_testkit::{AllocationGuard, Array, write_arrays};
use serde_json::Value;

/// A reader that trusts a size (or reads a device to its end) stops the test binary here
/// instead of taking the machine's memory.
#[global_allocator]
static GUARD: AllocationGuard = AllocationGuard::new(256 << 20);

/// `result` is an error whose message holds every one of `parts`.
fn refused(result: Result<Motion, MotionError>, parts: &[&str]) {
    match result {
        Ok(_) => panic!("accepted; expected an error mentioning {parts:?}"),
        Err(e) => {
            let e = e.to_string();
            for p in parts {
                assert!(e.contains(p), "`{e}` does not mention `{p}`");
            }
        }
    }
}

/// Reads `path` on another thread: a reader that blocks (a FIFO opened for reading) fails the
/// test after 20 s instead of hanging it.
fn read_in_time(path: PathBuf) -> Result<Motion, MotionError> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(read(&path));
    });
    rx.recv_timeout(Duration::from_secs(20))
        .expect("the reader hung (or panicked) instead of returning")
}

// --- glTF -------------------------------------------------------------------------------

/// f3g's own glTF motion split into its JSON document and binary buffer.
fn gltf_parts() -> (Value, Vec<u8>) {
    let glb = f3g_motion::write_gltf(&common::walk(0, 3));
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let doc = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    (doc, glb[20 + json_len + 8..].to_vec())
}

/// Writes `doc` as `dir/m.gltf` and `bin` as `dir/m.bin` (the URI `m.bin` unless `doc` sets
/// another) and returns the `.gltf`'s path.
fn write_gltf(dir: &Path, mut doc: Value, bin: &[u8]) -> PathBuf {
    if doc["buffers"][0]["uri"].is_null() {
        doc["buffers"][0]["uri"] = "m.bin".into();
    }
    std::fs::write(dir.join("m.bin"), bin).unwrap();
    let path = dir.join("m.gltf");
    std::fs::write(&path, serde_json::to_vec(&doc).unwrap()).unwrap();
    path
}

/// The byte offset in the buffer of element `k` of accessor `a`.
fn element(doc: &Value, a: usize, k: usize) -> usize {
    let accessor = &doc["accessors"][a];
    let view = &doc["bufferViews"][accessor["bufferView"].as_u64().unwrap() as usize];
    let width = match accessor["type"].as_str().unwrap() {
        "SCALAR" => 4,
        "VEC3" => 12,
        "VEC4" => 16,
        _ => 64,
    };
    view["byteOffset"].as_u64().unwrap_or(0) as usize
        + accessor["byteOffset"].as_u64().unwrap_or(0) as usize
        + k * width
}

fn set_f32(bin: &mut [u8], at: usize, v: f32) {
    bin[at..at + 4].copy_from_slice(&v.to_le_bytes());
}

/// The sampler accessors of channel `c`: (key times, values).
fn sampler_of(doc: &Value, c: usize) -> (usize, usize) {
    let anim = &doc["animations"][0];
    let s = &anim["samplers"][anim["channels"][c]["sampler"].as_u64().unwrap() as usize];
    (
        s["input"].as_u64().unwrap() as usize,
        s["output"].as_u64().unwrap() as usize,
    )
}

#[test]
fn the_gltf_fixture_reads() {
    let dir = tempfile::tempdir().unwrap();
    let (doc, bin) = gltf_parts();
    let m = read(&write_gltf(dir.path(), doc, &bin)).unwrap();
    assert_eq!(m.frames(), 3);
}

#[test]
fn a_gltf_channel_naming_a_missing_node_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (mut doc, bin) = gltf_parts();
    doc["animations"][0]["channels"][1]["target"]["node"] = 999.into();
    let path = write_gltf(dir.path(), doc, &bin);
    refused(read_in_time(path), &["m.gltf", "channel 1", "node 999"]);
}

#[test]
fn a_gltf_channel_with_an_unknown_target_path_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (mut doc, bin) = gltf_parts();
    doc["animations"][0]["channels"][0]["target"]["path"] = "rotations".into();
    let path = write_gltf(dir.path(), doc, &bin);
    refused(read_in_time(path), &["m.gltf", "channel 0", "target.path"]);
}

#[test]
fn gltf_key_times_out_of_order_are_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (doc, mut bin) = gltf_parts();
    let (times, _) = sampler_of(&doc, 0);
    set_f32(&mut bin, element(&doc, times, 1), 0.5);
    let path = write_gltf(dir.path(), doc, &bin);
    refused(
        read(&path),
        &["m.gltf", "channel 0", "key time", "increase"],
    );
}

#[test]
fn a_gltf_rotation_key_that_is_not_a_unit_quaternion_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (doc, mut bin) = gltf_parts();
    let (_, values) = sampler_of(&doc, 3);
    for i in 0..4 {
        set_f32(&mut bin, element(&doc, values, 1) + 4 * i, 1e30);
    }
    let path = write_gltf(dir.path(), doc, &bin);
    refused(
        read(&path),
        &["m.gltf", "channel 3", "key 1", "unit quaternion"],
    );
}

#[test]
fn a_gltf_root_translation_beyond_a_kilometre_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (doc, mut bin) = gltf_parts();
    let last = doc["animations"][0]["channels"].as_array().unwrap().len() - 1;
    let (_, values) = sampler_of(&doc, last);
    set_f32(&mut bin, element(&doc, values, 2), 1e30);
    let path = write_gltf(dir.path(), doc, &bin);
    refused(read(&path), &["m.gltf", "1 km"]);
}

#[test]
fn a_gltf_byte_stride_shorter_than_an_element_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (mut doc, bin) = gltf_parts();
    let (_, values) = sampler_of(&doc, 0);
    let view = doc["accessors"][values]["bufferView"].as_u64().unwrap() as usize;
    doc["bufferViews"][view]["byteStride"] = 4.into();
    let path = write_gltf(dir.path(), doc, &bin);
    refused(read_in_time(path), &["m.gltf", "byteStride 4"]);
}

#[test]
fn a_gltf_rotation_of_unsigned_int_components_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (mut doc, bin) = gltf_parts();
    let (_, values) = sampler_of(&doc, 0);
    doc["accessors"][values]["componentType"] = 5125.into();
    let path = write_gltf(dir.path(), doc, &bin);
    refused(read_in_time(path), &["m.gltf", "channel 0", "VEC4"]);
}

#[test]
fn a_gltf_node_cycle_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (mut doc, bin) = gltf_parts();
    // Two nodes above the root joint that are each other's parent: a walk up from the root
    // looking for a joint parent never ends.
    let nodes = doc["nodes"].as_array_mut().unwrap();
    let (a, b) = (nodes.len(), nodes.len() + 1);
    nodes.push(serde_json::json!({ "children": [0, b] }));
    nodes.push(serde_json::json!({ "children": [a] }));
    let path = write_gltf(dir.path(), doc, &bin);
    refused(read_in_time(path), &["m.gltf", "is its own ancestor"]);
}

#[test]
fn a_gltf_buffer_at_an_absolute_path_is_refused() {
    let elsewhere = tempfile::tempdir().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (mut doc, bin) = gltf_parts();
    let outside = elsewhere.path().join("outside.bin");
    std::fs::write(&outside, &bin).unwrap();
    doc["buffers"][0]["uri"] = outside.to_str().unwrap().into();
    let path = write_gltf(dir.path(), doc, &bin);
    refused(read(&path), &["m.gltf", "buffer 0", "relative"]);
}

#[test]
fn a_gltf_buffer_outside_the_folder_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let sub = dir.path().join("sub");
    std::fs::create_dir(&sub).unwrap();
    let (mut doc, bin) = gltf_parts();
    std::fs::write(dir.path().join("up.bin"), &bin).unwrap();
    doc["buffers"][0]["uri"] = "../up.bin".into();
    let path = write_gltf(&sub, doc, &bin);
    refused(read(&path), &["m.gltf", "buffer 0", "`..`"]);
}

#[test]
fn a_gltf_buffer_uri_that_decodes_to_no_text_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (mut doc, bin) = gltf_parts();
    doc["buffers"][0]["uri"] = "m%FF.bin".into();
    let path = write_gltf(dir.path(), doc, &bin);
    refused(read_in_time(path), &["m.gltf", "buffer 0", "m%FF.bin"]);
}

#[cfg(unix)]
#[test]
fn a_gltf_buffer_in_a_fifo_is_refused_without_opening_it() {
    let dir = tempfile::tempdir().unwrap();
    let (mut doc, bin) = gltf_parts();
    let status = std::process::Command::new("mkfifo")
        .arg(dir.path().join("pipe.bin"))
        .status()
        .unwrap();
    assert!(status.success());
    doc["buffers"][0]["uri"] = "pipe.bin".into();
    let path = write_gltf(dir.path(), doc, &bin);
    refused(
        read_in_time(path),
        &["m.gltf", "buffer 0", "not a regular file"],
    );
}

#[cfg(unix)]
#[test]
fn a_gltf_buffer_linked_to_a_device_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (mut doc, bin) = gltf_parts();
    std::os::unix::fs::symlink("/dev/zero", dir.path().join("zero.bin")).unwrap();
    doc["buffers"][0]["uri"] = "zero.bin".into();
    let path = write_gltf(dir.path(), doc, &bin);
    refused(
        read_in_time(path),
        &["m.gltf", "buffer 0", "not a regular file"],
    );
}

#[test]
fn a_gltf_buffer_file_is_read_only_up_to_its_byte_length() {
    let dir = tempfile::tempdir().unwrap();
    let (doc, bin) = gltf_parts();
    let path = write_gltf(dir.path(), doc, &bin);
    // 512 MiB past the buffer's end (sparse: no disk is used).
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(dir.path().join("m.bin"))
        .unwrap();
    file.set_len(bin.len() as u64 + (512 << 20)).unwrap();
    read(&path).unwrap();
}

#[test]
fn a_gltf_buffer_byte_length_past_the_maximum_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (mut doc, bin) = gltf_parts();
    doc["buffers"][0]["byteLength"] = (1u64 << 40).into();
    let path = write_gltf(dir.path(), doc, &bin);
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(dir.path().join("m.bin"))
        .unwrap();
    file.set_len(1 << 40).unwrap();
    refused(
        read(&path),
        &["m.gltf", "buffer 0", "byteLength 1099511627776"],
    );
}

// --- FBX --------------------------------------------------------------------------------

/// f3g's own ASCII FBX motion with the first key of its `curve`-th curve (0: the root's
/// rotation X, 3: its translation X) replaced by `value`.
fn fbx_with_key(curve: usize, value: &str) -> String {
    let text = f3g_motion::write_fbx(&common::walk(2, 3)).unwrap();
    let marker = "KeyValueFloat: *3 {\n\t\t\ta: ";
    let at = text.match_indices(marker).nth(curve).unwrap().0 + marker.len();
    let end = at + text[at..].find(',').unwrap();
    format!("{}{value}{}", &text[..at], &text[end..])
}

#[test]
fn the_fbx_fixture_reads() {
    let m = parse_fbx(fbx_with_key(0, "10").as_bytes(), Path::new("m.fbx")).unwrap();
    assert_eq!(m.frames(), 3);
}

#[test]
fn an_fbx_rotation_key_beyond_a_million_degrees_is_an_error() {
    let text = fbx_with_key(0, "1e39");
    refused(
        parse_fbx(text.as_bytes(), Path::new("m.fbx")),
        &["m.fbx", "Lcl Rotation", "key 0"],
    );
}

#[test]
fn an_fbx_translation_key_beyond_a_kilometre_is_an_error() {
    let text = fbx_with_key(3, "1e30");
    refused(
        parse_fbx(text.as_bytes(), Path::new("m.fbx")),
        &["m.fbx", "Lcl Translation", "key 0"],
    );
}

// --- AMASS, .smpl, smpl_params.npz -------------------------------------------------------

fn amass(poses: f32, trans: f32) -> Vec<Array> {
    let frames = 3;
    let mut p = vec![0.1; frames * 156];
    p[156 + 5] = poses;
    let mut t = vec![0.5; frames * 3];
    t[4] = trans;
    vec![
        Array::f32("poses", &[frames, 156], &p),
        Array::f32("trans", &[frames, 3], &t),
        Array::f32("betas", &[16], &[0.0; 16]),
        Array::f32("mocap_framerate", &[], &[60.0]),
    ]
}

#[test]
fn the_amass_fixture_reads() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.npz");
    write_arrays(&path, &amass(0.1, 0.5));
    read(&path).unwrap();
}

#[test]
fn an_amass_translation_beyond_a_kilometre_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.npz");
    write_arrays(&path, &amass(0.1, 1e30));
    refused(read(&path), &["m.npz", "`trans`", "frame 1", "1 km"]);
}

#[test]
fn an_amass_rotation_beyond_the_angle_bound_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.npz");
    write_arrays(&path, &amass(1e30, 0.5));
    refused(read(&path), &["m.npz", "`poses`", "frame 1, value 5"]);
}

#[test]
fn a_smpl_codec_translation_beyond_a_kilometre_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.smpl");
    let frames = 2;
    write_arrays(
        &path,
        &[
            Array::f32("frameRate", &[], &[30.0]),
            Array::f32(
                "bodyTranslation",
                &[frames, 3],
                &[0.0, 0.0, 0.0, 0.0, -1e30, 0.0],
            ),
            Array::f32("bodyPose", &[frames, 22, 3], &vec![0.1; frames * 66]),
        ],
    );
    refused(read(&path), &["m.smpl", "`bodyTranslation`", "frame 1"]);
}

#[test]
fn a_smpl_params_translation_beyond_a_kilometre_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("smpl_params.npz");
    let frames = 2;
    write_arrays(
        &path,
        &[
            Array::f32("betas", &[10], &[0.0; 10]),
            Array::f32("global_orient", &[frames, 3], &[0.0; 6]),
            Array::f32("body_pose", &[frames, 63], &vec![0.1; frames * 63]),
            Array::f32("transl", &[frames, 3], &[0.0, 0.0, 0.0, 1e30, 0.0, 0.0]),
        ],
    );
    refused(read(&path), &["smpl_params.npz", "`transl`", "frame 1"]);
}

// --- BVH --------------------------------------------------------------------------------

fn bvh() -> String {
    f3g_motion::write_bvh(&common::walk(1, 3)).unwrap()
}

#[test]
fn a_bvh_with_a_byte_order_mark_reads() {
    let text = format!("\u{feff}{}", bvh());
    let m = parse_bvh(text.as_bytes(), Path::new("m.bvh")).unwrap();
    assert_eq!(m.frames(), 3);
}

/// 3ds Max's Biped names hold spaces (`Bip01 L Thigh`): the name is the rest of the line, also
/// with the brace on it.
#[test]
fn bvh_joint_names_may_hold_spaces() {
    let text = "HIERARCHY\nROOT Bip01  Pelvis\n{\n OFFSET 0 0 0\n CHANNELS 3 Zrotation Xrotation \
                Yrotation\n JOINT Bip01 L Thigh {\n  OFFSET 0 -10 0\n  CHANNELS 3 Zrotation \
                Xrotation Yrotation\n  End Site\n  {\n   OFFSET 0 -40 0\n  }\n }\n}\nMOTION\n\
                Frames: 1\nFrame Time: 0.1\n0 0 0 0 0 0\n";
    let m = parse_bvh(text.as_bytes(), Path::new("m.bvh")).unwrap();
    let names: Vec<&str> = m
        .skeleton
        .joints()
        .iter()
        .map(|j| j.name.as_str())
        .collect();
    assert_eq!(names, ["Bip01 Pelvis", "Bip01 L Thigh"]);
    let again = f3g_motion::write_bvh(&m).unwrap();
    let m2 = parse_bvh(again.as_bytes(), Path::new("m.bvh")).unwrap();
    assert_eq!(m2.skeleton.joints()[1].name, "Bip01 L Thigh");
    // What would not read back so is refused by the writer.
    for bad in ["Bip01\tL Thigh", "Bip01  L", " Thigh", "Thigh {"] {
        let mut joints = m.skeleton.joints().to_vec();
        joints[1].name = bad.into();
        let odd = f3g_motion::Motion {
            skeleton: f3g_rig::Skeleton::new(joints).unwrap(),
            ..m.clone()
        };
        let e = f3g_motion::write_bvh(&odd).unwrap_err();
        assert!(e.contains("cannot be written to BVH"), "{bad:?}: {e}");
    }
}

#[test]
fn a_bvh_whose_offsets_are_all_zero_is_an_error() {
    let text: String = bvh()
        .lines()
        .map(|l| match l.trim_start().strip_prefix("OFFSET") {
            Some(_) => "OFFSET 0 0 0\n".to_string(),
            None => format!("{l}\n"),
        })
        .collect();
    refused(
        parse_bvh(text.as_bytes(), Path::new("m.bvh")),
        &[
            "m.bvh",
            "the rest skeleton has zero length: no units or scale can be inferred",
        ],
    );
}

/// The BVH fixture with its header line starting with `key` replaced by `line`.
fn bvh_with_line(key: &str, line: &str) -> String {
    bvh()
        .lines()
        .map(|l| {
            if l.starts_with(key) {
                format!("{line}\n")
            } else {
                format!("{l}\n")
            }
        })
        .collect()
}

/// Numbers are reported as the file writes them (an `f32` would print `1e-300` as `0` and
/// `999999999999` as `1000000000000`), and a huge token is quoted cut, not echoed.
#[test]
fn a_bvh_error_quotes_the_input_as_written_and_briefly() {
    refused(
        parse_bvh(
            bvh_with_line("Frame Time", "Frame Time: 1e-300").as_bytes(),
            Path::new("m.bvh"),
        ),
        &["m.bvh", "frame time `1e-300` s"],
    );
    refused(
        parse_bvh(
            bvh_with_line("Frames:", "Frames: 999999999999").as_bytes(),
            Path::new("m.bvh"),
        ),
        &["m.bvh", "`999999999999` frames"],
    );
    let token = "x".repeat(5 << 20);
    let text = bvh().replacen("HIERARCHY", &token, 1);
    match parse_bvh(text.as_bytes(), Path::new("m.bvh")) {
        Ok(_) => panic!("accepted a BVH without HIERARCHY"),
        Err(e) => {
            let e = e.to_string();
            assert!(
                e.len() < 600 && e.contains(&format!("({} bytes)", token.len())),
                "{}",
                &e[..e.len().min(600)]
            );
        }
    }
}

/// The BVH fixture with the first value of frame 1 — its `column`-th channel — set to `value`.
fn bvh_with_value(column: usize, value: &str) -> String {
    let text = bvh();
    let lines: Vec<&str> = text.lines().collect();
    let first = lines
        .iter()
        .position(|l| l.starts_with("Frame Time"))
        .unwrap()
        + 2;
    let mut row: Vec<&str> = lines[first].split_whitespace().collect();
    row[column] = value;
    let row = row.join(" ");
    let mut out: Vec<&str> = lines.clone();
    out[first] = &row;
    out.join("\n") + "\n"
}

#[test]
fn a_bvh_rotation_beyond_a_million_degrees_is_an_error() {
    let text = bvh_with_value(4, "1e7");
    refused(
        parse_bvh(text.as_bytes(), Path::new("m.bvh")),
        &["m.bvh", "frame 1", "1000000"],
    );
}

#[test]
fn a_bvh_root_position_beyond_a_kilometre_is_an_error() {
    let text = bvh_with_value(0, "1e30");
    refused(
        parse_bvh(text.as_bytes(), Path::new("m.bvh")),
        &["m.bvh", "frame 1", "1 km"],
    );
}
