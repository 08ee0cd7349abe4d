//! The validation grid: a held-out camera of a training frame rendered with the current
//! networks, ground truth | render | error for the body and the head crop, written to
//! `validation/step-N.png` and `validation.png`.

use burn::module::Module;

use super::Trainer;
use crate::AvatarError;
use crate::infer::report;
use crate::model::{AvatarNets, Constants, canonical, render_posed};
use f3g_data::loader::LoaderOptions;

impl Trainer {
    /// Renders the validation view (a held-out camera) and writes GT | render | error grids.
    pub(super) fn validate(&self) -> Result<(), AvatarError> {
        let Some((camera, frame)) = self.validation_view else {
            return Ok(());
        };
        let r = &self.replicas[0];
        let plain = r.device.clone().without_autodiff();
        let nets = AvatarNets {
            body: r.nets.body.valid(),
            face: r.nets.face.as_ref().map(Module::valid),
        };
        let constants = Constants::new(
            &self.setup,
            &self.config.model,
            self.face_base.as_ref(),
            &plain,
        );
        let cache = std::sync::Mutex::new(f3g_data::loader::ImageCache::new(1 << 28));
        // The whole ground truth: training blanks a boundary band in it (and in the render),
        // but the grid shows the render as it is, so a blanked band would show up as an
        // outline of error around every silhouette.
        let options = LoaderOptions {
            body_scale: self.config.body_scale,
            face_size: self.config.model.face_crop_size,
            face_padding: self.config.model.face_padding,
            band_radius: 0.0,
            ..Default::default()
        };
        let (body, face, _) =
            f3g_data::loader::make_view(&self.dataset, &cache, camera, frame, &options, [1.0; 3])?;
        let pose = self.setup.pose(&self.dataset.params[frame])?.upload(&plain);
        let inputs = constants.inputs(&pose, &body.camera, None, None)?;
        let c = canonical(&nets, &constants, &inputs)?;
        let mut rows = Vec::new();
        for view in std::iter::once(&body).chain(face.as_ref()) {
            let out = render_posed(&c, &inputs.skinning, &view.camera, [1.0; 3], &plain)?;
            let render = report::tensor_to_image(out.color);
            rows.push(report::comparison_row(&view.image, &render));
        }
        let dir = self.run.dir().join("validation");
        std::fs::create_dir_all(&dir).map_err(|e| AvatarError::file(&dir, e))?;
        let grid = report::stack_rows(&rows);
        f3g_io::write_png(&dir.join(format!("step-{:09}.png", self.state.step)), &grid)?;
        f3g_io::write_png(&self.run.dir().join("validation.png"), &grid)?;
        Ok(())
    }
}
