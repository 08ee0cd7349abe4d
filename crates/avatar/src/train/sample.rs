//! A training sample on its replica's device. The loader's worker thread prepares it: after
//! decoding, cropping and compositing the images (`f3g_data::loader`), it poses the body model
//! for the frame, draws the view noise and uploads all of it, so that a step only computes.

use burn::tensor::{Device, Tensor, TensorData};

use super::config::TrainConfig;
use crate::AvatarError;
use crate::model::PoseTensors;
use crate::model::Setup;
use f3g_data::imgops::CentredSquare;
use f3g_data::loader::{Sample, View};
use f3g_nets::metrics::into_image_tensor;
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
    /// Takes the view: its pixels become the image tensor's data without a copy.
    fn upload(view: View, device: &Device) -> Self {
        let (h, w) = (view.image.height, view.image.width);
        let band: Vec<f32> = view.band.iter().map(|&b| b as u8 as f32).collect();
        Self {
            square: CentredSquare::around_mask(&view.mask, 0),
            image: into_image_tensor(view.image, device),
            band: Tensor::from_data(TensorData::new(band, [1, 1, h, w]), device),
            camera: view.camera,
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
            body: DeviceView::upload(sample.body, device),
            face: sample.face.map(|v| DeviceView::upload(v, device)),
        })
    }
}

/// The view-direction noise of a training sample: `σ · N(0, 1)` per component for each of
/// `count` Gaussians, `[count, 3]` row-major. Each pair of Gaussians draws its six values from
/// a counter-based hash of `(seed, pair)`, so the noise is the same however it is computed.
/// Box–Muller in `f32`, both values of each draw used: the loader's worker draws 1.5 M values
/// per `paper` sample on the host, where the step needs the cores too.
pub fn view_noise(seed: u64, count: usize, sigma: f32) -> Vec<f32> {
    let mut noise = vec![0.0; 3 * count];
    for (pair, values) in noise.chunks_mut(6).enumerate() {
        let normals = gaussian6(seed, pair as u64);
        for (value, normal) in values.iter_mut().zip(normals) {
            *value = sigma * normal;
        }
    }
    noise
}

/// Six standard normal values from a counter-based hash (SplitMix64's finaliser).
fn gaussian6(seed: u64, pair: u64) -> [f32; 6] {
    let mut state = seed ^ pair.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    let mut uniform = || {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        // 24 bits and half a step: above 0, so `ln` is finite (the top value rounds to 1).
        ((z >> 40) as f32 + 0.5) / (1u32 << 24) as f32
    };
    let mut out = [0.0; 6];
    for two in out.chunks_mut(2) {
        let radius = (-2.0 * uniform().ln()).sqrt();
        let (sin, cos) = (std::f32::consts::TAU * uniform()).sin_cos();
        two[0] = radius * cos;
        two[1] = radius * sin;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counter_noise_is_deterministic_and_standard() {
        let a = view_noise(7, 2001, 1.0);
        assert_eq!(a.len(), 3 * 2001);
        assert_eq!(a, view_noise(7, 2001, 1.0));
        // A prefix of a longer draw: each Gaussian's values depend on its index alone.
        assert_eq!(a[..3 * 1000], view_noise(7, 1000, 1.0)[..]);
        let n = a.len() as f32;
        let mean = a.iter().sum::<f32>() / n;
        let var = a.iter().map(|v| v * v).sum::<f32>() / n;
        assert!(mean.abs() < 0.05, "{mean}");
        assert!((var - 1.0).abs() < 0.05, "{var}");
        // Standard normal quantiles: about 68.3 % within one σ, 95.4 % within two.
        let within = |k: f32| a.iter().filter(|v| v.abs() < k).count() as f32 / n;
        assert!((within(1.0) - 0.683).abs() < 0.02, "{}", within(1.0));
        assert!((within(2.0) - 0.954).abs() < 0.01, "{}", within(2.0));
        assert_ne!(a, view_noise(8, 2001, 1.0));
        let scaled = view_noise(7, 2001, 0.1);
        assert!(
            scaled
                .iter()
                .zip(&a)
                .all(|(s, v)| (s - 0.1 * v).abs() < 1e-6)
        );
    }
}
