//! The pose PCA of a run: fitted once, when the run is created, on the networks' posed body
//! maps of up to 300 training frames; inference projects unseen poses onto it
//! ([`crate::model::PcaTensors`]).

use burn::tensor::Device;

use crate::AvatarError;
use crate::model::GaussianTables;
use crate::model::Setup;
use crate::model::host_values;
use f3g_template::PosePca;

/// Fits the pose PCA on the networks' posed body maps of `frames` (root-relative, computed on
/// `device` as in training).
pub fn fit_pose_pca(
    setup: &Setup,
    frames: &[f3g_rig::RigParams],
    components: usize,
    sigma: f32,
    device: &Device,
) -> Result<PosePca, AvatarError> {
    // The posed maps in f32, their centred copy in f64, and the components.
    let values = 3 * setup.body_count() as u64;
    f3g_io::memory::ensure_available(
        values * 12 * (frames.len() as u64 + components as u64),
        &format!(
            "the pose PCA of {} frames × {} body Gaussians (training frames, map_resolution)",
            frames.len(),
            setup.body_count()
        ),
    )?;
    let tables = GaussianTables::new(setup, 1, 1, device);
    let samples = frames
        .iter()
        .map(|p| {
            let pose = setup.pose(p)?.upload(device);
            let (_, _, posed) = tables.posed_body(&pose);
            Ok(host_values(posed))
        })
        .collect::<Result<Vec<_>, AvatarError>>()?;
    Ok(PosePca::fit(&samples, components, sigma)?)
}
