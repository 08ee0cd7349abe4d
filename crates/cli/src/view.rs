//! `f3g view`: the browser player (`crates/cli/player`) with an avatar and its motions, served
//! from a local HTTP server or written as a static folder.
//!
//! What is served is a fixed table of files built before the server starts — the page, its
//! vendored libraries (compiled into the binary), `avatar.glb`, `motions.json` and one
//! `motions/N.bin` per motion — looked up by exact path. Nothing is read from the disk while
//! serving, so no request (`..`, absolute or percent-encoded paths, links) can reach another
//! file: anything not in the table is a 404. The server (`crate::server`: its rules) listens on
//! the loopback address unless `--host` says otherwise, with a warning then.
//!
//! A motion file is `frames × (16·J + E)` little-endian floats: each joint's world matrix in
//! the frame's pose (column major, the avatar's shape), then its `E` expression weights in the
//! avatar's order (`crates/cli/player/player.js` reads it).

use std::collections::BTreeMap;
use std::net::IpAddr;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use f3g_avatar::infer::bake::{BakeOptions, BakedAvatar};
use f3g_rig::RigParams;
use glam::Mat4;

use crate::device::DeviceArg;

/// Options of `f3g view`.
#[derive(Args, Debug, Clone)]
pub struct ViewArgs {
    /// A baked avatar (`.glb`, from `f3g export-avatar`) or a run folder (baked first, and
    /// kept as RUN/avatar-kK.glb for the next time).
    pub source: PathBuf,
    /// Motion to offer, repeatable: an f3g sequence, or AMASS .npz, .smpl, smpl_params.npz,
    /// BVH, glTF or FBX (retargeted onto the avatar, resampled to --fps); without one: a run's
    /// training poses, or the canonical pose.
    #[arg(long)]
    pub motion: Vec<PathBuf>,
    #[command(flatten)]
    pub retarget: crate::motion::RetargetArgs,
    #[command(flatten)]
    pub frames: crate::motion::FramesArg,
    /// Port to listen on (0: any free port).
    #[arg(long, default_value_t = 8080)]
    pub port: u16,
    /// Address to listen on; the default serves this machine only.
    #[arg(long, default_value = "127.0.0.1")]
    pub host: IpAddr,
    /// Write the player, the avatar and the motions into this folder (for any static file
    /// host) instead of serving them.
    /// New, empty, or an earlier `--static` folder (whose files it replaces).
    #[arg(long = "static", value_name = "DIR")]
    pub static_dir: Option<PathBuf>,
    /// Write into a --static folder that holds other files (those of the same names, e.g. an
    /// `index.html`, are replaced; nothing else is removed).
    #[arg(long, requires = "static_dir")]
    pub overwrite: bool,
    /// Pose correctives when baking a run, 0–256.
    #[arg(long, default_value_t = 16, value_parser = crate::bounds::size::<0, 256>)]
    pub correctives: usize,
    /// Frames per second of the motions.
    #[arg(long, default_value_t = 15.0)]
    pub fps: f32,
    #[command(flatten)]
    pub device: DeviceArg,
}

/// The player's own files, compiled in: (path, bytes).
const PLAYER: [(&str, &[u8]); 10] = [
    ("index.html", include_bytes!("../player/index.html")),
    ("player.js", include_bytes!("../player/player.js")),
    (
        "vendor/README.md",
        include_bytes!("../player/vendor/README.md"),
    ),
    (
        "vendor/three/three.module.js",
        include_bytes!("../player/vendor/three/three.module.js"),
    ),
    (
        "vendor/three/three.core.js",
        include_bytes!("../player/vendor/three/three.core.js"),
    ),
    (
        "vendor/three/LICENSE",
        include_bytes!("../player/vendor/three/LICENSE"),
    ),
    (
        "vendor/three/addons/postprocessing/Pass.js",
        include_bytes!("../player/vendor/three/addons/postprocessing/Pass.js"),
    ),
    (
        "vendor/three/addons/controls/OrbitControls.js",
        include_bytes!("../player/vendor/three/addons/controls/OrbitControls.js"),
    ),
    (
        "vendor/spark/spark.module.min.js",
        include_bytes!("../player/vendor/spark/spark.module.min.js"),
    ),
    (
        "vendor/spark/LICENSE",
        include_bytes!("../player/vendor/spark/LICENSE"),
    ),
];

/// The baked avatar of `source`: read from a `.glb`, or baked from a run (kept beside it).
fn avatar_of(
    a: &ViewArgs,
) -> Result<(
    BakedAvatar,
    Vec<u8>,
    Option<f3g_avatar::infer::TrainedAvatar>,
)> {
    if a.source.is_file() {
        let bytes = std::fs::read(&a.source).with_context(|| a.source.display().to_string())?;
        let avatar = f3g_avatar::infer::avatar_file::from_bytes(&bytes)
            .map_err(|e| anyhow::anyhow!("{}: {e}", a.source.display()))?;
        return Ok((avatar, bytes, None));
    }
    let trained = f3g_avatar::infer::TrainedAvatar::load(&a.source, &a.device.open()?)?;
    let cached = a.source.join(format!("avatar-k{}.glb", a.correctives));
    let checkpoint = f3g_avatar::infer::Run::new(&a.source).latest()?;
    let fresh = match (std::fs::metadata(&cached), checkpoint) {
        (Ok(file), Some(c)) => std::fs::metadata(c.join("state.json"))
            .and_then(|s| Ok(file.modified()? >= s.modified()?))
            .unwrap_or(false),
        _ => false,
    };
    if !fresh {
        println!(
            "baking {} with {} correctives …",
            a.source.display(),
            a.correctives
        );
        let options = BakeOptions {
            correctives: a.correctives,
            ..BakeOptions::default()
        };
        let (baked, _) = BakedAvatar::bake(&trained, &trained.training_poses()?, &options)?;
        f3g_avatar::infer::avatar_file::write(
            &baked,
            &cached,
            f3g_avatar::infer::avatar_file::Encoding::Float,
        )?;
    }
    let bytes = std::fs::read(&cached).with_context(|| cached.display().to_string())?;
    let avatar = f3g_avatar::infer::avatar_file::from_bytes(&bytes)
        .map_err(|e| anyhow::anyhow!("{}: {e}", cached.display()))?;
    Ok((avatar, bytes, Some(trained)))
}

