//! `f3g export-avatar` + `f3g view` in a real browser: Debian's headless Chromium (SwiftShader
//! WebGL) driven by puppeteer-core (`tests/browser/shoot.mjs`), the avatar file through the
//! Khronos glTF validator (`tests/browser/validate.mjs`) and Babylon.js's glTF loader
//! (`tests/browser/babylon.mjs`).
//!
//! The test that drives the browser needs `chromium`, `node` and `npm ci` in `tests/browser`,
//! so it is ignored by default (the README's test command runs on machines without a
//! browser); `.ci/run` installs them and runs it with `-- --ignored`.

mod common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use common::{f3g_in as f3g, ok};

fn scripts() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/browser")
}

/// `f3g view` running in the background; killed when dropped.
struct Server {
    child: Child,
    url: String,
}

impl Server {
    fn start(dir: &Path, args: &[&str]) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_f3g"))
            .arg("view")
            .args(args)
            .args(["--port", "0"])
            .current_dir(dir)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let mut line = String::new();
        let mut out = BufReader::new(child.stdout.take().unwrap());
        while !line.contains("http://") {
            line.clear();
            assert!(
                out.read_line(&mut line).unwrap() > 0,
                "f3g view exited early"
            );
        }
        let url = line[line.find("http://").unwrap()..]
            .split_whitespace()
            .next()
            .unwrap()
            .to_string();
        Self { child, url }
    }

    /// The status line of a raw GET of `path` (sent as is, unnormalised).
    fn status_of(&self, path: &str) -> String {
        let host = self.url.trim_start_matches("http://").trim_end_matches('/');
        let mut stream = TcpStream::connect(host).unwrap();
        write!(
            stream,
            "GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut response = String::new();
        let _ = stream.read_to_string(&mut response);
        response.lines().next().unwrap_or("").to_string()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Runs `shoot.mjs` on `url`; returns its JSON report.
fn shoot(url: &str, png: &Path, extra: &[&str]) -> serde_json::Value {
    let report = png.with_extension("json");
    let out = Command::new("node")
        .arg(scripts().join("shoot.mjs"))
        .args([url, png.to_str().unwrap(), report.to_str().unwrap()])
        .args(extra)
        .output()
        .unwrap();
    ok(&out);
    serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap()
}

/// PSNR over the pixels either image covers (not the white background).
fn avatar_psnr(a: &Path, b: &Path) -> (f64, usize) {
    let (a, b) = (f3g_io::read_rgb(a).unwrap(), f3g_io::read_rgb(b).unwrap());
    assert_eq!((a.width, a.height), (b.width, b.height));
    let (mut sum, mut count) = (0.0f64, 0usize);
    for (p, q) in a.data.chunks_exact(3).zip(b.data.chunks_exact(3)) {
        if p.iter().chain(q).any(|v| *v < 0.98) {
            sum += p
                .iter()
                .zip(q)
                .map(|(x, y)| ((x - y) as f64).powi(2))
                .sum::<f64>()
                / 3.0;
            count += 1;
        }
    }
    (-10.0 * (sum / count.max(1) as f64).log10(), count)
}

/// `avatar` driven by `motion` at `frame`, seen by the same camera (`view` for the player,
/// `cam.json` for f3g): the player's `?paused&bare` screenshot (`OUT.png`, its page ready and
/// without errors) against f3g's render of that frame (`OUT/frames/`, without the floor the
/// bare picture lacks); their PSNR over the avatar, which must cover over 1000 pixels.
fn player_against_f3g(
    d: &Path,
    avatar: &str,
    motion: &str,
    view: &str,
    frame: usize,
    out: &str,
) -> f64 {
    let server = Server::start(d, &[avatar, "--motion", motion]);
    assert!(
        server.url.starts_with("http://127.0.0.1:"),
        "{}",
        server.url
    );
    let shot = d.join(format!("{out}.png"));
    let report = shoot(
        &format!("{}?paused&bare", server.url),
        &shot,
        &["--view", view, "--frame", &frame.to_string()],
    );
    assert_eq!(report["ready"], true, "{report}");
    assert_eq!(report["errors"].as_array().unwrap().len(), 0, "{report}");
    drop(server);
    ok(&f3g(
        d,
        &[
            "animate",
            avatar,
            "--motion",
            motion,
            "--camera",
            "cam.json",
            "--out",
            out,
            "--no-floor",
        ],
    ));
    let (psnr, pixels) = avatar_psnr(&shot, &d.join(format!("{out}/frames/frame_{frame:05}.png")));
    assert!(pixels > 1000, "{out}: the avatar covers {pixels} pixels");
    psnr
}

/// `cam.json` of a three.js PerspectiveCamera at `eye` looking at `target` (+Y up) with a
/// vertical field of view `fov` (degrees): what the player's `setView` sets.
fn camera_json(eye: [f64; 3], target: [f64; 3], fov: f64, w: u32, h: u32) -> String {
    let focal = h as f64 / 2.0 / (fov.to_radians() / 2.0).tan();
    serde_json::to_string(&f3g_splat::Camera::look_at(
        eye,
        target,
        [0.0, 1.0, 0.0],
        focal,
        w,
        h,
    ))
    .unwrap()
}

/// A tiny trained run on a 5-frame capture, and its avatar baked with `k` correctives.
fn avatar(d: &Path, k: &[usize]) {
    common::tiny_capture(d, [3, 6, 1, 6, 1]);
    ok(&f3g(
        d,
        &[
            "train",
            "--data",
            "cap",
            "--out",
            "run",
            "--config",
            "tiny.json",
        ],
    ));
    for k in k {
        export_avatar(d, &format!("k{k}.glb"), *k, &[]);
    }
}

/// The tiny run baked with `k` correctives into `out` (a small bake: 4 perturbations, 16
/// directions), `extra` flags added.
fn export_avatar(d: &Path, out: &str, k: usize, extra: &[&str]) {
    let k = k.to_string();
    let mut args = vec![
        "export-avatar",
        "run",
        "--out",
        out,
        "--correctives",
        &k,
        "--perturbations",
        "4",
        "--directions",
        "16",
    ];
    args.extend_from_slice(extra);
    ok(&f3g(d, &args));
}

/// The Khronos glTF validator's report on `file` (`validate.mjs`), which fails on any error
/// but the splat attribute names this validator does not know.
fn validate(file: &Path) -> serde_json::Value {
    let out = Command::new("node")
        .arg(scripts().join("validate.mjs"))
        .arg(file)
        .output()
        .unwrap();
    ok(&out);
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
#[ignore = "needs chromium and the npm packages (see .ci/run)"]
fn the_player_draws_the_avatar_where_f3g_does_and_the_server_serves_only_the_player() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    avatar(d, &[0, 16]);
    // A motion f3g exports as a glTF animation passes the validator without a warning.
    ok(&f3g(
        d,
        &[
            "motion",
            "export",
            "run",
            "--format",
            "glb",
            "--out",
            "poses.glb",
        ],
    ));
    let report = validate(&d.join("poses.glb"));
    assert_eq!(report["warnings"].as_array().unwrap().len(), 0, "{report}");
    let (eye, target, fov, w, h) = ([0.5, 0.4, 2.6], [0.0, 0.3, 0.0], 30.0, 320, 240);
    std::fs::write(d.join("cam.json"), camera_json(eye, target, fov, w, h)).unwrap();
    let view = format!(
        "{},{},{},{},{},{},{fov},{w},{h}",
        eye[0], eye[1], eye[2], target[0], target[1], target[2]
    );
    for k in ["k0", "k16"] {
        // The Khronos validator finds nothing but the extension it does not know.
        validate(&d.join(format!("{k}.glb")));
        // The same frame, seen by the same camera, in the browser and by f3g's renderer.
        let psnr = player_against_f3g(d, &format!("{k}.glb"), "cap/body_params.npz", &view, 3, k);
        // 29.7 (k0) and 29.6 dB (k16) when written (2026-11-28); 30.4 and 30.2 with the file's
        // learnt light set to the neutral one: the player's lit colours differ from f3g's by
        // about 0.7 dB here, cause not found (open in issue #43's notes).
        assert!(
            psnr >= 29.0,
            "{k}: the player's picture is {psnr:.2} dB from f3g's"
        );
    }

    // The compressed file (SPZ Gaussians, packed correctives and expressions, byte weights):
    // the validator finds no error in it, and the player decodes it and draws what f3g draws
    // of it, and what it drew of the float file but for the quantisation.
    export_avatar(d, "k16c.glb", 16, &["--compress"]);
    validate(&d.join("k16c.glb"));
    let psnr = player_against_f3g(d, "k16c.glb", "cap/body_params.npz", &view, 3, "k16c");
    // 28.5 dB when written (2026-11-28; the float file 29.6): f3g's renders of the two files
    // are 39.7 dB apart, the player's 35.0 — Spark stores what it is given in its own
    // quantised form, which meets SPZ's grid differently from the floats' (both under the
    // unexplained 0.7 dB of lit colour above).
    assert!(
        psnr >= 28.0,
        "compressed: the player's picture is {psnr:.2} dB from f3g's"
    );
    let (psnr, _) = avatar_psnr(&d.join("k16c.png"), &d.join("k16.png"));
    assert!(
        psnr >= 33.0,
        "the player's pictures of the compressed and float files differ: {psnr:.1} dB"
    );

    // Babylon.js 9.28's own glTF loader, as a user of that viewer opens the files: the float
    // file loads as a Gaussian-splatting mesh and is drawn (unposed: Babylon reads no skin);
    // the compressed one is refused for the SPZ extension it requires.
    let babylon = |file: &str| -> serde_json::Value {
        let (png, report) = (
            d.join(format!("{file}.babylon.png")),
            d.join(format!("{file}.babylon.json")),
        );
        ok(&Command::new("node")
            .arg(scripts().join("babylon.mjs"))
            .args([d.join(file), png.clone(), report.clone()])
            .output()
            .unwrap());
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap()
    };
    let float = babylon("k16.glb");
    assert!(
        float["meshes"]
            .to_string()
            .contains("GaussianSplattingMesh"),
        "{float}"
    );
    let picture = f3g_io::read_rgb(&d.join("k16.glb.babylon.png")).unwrap();
    let drawn = picture
        .data
        .chunks_exact(3)
        .filter(|p| p.iter().any(|&v| v < 0.9))
        .count();
    assert!(drawn > 1000, "Babylon.js drew {drawn} pixels of the avatar");
    let compressed = babylon("k16c.glb");
    assert!(
        compressed["error"]
            .as_str()
            .is_some_and(|e| e.contains("KHR_gaussian_splatting_compression_spz_2")),
        "{compressed}"
    );
    // A posed frame for it: `export-ply`'s standard 3DGS `.ply`, read by Babylon's splat loader.
    ok(&f3g(
        d,
        &[
            "export-ply",
            "run",
            "--out",
            "frame.ply",
            "--frame",
            "3",
            "--directions",
            "16",
        ],
    ));
    let frame = babylon("frame.ply");
    assert!(
        frame["meshes"]
            .to_string()
            .contains("GaussianSplattingMesh"),
        "{frame}"
    );

    // A pose far from training (a deep lunge, the arms overhead): the player poses the avatar
    // and adds its correctives there as f3g does, so what it shows is the avatar's own.
    let rig = f3g_rig::ModelSpec::Builtin.load().unwrap();
    let mut far = f3g_rig::sequence::read(&d.join("cap/body_params.npz"), &rig).unwrap()[0].clone();
    for (name, value) in [
        ("upperleg01.L_rx", -1.4),
        ("lowerleg01.L_rx", 1.9),
        ("upperarm01.L_rz", 2.4),
        ("upperarm01.R_rz", -2.4),
    ] {
        let i = rig.pose_param_names().iter().position(|n| n == name);
        far.pose[i.unwrap_or_else(|| panic!("{name}"))] = value;
    }
    f3g_rig::sequence::write(&d.join("far.npz"), &rig, &[far]).unwrap();
    let psnr = player_against_f3g(d, "k16.glb", "far.npz", &view, 0, "far");
    // 27.2 dB when written (2026-11-27; frame 3: ≥ 30): the pictures differ only at the two
    // shoulders, where the blend of the arm's and the torso's transforms is furthest from a
    // rotation — the player transforms covariances by the blended matrix, f3g by its polar
    // rotation (BENCHMARKS, "Where the blotches under new motions come from").
    assert!(
        psnr >= 26.0,
        "far pose: the player's picture is {psnr:.2} dB from f3g's"
    );
    let (psnr, _) = avatar_psnr(&d.join("far.png"), &d.join("k16.png"));
    assert!(
        psnr < 25.0,
        "the far pose looks like frame 3 ({psnr:.1} dB)"
    );

    // The light fixed in the world, made strong (from above and the front; the tiny run's is
    // near the neutral one): the player shades each splat from its turned normal as f3g does.
    let mut glb = f3g_rig::glb::GlbFile::parse(&std::fs::read(d.join("k16.glb")).unwrap()).unwrap();
    let light = &mut glb.document["meshes"][0]["primitives"][0]["extensions"]["F3G_world_shading"];
    assert!(light.is_object(), "the cpu preset's avatar has its light");
    let mut coefficients = vec![0.0f32; 27];
    coefficients[..3].fill(1.0 / f3g_splat::sh::SH_C0 as f32);
    coefficients[3..6].fill(-2.5);
    coefficients[6..9].fill(1.5);
    light["coefficients"] = serde_json::json!(coefficients);
    std::fs::write(d.join("lit.glb"), glb.to_bytes()).unwrap();
    let psnr = player_against_f3g(d, "lit.glb", "far.npz", &view, 0, "lit");
    assert!(
        psnr >= 26.0,
        "lit: the player's picture is {psnr:.2} dB from f3g's"
    );
    let (psnr, _) = avatar_psnr(&d.join("lit.png"), &d.join("far.png"));
    assert!(psnr < 22.0, "the light changes nothing ({psnr:.1} dB)");

    // Moving the slider changes the frame and the picture.
    let server = Server::start(d, &["k16.glb", "--motion", "cap/body_params.npz"]);
    let report = shoot(
        &format!("{}?paused&bare", server.url),
        &d.join("slider.png"),
        &["--view", &view, "--slider"],
    );
    assert_ne!(report["frameBefore"], report["frameAfter"], "{report}");
    let (psnr, _) = avatar_psnr(&d.join("k16.png"), &d.join("slider.png"));
    assert!(
        psnr < 40.0,
        "the picture did not change with the frame ({psnr:.1} dB)"
    );

    // The server serves its table and nothing else.
    assert!(server.status_of("/").contains("200"));
    for path in [
        "/../Cargo.toml",
        "/%2e%2e/Cargo.toml",
        "//etc/passwd",
        "/vendor/../player.js",
        "/%2Fetc%2Fpasswd",
        "/motions/../avatar.glb",
    ] {
        assert!(
            server.status_of(path).contains("404"),
            "{path}: {}",
            server.status_of(path)
        );
    }

    // A damaged avatar is shown as an error on the page.
    let report = shoot(&server.url, &d.join("corrupt.png"), &["--corrupt-avatar"]);
    assert_eq!(report["ready"], false, "{report}");
    let shown = report["errorShown"].as_str().unwrap_or("");
    assert!(
        shown.contains("avatar.glb") && shown.contains("truncated"),
        "{report}"
    );
}

#[test]
fn bad_avatar_files_and_motions_are_refused_before_serving() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("bad.glb"), b"glTF\x02\0\0\0\xff\xff\0\0").unwrap();
    let out = f3g(d, &["view", "bad.glb", "--static", "out"]);
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("bad.glb") && e.contains("truncated"), "{e}");
    assert!(!d.join("out").exists(), "nothing is written on failure");

    // Motions with NaN, or of a body model that cannot be mapped, are errors naming the file.
    avatar(d, &[0]);
    let rig = f3g_rig::ModelSpec::Builtin.load().unwrap();
    let mut frame = rig.zero_params();
    frame.pose[7] = f32::NAN;
    f3g_rig::sequence::write(&d.join("nan.npz"), &rig, &[frame]).unwrap();
    // A sequence of a body model that cannot be loaded here cannot be retargeted.
    let mut other = rig.clone();
    other.name = "smplx:/missing/SMPLX_NEUTRAL.npz".into();
    if let f3g_rig::Parameterization::Momentum(t) = &mut other.parameterization {
        t.names[0] = "elsewhere".into();
    }
    f3g_rig::sequence::write(&d.join("other.npz"), &other, &[other.zero_params()]).unwrap();
    for (motion, says) in [("nan.npz", "finite"), ("other.npz", "cannot be loaded")] {
        let out = f3g(
            d,
            &["view", "k0.glb", "--motion", motion, "--static", "out"],
        );
        assert!(!out.status.success());
        let e = String::from_utf8_lossy(&out.stderr);
        assert!(e.contains(motion) && e.contains(says), "{motion}: {e}");
        assert!(!d.join("out").exists());
    }
}
