//! The networks' inputs for one frame seen from one camera: posed position maps, view maps,
//! the template displacement and the skinning transforms of every Gaussian. Training,
//! evaluation and animation all build them here from the [`Setup`], on the device they are
//! given.

use burn::tensor::{Device, Tensor, TensorData};

use crate::AvatarError;
use crate::model::Constants;
use crate::setup::Setup;
use f3g_rig::PointTransform;

/// Everything the networks need for one (frame, camera), as tensors.
pub struct NetInputs {
    pub body_map: Tensor<4>,
    pub body_view: (Tensor<4>, Tensor<4>),
    pub face_map: Option<Tensor<4>>,
    pub face_view: Option<(Tensor<4>, Tensor<4>)>,
    /// `[N, 3]` canonical displacement of every Gaussian by the frame's blend shapes and
    /// correctives (body then face).
    pub displacement: Tensor<2>,
    /// Skinning transforms of every Gaussian (body then face).
    pub transforms: Vec<PointTransform>,
}

/// The network inputs for body parameters seen from `camera`. With `pca`, the body's posed map
/// is first projected onto the training poses' principal components (Animatable Gaussians'
/// treatment of unseen poses; the head maps are used as they are).
pub fn inputs_for(
    setup: &Setup,
    constants: &Constants,
    params: &f3g_rig::RigParams,
    camera: &f3g_splat::Camera,
    noise: Option<(f32, u64)>,
    pca: Option<&f3g_template::PosePca>,
    device: &Device,
) -> Result<NetInputs, AvatarError> {
    let frame = setup.frame(params)?;
    let mut posed_body = frame.posed_body.clone();
    if let Some(pca) = pca {
        let flat: Vec<f32> = posed_body.iter().flat_map(|v| v.to_array()).collect();
        posed_body = pca
            .project(&flat)?
            .chunks_exact(3)
            .map(glam::Vec3::from_slice)
            .collect();
    }
    let s = constants.net_input_size;
    let body_map = setup.body_input(&posed_body, s, device);
    let body_view = setup.body_view_maps(&frame, camera, s, noise, device);
    let (face_map, face_view) = match (&frame.posed_face, constants.has_face()) {
        (Some(pf), true) => {
            let f = constants.face_input_size;
            (
                Some(setup.face_input(pf, f, device)),
                Some(setup.face_view_maps(&frame, camera, f, noise, device)),
            )
        }
        _ => (None, None),
    };
    let count = setup.body_count()
        + if constants.has_face() {
            setup.face_count()
        } else {
            0
        };
    let displacement: Vec<f32> = frame.displacement[..count]
        .iter()
        .flat_map(|v| v.to_array())
        .collect();
    Ok(NetInputs {
        body_map,
        body_view,
        face_map,
        face_view,
        displacement: Tensor::from_data(TensorData::new(displacement, [count, 3]), device),
        transforms: frame.transforms[..count].to_vec(),
    })
}
