//! A training sample on its replica's device. The loader's worker thread prepares it: after
//! decoding, cropping and compositing the images (`f3g_data::loader`), it poses the body model
//! for the frame, draws the view noise and uploads all of it, so that a step only computes.

use burn::tensor::{Device, Tensor, TensorData};

use crate::AvatarError;
use crate::config::TrainConfig;
use crate::inputs::{PoseTensors, view_noise};
use crate::setup::Setup;
use f3g_data::imgops::CentredSquare;
use f3g_data::loader::{Sample, View};
use f3g_nets::metrics::image_tensor;
use f3g_splat::Camera;

/// One camera's view of the sample, on the device.
pub struct DeviceView {
    pub camera: Camera,
    /// `[1, 3, H, W]` ground truth (background composited, boundary band blanked).
    pub image: Tensor<4>,
    /// `[1, 1, H, W]`: 1 in the boundary band, 0 elsewhere.
    pub band: Tensor<4>,
    /// The LPIPS square around the mask (body views).
    pub square: Option<CentredSquare>,
}

impl DeviceView {
    fn upload(view: &View, device: &Device) -> Self {
        let (h, w) = (view.image.height, view.image.width);
        let band: Vec<f32> = view.band.iter().map(|&b| b as u8 as f32).collect();
        Self {
            camera: view.camera.clone(),
            image: image_tensor(&view.image, device),
            band: Tensor::from_data(TensorData::new(band, [1, 1, h, w]), device),
            square: CentredSquare::around_mask(&view.mask, 0),
        }
    }
}

/// A training sample uploaded to one device.
pub struct DeviceSample {
    /// The sample's index (samples are a pure function of the seed and the index).
    pub index: u64,
    pub frame: usize,
    pub camera: usize,
    pub background: [f32; 3],
    pub pose: PoseTensors,
    /// `[N, 3]` view-direction noise of every Gaussian (`None` when `view_noise` is 0).
    pub noise: Option<Tensor<2>>,
    pub body: DeviceView,
    /// `None` when the head is not in view.
    pub face: Option<DeviceView>,
}

impl DeviceSample {
    /// Poses, draws and uploads `sample` for `device`.
    pub fn prepare(
        setup: &Setup,
        config: &TrainConfig,
        sample: Sample,
        device: &Device,
    ) -> Result<Self, AvatarError> {
        let pose = setup.pose(&sample.params)?.upload(device);
        let noise = (config.view_noise > 0.0).then(|| {
            // A pure function of the seed and the sample, like the sample itself.
            let seed = config.seed ^ sample.index.wrapping_mul(0x2545_f491_4f6c_dd1d);
            let count = setup.body_count() + setup.face_count();
            Tensor::from_data(
                TensorData::new(view_noise(seed, count, config.view_noise), [count, 3]),
                device,
            )
        });
        Ok(Self {
            index: sample.index,
            frame: sample.frame,
            camera: sample.camera,
            background: sample.background,
            pose,
            noise,
            body: DeviceView::upload(&sample.body, device),
            face: sample.face.as_ref().map(|v| DeviceView::upload(v, device)),
        })
    }
}
