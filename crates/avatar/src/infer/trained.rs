//! A trained avatar loaded from its run folder for inference: rendering new poses and views,
//! and exporting posed Gaussians.

use std::path::Path;

use burn::tensor::Device;

use super::bake::BakedShading;
use super::report::tensor_to_image;
use super::run::{Run, RunInfo, load_face_base, read_state};
use crate::AvatarError;
use crate::model::ModelConfig;
use crate::model::posing::Skinning;
use crate::model::{
    AvatarNets, Canonical, Constants, FaceBase, STORED_SETUP, Setup, canonical, pose, render_posed,
};
use crate::model::{
    NetInputs, PcaTensors, PoseTensors, ViewFree, canonical_seen, host_values, shading, view_free,
};
use f3g_io::Image;
use f3g_rig::RigParams;
use f3g_splat::{Camera, GaussianCloud};

/// The networks, canonical face model and setup of a run, on the device it was loaded onto
/// (without autodiff).
pub struct TrainedAvatar {
    /// The run folder it was loaded from.
    dir: std::path::PathBuf,
    /// The model's configuration (the run's training settings are not needed).
    pub(crate) model: ModelConfig,
    pub info: RunInfo,
    pub setup: Setup,
    pub nets: AvatarNets,
    /// The canonical face model of the checkpoint (once training built it).
    pub face_base: Option<FaceBase>,
    /// The training poses' PCA, for unseen poses.
    pca: Option<PcaTensors>,
    constants: Constants,
    device: Device,
    /// The training step of the loaded checkpoint.
    pub step: u64,
}

impl TrainedAvatar {
    /// Loads the newest checkpoint of `run_dir` onto `device` (any device: a checkpoint does
    /// not remember where it was trained). Everything comes from the run folder — the model
    /// configuration, the stored setup (body model, template, tables), the pose PCA, the
    /// networks — so a run copied to a machine without the body model's files or the capture
    /// works. A run folder of another format ([`super::RUN_FORMAT`]) is an error naming it.
    pub fn load(run_dir: &Path, device: &Device) -> Result<Self, AvatarError> {
        let run = Run::new(run_dir);
        let config_path = run.config_path();
        if !config_path.exists() {
            return Err(run.not_a_run());
        }
        let model = ModelConfig::from_file(&config_path)?;
        let info = run.info()?;
        let checkpoint = run
            .latest()?
            .ok_or_else(|| AvatarError::file(run_dir, "has no checkpoint yet: train it first"))?;
        let step = read_state(&checkpoint)?.step;
        if !Setup::stored_in(run.dir()) {
            return Err(AvatarError::file(
                run_dir,
                format!(
                    "lacks its stored setup ({}), which inference reads instead of the body \
                     model's files: retrain with this version of f3g (`f3g train`)",
                    STORED_SETUP.join(", ")
                ),
            ));
        }
        let setup = Setup::read(run.dir(), &model)?;
        let device = device.clone().without_autodiff();
        let nets = f3g_nets::checkpoint::load(
            AvatarNets::new(&model, 0, &setup, &device)?,
            &checkpoint.join("nets.bpk"),
        )?;
        let face_path = checkpoint.join("face_base.npz");
        let face_base = if face_path.exists() {
            Some(load_face_base(&face_path, setup.face_count())?)
        } else {
            None
        };
        let pca = if run.pca_path().exists() {
            let p = run.pca()?;
            if p.mean.len() != 3 * setup.body_count() {
                return Err(AvatarError::file(
                    &run.pca_path(),
                    format!(
                        "has {} values per map, the avatar {} Gaussians",
                        p.mean.len(),
                        setup.body_count()
                    ),
                ));
            }
            Some(PcaTensors::new(&p, &device))
        } else {
            None
        };
        let constants = Constants::new(&setup, &model, face_base.as_ref(), &device);
        Ok(Self {
            dir: run.dir().to_path_buf(),
            model,
            info,
            setup,
            nets,
            face_base,
            pca,
            constants,
            device,
            step,
        })
    }

    /// The training frames' body parameters (the run's `poses.npz`).
    pub fn training_poses(&self) -> Result<Vec<RigParams>, AvatarError> {
        let path = Run::new(&self.dir).poses_path();
        Ok(f3g_rig::sequence::read(&path, &self.setup.rig)?)
    }

    /// The device the avatar computes on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Number of Gaussians rendered (body + face when the face model exists).
    pub fn gaussian_count(&self) -> usize {
        self.setup.body_count()
            + if self.constants.has_face() {
                self.setup.face_count()
            } else {
                0
            }
    }

    pub(crate) fn canonical_for(
        &self,
        params: &RigParams,
        camera: &Camera,
        use_pca: bool,
    ) -> Result<(Canonical, Skinning), AvatarError> {
        let (c, inputs) = self.canonical_with_inputs(params, camera, use_pca)?;
        Ok((c, inputs.skinning))
    }

    /// The canonical Gaussians of `params` seen from `camera` and the networks' inputs they
    /// came from (the displacement by blend shapes and correctives, the skinning).
    pub(crate) fn canonical_with_inputs(
        &self,
        params: &RigParams,
        camera: &Camera,
        use_pca: bool,
    ) -> Result<(Canonical, NetInputs), AvatarError> {
        let (pose, pca) = self.pose_tensors(params, use_pca)?;
        let inputs = self.constants.inputs(&pose, camera, None, pca)?;
        let c = canonical(&self.nets, &self.constants, &inputs)?;
        Ok((c, inputs))
    }

