//! `f3g bench lbs`: the LBS of a training step on the built-in human, timed.

use std::time::Instant;

use anyhow::{Result, ensure};
use burn::tensor::{Tensor, TensorData};
use clap::Args;
use f3g_avatar::model::posing::{Skinning, Taps, affine_tensor, pose_gaussians};

use super::{median, millis};
use crate::device::DeviceArg;

/// Bytes `bench lbs` holds per Gaussian, an upper estimate: the skin lists and taps (~250 B),
/// the gathered joint transforms of 8 influences (384 B), the blend and the polar iteration's
/// temporaries (~300 B), the quaternion candidates (~100 B), inputs and posed outputs (56 B),
/// slack.
const LBS_BYTES_PER_GAUSSIAN: u64 = 1500;

/// Options of `f3g bench lbs`.
#[derive(Args, Debug)]
pub struct LbsBenchArgs {
    /// Number of Gaussians to skin (at most 100 million).
    #[arg(long, default_value_t = 400_000, value_parser = crate::bounds::size::<1, 100_000_000>)]
    pub points: usize,
    /// Timed repetitions (the median is reported).
    #[arg(long, default_value_t = 7)]
    pub repeats: usize,
    #[command(flatten)]
    pub device: DeviceArg,
}

/// Times the LBS of a training step on the built-in human: `rig.pose` (joint transforms, host),
/// the per-Gaussian blended transforms with their nearest rotations and quaternions
/// ([`f3g_avatar::model::posing::Skinning`], on `--device`, from the uploaded joint transforms) and
/// [`f3g_avatar::model::posing::pose_gaussians`] (the tensor LBS of means and rotations), each until the
/// device is done.
pub fn run(args: &LbsBenchArgs) -> Result<()> {
    ensure!(args.repeats > 0, "--repeats must be at least 1");
    f3g_io::memory::ensure_available(
        args.points as u64 * LBS_BYTES_PER_GAUSSIAN,
        &format!("--points {}", args.points),
    )?;
    let device = args.device.open()?;
    let sync = |what: &str| {
        device
            .sync()
            .map_err(|e| anyhow::anyhow!("{what} on {}: {e:?}", args.device))
    };
    let human = f3g_rig::builtin::load()?;
    let rig = &human.rig;
    let mut params = rig.zero_params();
    for (i, p) in params.pose.iter_mut().enumerate() {
        *p = 0.2 * ((i * 37 % 11) as f32 / 11.0 - 0.5);
    }
    // Gaussians: copies of the mesh vertices with their skin weights.
    let n = rig.mesh.vertices.len();
    let index: Vec<usize> = (0..args.points).map(|i| i % n).collect();
    let skin = Taps::skin(&rig.skin.select(&index), &device);
    let means: Vec<f32> = index
        .iter()
        .flat_map(|&i| rig.mesh.vertices[i].to_array())
        .collect();
    let means = Tensor::<2>::from_data(TensorData::new(means, [args.points, 3]), &device);
    let quats = Tensor::<2>::from_data(
        TensorData::new(
            [1.0f32, 0.0, 0.0, 0.0].repeat(args.points),
            [args.points, 4],
        ),
        &device,
    );
    let (mut pose_ms, mut skin_ms, mut lbs_ms) = (Vec::new(), Vec::new(), Vec::new());
    for rep in 0..=args.repeats {
        let start = Instant::now();
        let posed = rig.pose(&params)?;
        let t_pose = millis(start);
        let start = Instant::now();
        let skinning = Skinning::new(&affine_tensor(&posed.skinning, &device), &skin);
        sync("skinning")?;
        let t_skin = millis(start);
        let start = Instant::now();
        let (m, q) = pose_gaussians(means.clone(), quats.clone(), &skinning);
        std::hint::black_box((m, q));
        sync("posing")?;
        let t_lbs = millis(start);
        if rep > 0 {
            pose_ms.push(t_pose);
            skin_ms.push(t_skin);
            lbs_ms.push(t_lbs);
        }
    }
    let per = |ms: f64| ms * 1e6 / args.points as f64;
    let (skinning, lbs) = (median(skin_ms), median(lbs_ms));
    println!(
        "built-in human ({} vertices, {} joints), {} Gaussians, {} host threads, on {}:\n  \
         pose (joint transforms, host) {:.2} ms\n  \
         upload of the joint transforms + blended transforms + nearest rotations {:.1} ms ({:.0} ns per Gaussian)\n  \
         tensor LBS of means and rotations {:.1} ms ({:.0} ns per Gaussian)",
        n,
        rig.skeleton.len(),
        args.points,
        rayon::current_num_threads(),
        args.device,
        median(pose_ms),
        skinning,
        per(skinning),
        lbs,
        per(lbs),
    );
    Ok(())
}
