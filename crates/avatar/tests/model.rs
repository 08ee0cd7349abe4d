//! The avatar model on the built-in human, untrained: the camera reaches colours only (with the
//! split and three-network layouts, not with the single network kept for comparison), and the
//! networks do not see finger articulation.

use burn::tensor::{Device, Tensor};
use f3g_avatar::TrainConfig;
use f3g_avatar::config::BodyLayout;
use f3g_avatar::inputs::inputs_for;
use f3g_avatar::model::{AvatarNets, Canonical, Constants, canonical};
use f3g_avatar::setup::Setup;
use f3g_rig::RigParams;
use f3g_splat::Camera;

/// The cpu preset at a size that builds in a second.
fn small(layout: BodyLayout) -> TrainConfig {
    let mut c = TrainConfig::cpu();
    c.map_resolution = 32;
    c.face_branch = false;
    c.face_losses = false;
    c.body_layout = layout;
    c.body_net.input_size = 16;
    c.body_net.output_size = 32;
    c.body_net.max_channels = 8;
    c.body_net.channel_base = 128;
    c.body_net.style_dim = 8;
    c.body_net.middle_size = 4;
    c.validate().unwrap();
    c
}

fn camera(yaw: f64) -> Camera {
    let eye = [3.0 * yaw.sin(), 0.3, 3.0 * yaw.cos()];
    Camera::look_at(eye, [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 200.0, 96, 128)
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec::<f32>().unwrap()
}

/// The canonical Gaussians of `params` seen from `camera`.
fn gaussians(config: &TrainConfig, params: &RigParams, camera: &Camera) -> Canonical {
    let device = Device::flex();
    let rig = f3g_rig::ModelSpec::Builtin.load().unwrap();
    let setup = Setup::new("builtin", &rig.zero_params().identity, config).unwrap();
    let nets = AvatarNets::new(config, &setup, &device).unwrap();
    let constants = Constants::new(&setup, config, None, &device);
    let inputs = inputs_for(&setup, &constants, params, camera, None, None, &device).unwrap();
    canonical(&nets, &constants, &inputs).unwrap()
}

fn max_difference(a: Vec<f32>, b: Vec<f32>) -> f32 {
    a.iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Max differences of (geometry, colour) between two cameras at one pose.
fn camera_effect(layout: BodyLayout) -> (f32, f32) {
    let config = small(layout);
    let rig = f3g_rig::ModelSpec::Builtin.load().unwrap();
    let params = rig.zero_params();
    let (a, b) = (
        gaussians(&config, &params, &camera(0.0)),
        gaussians(&config, &params, &camera(2.0)),
    );
    let geometry = [
        max_difference(host(a.means), host(b.means)),
        max_difference(host(a.log_scales), host(b.log_scales)),
        max_difference(host(a.quats), host(b.quats)),
        max_difference(host(a.opacity_logits), host(b.opacity_logits)),
    ]
    .into_iter()
    .fold(0.0, f32::max);
    (geometry, max_difference(host(a.colours), host(b.colours)))
}

#[test]
fn the_camera_changes_colours_only() {
    for layout in [BodyLayout::Split, BodyLayout::Three] {
        let (geometry, colour) = camera_effect(layout);
        assert_eq!(geometry, 0.0, "{layout:?}: the camera moved the geometry");
        assert!(colour > 1e-4, "{layout:?}: the colours ignore the view");
    }
    // The single view-conditioned network (the old design) lets the camera move everything.
    let (geometry, _) = camera_effect(BodyLayout::Single);
    assert!(geometry > 1e-4, "{geometry}");
}

#[test]
fn the_networks_do_not_see_the_fingers() {
    let config = small(BodyLayout::Split);
    let rig = f3g_rig::ModelSpec::Builtin.load().unwrap();
    let fingers = rig.finger_params();
    let names = rig.pose_param_names();
    assert!(
        fingers.iter().all(|&i| names[i].starts_with("finger")
            || names[i].starts_with("thumb")
            || names[i].starts_with("metacarpal")),
        "{:?}",
        fingers.iter().map(|&i| &names[i]).collect::<Vec<_>>()
    );
    assert!(fingers.len() >= 30, "{}", fingers.len());
    let device = Device::flex();
    let setup = Setup::new("builtin", &rig.zero_params().identity, &config).unwrap();
    let constants = Constants::new(&setup, &config, None, &device);
    let rest = rig.zero_params();
    let mut curled = rest.clone();
    for &i in &fingers {
        curled.pose[i] = 0.8;
    }
    let mut wrist = rest.clone();
    let w = names.iter().position(|n| n == "wrist.L_rx").unwrap();
    wrist.pose[w] = 0.8;
    let cam = camera(0.0);
    let input = |p: &RigParams| {
        let i = inputs_for(&setup, &constants, p, &cam, None, None, &device).unwrap();
        (host(i.body_map), i.transforms)
    };
    let (rest_map, rest_skin) = input(&rest);
    let (curled_map, curled_skin) = input(&curled);
    // Same network input, but the Gaussians of the hands still follow the fingers.
    assert_eq!(rest_map, curled_map);
    assert_ne!(rest_skin, curled_skin);
    // The wrist is not a finger: it reaches the networks.
    assert_ne!(input(&wrist).0, rest_map);
}