    /// `params` checked and on the device, with the PCA its body map is projected onto when
    /// `use_pca` (unseen poses).
    fn pose_tensors(
        &self,
        params: &RigParams,
        use_pca: bool,
    ) -> Result<(PoseTensors, Option<&PcaTensors>), AvatarError> {
        self.setup.check_params(params, "pose")?;
        let pca = if use_pca { self.pca.as_ref() } else { None };
        Ok((self.setup.pose(params)?.upload(&self.device), pca))
    }

    /// One pose to be seen from several views ([`PoseViews::seen_from`]): the networks that
    /// do not see the camera run here, once.
    pub(crate) fn views_of(
        &self,
        params: &RigParams,
        use_pca: bool,
    ) -> Result<PoseViews<'_>, AvatarError> {
        let (pose, pca) = self.pose_tensors(params, use_pca)?;
        // Any camera: the view-free networks do not read the view maps.
        let anywhere = Camera::look_at([0.0, 0.0, 1e3], [0.0; 3], [0.0, 1.0, 0.0], 500.0, 64, 64);
        let inputs = self.constants.inputs(&pose, &anywhere, None, pca)?;
        let free = view_free(&self.nets, &self.constants, &inputs)?;
        Ok(PoseViews {
            avatar: self,
            pose,
            pca,
            free,
        })
    }

    /// The head maps of the face Gaussians when they are rendered (the face branch and its
    /// canonical face model exist): their tables follow the body's.
    fn rendered_head(&self) -> Option<&f3g_template::HeadMaps> {
        self.setup
            .head
            .as_ref()
            .filter(|_| self.constants.has_face())
    }

    /// The light fixed in the world (with `world_shading`): its `[9, 3]` coefficients
    /// ([`crate::model::shading`]) and every rendered Gaussian's canonical unit normal (body,
    /// then face), which skinning turns into the normal the light falls on.
    pub fn world_light(&self) -> Option<BakedShading> {
        let p = self.nets.body.shading.as_ref()?;
        let mut normals = self.setup.maps.normals.clone();
        if let Some(h) = self.rendered_head() {
            normals.extend(&h.normals);
        }
        Some(BakedShading {
            coefficients: host_values(shading::coefficients(p)),
            normals: normals
                .iter()
                .flat_map(|n| n.normalize_or_zero().to_array())
                .collect(),
        })
    }

    /// The skin weights of every rendered Gaussian (body, then face), as the setup holds them.
    pub fn skin(&self) -> f3g_rig::SkinWeights {
        let mut skin = self.setup.maps.skin.clone();
        if let Some(h) = self.rendered_head() {
            skin.joints.extend(&h.skin.joints);
            skin.weights.extend(&h.skin.weights);
        }
        skin
    }

    /// Renders body parameters from `camera` over `background`. With `use_pca`, the posed map
    /// is projected onto the training poses' principal components first (for unseen poses).
    pub fn render(
        &self,
        params: &RigParams,
        camera: &Camera,
        background: [f32; 3],
        use_pca: bool,
    ) -> Result<Image, AvatarError> {
        let (c, skinning) = self.canonical_for(params, camera, use_pca)?;
        let out = render_posed(&c, &skinning, camera, background, &self.device)?;
        Ok(tensor_to_image(out.color))
    }

    /// [`Self::render`]'s layers (colour over black, coverage, depth) for compositing.
    pub fn render_layers(
        &self,
        params: &RigParams,
        camera: &Camera,
        use_pca: bool,
    ) -> Result<super::eval::Layers, AvatarError> {
        let (c, skinning) = self.canonical_for(params, camera, use_pca)?;
        let out = render_posed(&c, &skinning, camera, [0.0; 3], &self.device)?;
        Ok(super::eval::Layers::new(
            tensor_to_image(out.color),
            host_values(out.alpha),
            host_values(out.depth),
        ))
    }

    /// The posed Gaussians of a frame with their colour as seen from `camera` (SH degree 0,
    /// zero-padded to the degree-3 layout that every 3DGS tool reads), for the per-frame `.ply`
    /// files of an animation; [`super::export::export_cloud`] keeps the view dependence.
    pub fn posed_cloud(
        &self,
        params: &RigParams,
        camera: &Camera,
        use_pca: bool,
    ) -> Result<GaussianCloud, AvatarError> {
        let (c, skinning) = self.canonical_for(params, camera, use_pca)?;
        let (means, quats) = pose(&c, &skinning);
        let colours = host_values(c.lit_colours());
        Ok(GaussianCloud {
            means: host_values(means),
            log_scales: host_values(c.log_scales),
            quats: host_values(quats),
            opacity_logits: host_values(c.opacity_logits),
            sh: colours
                .iter()
                .map(|x| (x - 0.5) / f3g_splat::sh::SH_C0 as f32)
                .collect(),
            sh_degree: 0,
        }
        .padded_to_degree(3))
    }
}

/// One pose of a [`TrainedAvatar`] with the outputs of its networks that do not see the camera
/// ([`TrainedAvatar::views_of`]).
pub(crate) struct PoseViews<'a> {
    avatar: &'a TrainedAvatar,
    pose: PoseTensors,
    pca: Option<&'a PcaTensors>,
    free: ViewFree,
}

impl PoseViews<'_> {
    /// The canonical Gaussians of the pose seen from `camera` and the networks' inputs, as
    /// [`TrainedAvatar::canonical_with_inputs`] gives them, running only the colour networks.
    pub(crate) fn seen_from(&self, camera: &Camera) -> Result<(Canonical, NetInputs), AvatarError> {
        let a = self.avatar;
        let inputs = a.constants.inputs(&self.pose, camera, None, self.pca)?;
        let c = canonical_seen(&a.nets, &a.constants, &inputs, &self.free)?;
        Ok((c, inputs))
    }
}