/// A motion as the player reads it (module docs), in the avatar's shape.
pub fn motion_bytes(avatar: &BakedAvatar, frames: &[RigParams]) -> Result<Vec<u8>> {
    let rig = &avatar.rig;
    let expression_index: Vec<Option<usize>> = avatar
        .expression_names
        .iter()
        .map(|n| rig.expression.names.iter().position(|m| m == n))
        .collect();
    let mut out = Vec::with_capacity(frames.len() * (16 * rig.skeleton.len() + 4) * 4);
    for (f, params) in frames.iter().enumerate() {
        let mut p = params.clone();
        p.identity = avatar.canonical.identity.clone();
        let posed = rig
            .pose(&p)
            .with_context(|| format!("posing frame {f} of the motion"))?;
        for w in &posed.joints {
            for v in Mat4::from(w.to_affine()).to_cols_array() {
                out.extend(v.to_le_bytes());
            }
        }
        for i in &expression_index {
            let v = i.and_then(|i| p.expression.get(i).copied()).unwrap_or(0.0);
            out.extend(v.to_le_bytes());
        }
    }
    Ok(out)
}

/// Every file of the player for `a`: path → bytes.
fn files(a: &ViewArgs) -> Result<BTreeMap<String, Vec<u8>>> {
    let (avatar, glb, trained) = avatar_of(a)?;
    let mut motions: Vec<(String, Vec<RigParams>)> = Vec::new();
    for path in &a.motion {
        let motion = f3g_avatar::infer::animate::read_motion(
            path,
            &avatar.rig,
            &avatar.canonical,
            &a.retarget.options(Some(a.fps))?,
        )?;
        if let Some(r) = &motion.retargeted {
            eprintln!("{}", crate::motion::describe(path, r, motion.frames.len()));
        }
        let frames = a.frames.cut(motion.frames)?;
        let name = path
            .file_stem()
            .map_or("motion".into(), |s| s.to_string_lossy().into_owned());
        motions.push((name, frames));
    }
    if motions.is_empty() {
        match &trained {
            Some(t) => motions.push(("training poses".into(), t.training_poses()?)),
            None => motions.push(("canonical pose".into(), vec![avatar.canonical.clone()])),
        }
    }
    let mut files: BTreeMap<String, Vec<u8>> = PLAYER
        .iter()
        .map(|(p, b)| (p.to_string(), b.to_vec()))
        .collect();
    files.insert("avatar.glb".into(), glb);
    let mut list = Vec::new();
    for (i, (name, frames)) in motions.iter().enumerate() {
        let url = format!("motions/{i}.bin");
        files.insert(url.clone(), motion_bytes(&avatar, frames)?);
        list.push(serde_json::json!({
            "name": name, "frames": frames.len(), "fps": a.fps, "url": url,
        }));
    }
    files.insert("motions.json".into(), serde_json::to_vec_pretty(&list)?);
    Ok(files)
}

pub fn view(a: &ViewArgs) -> Result<()> {
    if !(a.fps.is_finite() && a.fps > 0.0 && a.fps <= 1000.0) {
        bail!("--fps {}: expected a rate in (0, 1000]", a.fps);
    }
    // Refused before the avatar is baked, not after.
    let out = match &a.static_dir {
        Some(dir) => Some(f3g_io::OutputDir::open(dir, "view", a.overwrite)?),
        None => None,
    };
    let files = files(a)?;
    if let (Some(mut out), Some(dir)) = (out, &a.static_dir) {
        for (path, bytes) in &files {
            f3g_io::write_atomic(&out.file(path)?, bytes)?;
        }
        out.finish()?;
        println!(
            "wrote the player ({} files) to {}: serve that folder with any static file host",
            files.len(),
            dir.display()
        );
        return Ok(());
    }
    serve(files, a.host, a.port)
}

fn serve(files: BTreeMap<String, Vec<u8>>, host: IpAddr, port: u16) -> Result<()> {
    let listener = std::net::TcpListener::bind((host, port))
        .with_context(|| format!("cannot listen on {host}:{port}"))?;
    let address = listener.local_addr()?;
    if !host.is_loopback() {
        eprintln!(
            "warning: --host {host} serves the avatar, its motions and the player to every \
             machine that can reach {address}, not only this one"
        );
    }
    println!("serving the player at http://{address}/ (Ctrl-C to stop)");
    use std::io::Write;
    std::io::stdout().flush()?;
    crate::server::serve(listener, crate::server::Site::new(files, address))
        .with_context(|| format!("serving on {address}"))
}
