//! The losses of paper §3.5, as tensors on the training device.
//!
//! - **pretrain**: L1 between the body network's activated attributes and the initial ones.
//! - **body**: L1 on the full (down-scaled) render, LPIPS on the mask-bounding-box square
//!   (padded with the background, as Animatable Gaussians crops), and the offset regulariser.
//! - **face**: on the head crop rendered with its own intrinsics, L1, LPIPS and the
//!   non-saturating adversarial loss of the (frozen, for this term) discriminator.
//!
//! Every term is returned already weighted, by name, so that the log shows what the total is
//! made of. In the boundary band the render is replaced by the background, as in the ground
//! truth.

use burn::module::Module;
use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Tensor, TensorData};

use super::config::TrainConfig;
use super::profile::{Phase, PhaseTimer, mark};
use super::sample::{DeviceSample, DeviceView};
use crate::AvatarError;
use crate::model::NetInputs;
use crate::model::{Canonical, Constants, nchw, render_posed};
use f3g_data::imgops::CentredSquare;
use f3g_nets::discriminator::generator_loss;
use f3g_nets::layers::resize;
use f3g_nets::metrics::l1_loss;
use f3g_nets::{Discriminator, Lpips};

/// Named, weighted loss terms of one sample.
pub type Terms = Vec<(String, Tensor<1>)>;

/// What the losses of one step read: the configuration, the setup's tensors, the perceptual
/// network and the discriminator, all on `device`.
pub struct Losses<'a> {
    pub config: &'a TrainConfig,
    pub constants: &'a Constants,
    pub lpips: &'a Lpips,
    pub disc: Option<&'a Discriminator>,
    pub device: &'a Device,
    /// The step, for the error a diverged network gives.
    pub step: u64,
    /// Times the phases when `f3g bench train` asks.
    pub timer: Option<&'a PhaseTimer>,
}

