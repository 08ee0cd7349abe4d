//! Putting a run together on its devices: the networks, optimisers and discriminator, from a
//! checkpoint when there is one (a new run may start its discriminator from pretrained
//! weights), replicated onto every device from the first one's state.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use burn::module::Module;
use burn::tensor::Device;

use super::config::TrainConfig;
use super::run::load_optim;
use super::schedule::Schedule;
use super::step::{AllReduce, Optimisers, Replica, adam, adam_disc};
use super::{Trainer, first_device};
use crate::AvatarError;
use crate::infer::{Run, TrainState};
use crate::model::Setup;
use crate::model::{AvatarNets, Constants, FaceBase};
use f3g_data::Dataset;
use f3g_data::loader::ImageCache;
use f3g_data::split::{Protocol, Split, SplitKind, preset};

impl Trainer {
    #[allow(clippy::too_many_arguments)]
    pub(super) fn assemble(
        run: Run,
        config: TrainConfig,
        setup: Setup,
        dataset: Arc<Dataset>,
        split: Split,
        state: TrainState,
        checkpoint: Option<PathBuf>,
        face_base: Option<FaceBase>,
        devices: &[Device],
    ) -> Result<Self, AvatarError> {
        let device = first_device(devices)?.without_autodiff().autodiff();
        let mut nets = AvatarNets::new(&config.model, config.seed, &setup, &device)?;
        let mut optimisers = Optimisers {
            body: adam(config.adam_epsilon),
            face: config.model.face_branch.then(|| adam(config.adam_epsilon)),
            disc: None,
        };
        let with_disc = config.face_losses && config.adversarial;
        let mut disc = if with_disc {
            let d = f3g_nets::checkpoint::with_deterministic_ids(
                config
                    .discriminator
                    .init(config.seed.wrapping_add(20), &device)?,
                crate::model::DISCRIMINATOR_PARAM_IDS,
            );
            // A new run may start from pretrained discriminator weights; a resumed one has its
            // own in the checkpoint.
            Some(match (&config.discriminator_weights, &checkpoint) {
                (Some(path), None) => f3g_nets::checkpoint::load(d, Path::new(path))?,
                _ => d,
            })
        } else {
            None
        };
        optimisers.disc = with_disc.then(adam_disc);
        if let Some(c) = &checkpoint {
            nets = f3g_nets::checkpoint::load(nets, &c.join("nets.bpk"))?;
            optimisers.body = load_optim(optimisers.body, &c.join("optim_body.bpk"), &nets.body)?;
            if let Some(face) = nets.face.as_ref()
                && let Some(o) = optimisers.face.take()
            {
                let path = c.join("optim_face.bpk");
                optimisers.face = Some(if path.exists() {
                    load_optim(o, &path, face)?
                } else {
                    o
                });
            }
            if let Some(d) = disc.take() {
                let path = c.join("disc.bpk");
                disc = Some(if path.exists() {
                    let d = f3g_nets::checkpoint::load(d, &path)?;
                    if let Some(o) = optimisers.disc.take() {
                        optimisers.disc = Some(load_optim(o, &c.join("optim_disc.bpk"), &d)?);
                    }
                    d
                } else {
                    d
                });
            }
        }
        let mut replicas = Vec::with_capacity(devices.len());
        for (rank, d) in devices.iter().enumerate() {
            let d = d.clone().without_autodiff().autodiff();
            // Every replica starts from the first one's weights and optimiser state (random
            // initialisation differs between backends); optimiser state follows its
            // parameters to their device on the first step.
            let (n, dc) = if rank == 0 {
                (nets.clone(), disc.clone())
            } else {
                (nets.clone().fork(&d), disc.clone().map(|x| x.fork(&d)))
            };
            replicas.push(Replica {
                constants: Constants::new(&setup, &config.model, face_base.as_ref(), &d),
                lpips: f3g_nets::Lpips::load(config.lpips_net, &d)?,
                nets: n,
                disc: dc,
                optimisers: optimisers.clone(),
                device: d,
            });
        }
        // Checkpoints from now on are written by these devices.
        let mut state = state;
        state.device = devices
            .iter()
            .map(|d| format!("{:?}", d.clone().without_autodiff()))
            .collect::<Vec<_>>()
            .join(",");
        state.replicas = devices.len() as u64;
        let validation_view = preset(
            Protocol::of(&dataset),
            SplitKind::NovelView,
            dataset.cameras.len(),
            dataset.frames(),
        )
        .ok()
        .and_then(|s| {
            s.frames
                .iter()
                .flat_map(|&f| s.cameras.iter().map(move |&c| (c, f)))
                .find(|&(c, f)| dataset.has_image(c, f))
        });
        let cache_bytes = config.cache_bytes;
        Ok(Self {
            schedule: Schedule::new(&config),
            config,
            run,
            setup: Arc::new(setup),
            dataset,
            split,
            replicas,
            all_reduce: AllReduce::Host,
            face_base,
            state,
            last_checkpoint: checkpoint,
            validation_view,
            image_cache: Arc::new(Mutex::new(ImageCache::new(cache_bytes))),
        })
    }
}