impl Losses<'_> {
    /// L1 between the body network's activated attributes and the initial ones (zero offsets,
    /// grey colour, opacity 0.1, the k-NN scales, identity rotations). Animatable Gaussians
    /// leaves the colour out; starting from grey instead of the untrained network's colour
    /// noise shortens the short CPU schedules noticeably.
    pub fn pretrain(&self, raw: &Tensor<2>) -> Tensor<1> {
        let n = raw.dims()[0];
        let col = |a: usize, b: usize| raw.clone().slice([0..n, a..b]);
        let offsets = col(0, 3).abs().mean() + col(3, 6).abs().mean();
        let o0 = self.config.model.initial_opacity;
        let opacity = (sigmoid(col(6, 7) + crate::model::logit(o0)) - o0)
            .abs()
            .mean();
        let (base, base_quats) = self.constants.initial_body();
        let scales = ((base.clone() + col(7, 10)).exp() - base.exp())
            .abs()
            .mean();
        let q = col(10, 14) + base_quats.clone();
        let norm = (q.clone().powf_scalar(2.0).sum_dim(1) + 1e-12).sqrt();
        let rotation = (q / norm - base_quats).abs().mean();
        offsets + opacity + scales + rotation
    }

    /// Renders the body view: L1, LPIPS on the mask box, offset regulariser.
    pub fn body(
        &self,
        c: &Canonical,
        inputs: &NetInputs,
        sample: &DeviceSample,
        terms: &mut Terms,
    ) -> Result<(), AvatarError> {
        let w = &self.config.losses;
        let view = &sample.body;
        let pred = self.render_view(c, inputs, view, sample.background)?;
        mark(self.timer, Phase::Render)?;
        let gt = view.image.clone();
        terms.push(("l1".into(), l1_loss(pred.clone(), gt.clone()) * w.l1));
        if w.lpips > 0.0
            && let Some(square) = &view.square
        {
            let size = self.config.lpips_size;
            let bg = sample.background;
            let crop = |t: Tensor<4>| resize(square_crop(t, square, bg), size, size);
            let d = self.lpips.forward(crop(pred), crop(gt))?.mean();
            terms.push(("lpips".into(), d * w.lpips));
            mark(self.timer, Phase::Lpips)?;
        }
        let mut offset = offset_norm(c.body_offsets.clone());
        if let Some(f) = &c.face_offsets {
            offset = offset + offset_norm(f.clone());
        }
        terms.push(("offset".into(), offset * w.offset));
        Ok(())
    }

    /// Renders the head crop: L1, LPIPS and the adversarial loss; returns the render
    /// (detached) for the discriminator step, or `None` when the sample has no head crop.
    pub fn face(
        &self,
        c: &Canonical,
        inputs: &NetInputs,
        sample: &DeviceSample,
        terms: &mut Terms,
    ) -> Result<Option<Tensor<4>>, AvatarError> {
        let Some(view) = &sample.face else {
            return Ok(None);
        };
        let w = &self.config.losses;
        let pred = self.render_view(c, inputs, view, sample.background)?;
        mark(self.timer, Phase::Render)?;
        let gt = view.image.clone();
        terms.push((
            "face_l1".into(),
            l1_loss(pred.clone(), gt.clone()) * w.face_l1,
        ));
        if w.face_lpips > 0.0 {
            let d = self.lpips.forward(pred.clone(), gt)?.mean();
            terms.push(("face_lpips".into(), d * w.face_lpips));
            mark(self.timer, Phase::Lpips)?;
        }
        if let Some(d) = self.disc {
            let frozen = d.clone().no_grad();
            let g = generator_loss(frozen.forward(pred.clone())?);
            terms.push(("adversarial".into(), g * w.adversarial));
            mark(self.timer, Phase::Adversarial)?;
        }
        Ok(Some(pred.detach()))
    }

    /// The posed Gaussians rendered into `view`, `[1, 3, H, W]`, with the boundary band set to
    /// the background.
    fn render_view(
        &self,
        c: &Canonical,
        inputs: &NetInputs,
        view: &DeviceView,
        background: [f32; 3],
    ) -> Result<Tensor<4>, AvatarError> {
        let out = render_posed(c, &inputs.skinning, &view.camera, background, self.device)
            .map_err(|e| match e {
                // Diverged networks produce non-finite Gaussians before any loss sees them.
                AvatarError::Splat(f3g_splat::SplatError::NonFinite { name, value, .. }) => {
                    AvatarError::NonFinite {
                        step: self.step,
                        name: format!("gaussians.{name}"),
                        value: value as f32,
                        checkpoint: None,
                    }
                }
                other => other,
            })?;
        let pred = nchw(out.color);
        let band = view.band.clone();
        let bg = Tensor::<4>::from_data(
            TensorData::new(background.to_vec(), [1, 3, 1, 1]),
            self.device,
        );
        Ok(pred * (band.clone() * -1.0 + 1.0) + bg * band)
    }
}

/// Mean length of per-Gaussian offsets (smooth at zero).
fn offset_norm(offsets: Tensor<2>) -> Tensor<1> {
    (offsets.powf_scalar(2.0).sum_dim(1) + 1e-12).sqrt().mean()
}

/// The LPIPS square of Animatable Gaussians cut from `[1, 3, H, W]`: the mask's box, padded
/// with the background colour to the square (never clipped, so portrait frames keep the head).
fn square_crop(t: Tensor<4>, square: &CentredSquare, background: [f32; 3]) -> Tensor<4> {
    let [x0, y0, x1, y1] = square.bounds;
    let device = t.device();
    let region = t.slice([0..1, 0..3, y0..y1, x0..x1]);
    let fill = |h: usize, w: usize| {
        Tensor::<4>::from_data(TensorData::new(background.to_vec(), [1, 3, 1, 1]), &device)
            .expand([1, 3, h, w])
    };
    let (w, h, side) = (x1 - x0, y1 - y0, square.side);
    let (left, top) = (
        (x0 as i64 - square.x0) as usize,
        (y0 as i64 - square.y0) as usize,
    );
    let mut row = vec![region];
    if left > 0 {
        row.insert(0, fill(h, left));
    }
    if side - w - left > 0 {
        row.push(fill(h, side - w - left));
    }
    let mut column = vec![Tensor::cat(row, 3)];
    if top > 0 {
        column.insert(0, fill(top, side));
    }
    if side - h - top > 0 {
        column.push(fill(side - h - top, side));
    }
    Tensor::cat(column, 2)
}
