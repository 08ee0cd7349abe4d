//! The avatar model on the built-in human, untrained: the networks' inputs computed on the
//! device equal the host's reading of the method (skinning with `f3g_rig`, maps reduced texel
//! by texel), the camera reaches colours only (with the split and three-network layouts, not
//! with the single network kept for comparison), and the networks do not see finger
//! articulation; another view of a pose from the view-free outputs equals the whole forward.

use burn::tensor::{Device, Tensor};
use f3g_avatar::model::{
    AvatarNets, BodyLayout, Canonical, Constants, FaceBase, Setup, canonical, canonical_seen,
    view_free,
};
use f3g_avatar::train::TrainConfig;
use f3g_rig::RigParams;
use f3g_splat::Camera;

/// The cpu preset at a size that builds in a second.
fn small(layout: BodyLayout) -> TrainConfig {
    let mut c = TrainConfig::cpu();
    c.model.map_resolution = 32;
    c.model.face_branch = false;
    c.face_losses = false;
    c.model.body_layout = layout;
    c.model.body_net.input_size = 16;
    c.model.body_net.output_size = 32;
    c.model.body_net.max_channels = 8;
    c.model.body_net.channel_base = 128;
    c.model.body_net.style_dim = 8;
    c.model.body_net.middle_size = 4;
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
    let setup = Setup::new("builtin", &rig.zero_params().identity, &config.model).unwrap();
    let nets = AvatarNets::new(&config.model, config.seed, &setup, &device).unwrap();
    let constants = Constants::new(&setup, &config.model, None, &device);
    let pose = setup.pose(params).unwrap().upload(&device);
    let inputs = constants.inputs(&pose, camera, None, None).unwrap();
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

/// A canonical face model of grey, small, half-opaque Gaussians at the head maps' points.
fn face_base(setup: &Setup) -> FaceBase {
    let n_face = setup.face_count();
    FaceBase {
        positions: vec![0.0; 3 * n_face],
        colours: vec![0.5; 3 * n_face],
        opacity_logits: vec![0.0; n_face],
        log_scales: vec![-4.0; 3 * n_face],
        quats: [1.0, 0.0, 0.0, 0.0].repeat(n_face),
    }
}

#[test]
fn another_view_of_a_pose_from_the_view_free_outputs_equals_the_whole_forward() {
    for layout in [BodyLayout::Split, BodyLayout::Three, BodyLayout::Single] {
        let mut config = small(layout);
        config.model.face_branch = true;
        let face = &mut config.model.face_net;
        (face.input_size, face.output_size, face.max_channels) = (16, 16, 8);
        let device = Device::flex();
        let rig = f3g_rig::ModelSpec::Builtin.load().unwrap();
        let setup = Setup::new("builtin", &rig.zero_params().identity, &config.model).unwrap();
        let nets = AvatarNets::new(&config.model, config.seed, &setup, &device).unwrap();
        let constants = Constants::new(&setup, &config.model, Some(&face_base(&setup)), &device);
        let pose = setup.pose(&rig.zero_params()).unwrap().upload(&device);
        let seen_from = |yaw| constants.inputs(&pose, &camera(yaw), None, None).unwrap();
        let (first, second) = (seen_from(0.0), seen_from(2.0));
        let free = view_free(&nets, &constants, &first).unwrap();
        let again = canonical_seen(&nets, &constants, &second, &free).unwrap();
        let whole = canonical(&nets, &constants, &second).unwrap();
        let fields = |c: Canonical| {
            [
                host(c.means),
                host(c.log_scales),
                host(c.quats),
                host(c.opacity_logits),
                host(c.colours),
            ]
        };
        let n = setup.body_count() + setup.face_count();
        let (again, whole) = (fields(again), fields(whole));
        assert_eq!(
            again[0].len(),
            3 * n,
            "{layout:?}: the face Gaussians are there"
        );
        assert_eq!(again, whole, "{layout:?}");
        // The second view's colours, not the first's.
        let first_colours = host(canonical(&nets, &constants, &first).unwrap().colours);
        assert!(
            max_difference(first_colours, whole[4].clone()) > 1e-4,
            "{layout:?}"
        );
    }
}

#[test]
fn the_networks_do_not_see_the_fingers() {
    let config = small(BodyLayout::Split);
    let rig = f3g_rig::ModelSpec::Builtin.load().unwrap();
    let fingers = rig.finger_params().unwrap();
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
    let setup = Setup::new("builtin", &rig.zero_params().identity, &config.model).unwrap();
    let constants = Constants::new(&setup, &config.model, None, &device);
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
        let pose = setup.pose(p).unwrap().upload(&device);
        let i = constants.inputs(&pose, &cam, None, None).unwrap();
        (host(i.body_map), host(i.skinning.translation))
    };
    let (rest_map, rest_skin) = input(&rest);
    let (curled_map, curled_skin) = input(&curled);
    // Same network input, but the Gaussians of the hands still follow the fingers.
    assert_eq!(rest_map, curled_map);
    assert_ne!(rest_skin, curled_skin);
    // The wrist is not a finger: it reaches the networks.
    assert_ne!(input(&wrist).0, rest_map);
}

/// The host's reading of a two-sided map input: per-Gaussian `values` at their texels of a
/// `[n, 2n]` map, each input pixel the mean of the covered texels of its footprint (`[2, C, S,
/// S]` as a flat vector: the network input's layout, front channels first).
fn host_input(values: &[Vec<f32>], pixels: &[usize], n: usize, size: usize) -> Vec<f32> {
    let c = values[0].len();
    let mut at = vec![None; 2 * n * n];
    for (g, &p) in pixels.iter().enumerate() {
        at[p] = Some(g);
    }
    // Source rows/columns of output pixel `i`: its box when down-sampling, else the texel under
    // its centre.
    let ratio = n as f32 / size as f32;
    let span = |i: usize| {
        if ratio <= 1.0 {
            let s = (((i as f32 + 0.5) * ratio) as usize).min(n - 1);
            s..s + 1
        } else {
            let a = (i as f32 * ratio).floor() as usize;
            a..(((i + 1) as f32 * ratio).ceil() as usize).min(n)
        }
    };
    let mut out = vec![0.0; 2 * c * size * size];
    for side in 0..2 {
        for y in 0..size {
            for x in 0..size {
                let at = &at;
                let covered: Vec<usize> = span(y)
                    .flat_map(|sy| span(x).filter_map(move |sx| at[sy * 2 * n + side * n + sx]))
                    .collect();
                let mut sum = vec![0.0f32; c];
                for &g in &covered {
                    for (s, v) in sum.iter_mut().zip(&values[g]) {
                        *s += v;
                    }
                }
                for (ch, s) in sum.into_iter().enumerate() {
                    out[((side * c + ch) * size + y) * size + x] = s / covered.len().max(1) as f32;
                }
            }
        }
    }
    out
}

#[test]
fn device_inputs_equal_the_host_reference() {
    let mut config = small(BodyLayout::Split);
    config.model.face_branch = true;
    config.model.face_net.input_size = 16;
    let device = Device::flex();
    let rig = f3g_rig::ModelSpec::Builtin.load().unwrap();
    let setup = Setup::new("builtin", &rig.zero_params().identity, &config.model).unwrap();
    // A pose with root motion, a turned head, an open jaw and expressions.
    let mut params = rig.zero_params();
    for (i, p) in params.pose.iter_mut().enumerate() {
        *p = 0.3 * ((i * 37 % 11) as f32 / 11.0 - 0.5);
    }
    for (i, e) in params.expression.iter_mut().enumerate() {
        *e = if i % 2 == 0 { 0.6 } else { -0.3 };
    }
    let cam = camera(0.7);
    let pose = setup.pose(&params).unwrap();
    // With a face model: the face inputs too.
    let constants = Constants::new(&setup, &config.model, Some(&face_base(&setup)), &device);
    let inputs = constants
        .inputs(&pose.upload(&device), &cam, None, None)
        .unwrap();

    // The host's reading: displacements interpolated at the texels and densified into the face,
    // skinning by `f3g_rig`, view cosines per Gaussian, maps reduced texel by texel.
    let maps = &setup.maps;
    let head = setup.head.as_ref().unwrap();
    let body_disp = maps.interpolate(&pose.displacement);
    let face_disp = head.from_body(&body_disp);
    let canon = |p: &[glam::Vec3], d: &[glam::Vec3]| -> Vec<glam::Vec3> {
        p.iter().zip(d).map(|(p, d)| *p + *d).collect()
    };
    let (body_canon, face_canon) = (
        canon(&maps.positions, &body_disp),
        canon(&head.positions, &face_disp),
    );
    let as_rows =
        |v: &[glam::Vec3]| -> Vec<Vec<f32>> { v.iter().map(|p| p.to_array().to_vec()).collect() };
    let close = |got: Vec<f32>, want: Vec<f32>, tol: f32, what: &str| {
        assert_eq!(got.len(), want.len(), "{what}");
        let worst = max_difference(got, want);
        assert!(worst < tol, "{what}: {worst}");
    };
    let posed_body = f3g_rig::skin_points(&pose.input_joints, &maps.skin, &body_canon);
    close(
        host(inputs.body_map.clone()),
        host_input(&as_rows(&posed_body), &maps.pixels, maps.resolution, 16),
        1e-5,
        "body map",
    );
    let posed_face = f3g_rig::skin_points(&pose.input_joints, &head.skin, &face_canon);
    close(
        host(inputs.face_map.clone().unwrap()),
        host_input(&as_rows(&posed_face), &head.pixels, head.size, 16),
        1e-5,
        "face map",
    );
    let skinning: Vec<_> = f3g_rig::point_transforms(&pose.joints, &maps.skin)
        .into_iter()
        .chain(f3g_rig::point_transforms(&pose.joints, &head.skin))
        .collect();
    let all_canon: Vec<glam::Vec3> = body_canon.iter().chain(&face_canon).copied().collect();
    let posed: Vec<f32> = skinning
        .iter()
        .zip(&all_canon)
        .flat_map(|(t, p)| t.affine.transform_point3(*p).to_array())
        .collect();
    close(
        host(f3g_avatar::model::posing::transform_points(
            &inputs.skinning.linear,
            &inputs.skinning.translation,
            Tensor::from_data(
                burn::tensor::TensorData::new(
                    all_canon
                        .iter()
                        .flat_map(|p| p.to_array())
                        .collect::<Vec<f32>>(),
                    [all_canon.len(), 3],
                ),
                &device,
            ),
        )),
        posed,
        1e-5,
        "posed Gaussians",
    );
    let q = host(inputs.skinning.quaternion.clone());
    for (i, t) in skinning.iter().enumerate() {
        let got = glam::Quat::from_xyzw(q[4 * i + 1], q[4 * i + 2], q[4 * i + 3], q[4 * i]);
        assert!(
            got.dot(t.rotation).abs() > 1.0 - 1e-5,
            "rotation of Gaussian {i}"
        );
    }
    close(
        host(inputs.displacement.clone()),
        body_disp
            .iter()
            .chain(&face_disp)
            .flat_map(|d| d.to_array())
            .collect(),
        1e-6,
        "displacement",
    );
    let c = cam.center();
    let centre = glam::Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32);
    let cosines = |normals: &[glam::Vec3],
                   canon: &[glam::Vec3],
                   transforms: &[f3g_rig::PointTransform]|
     -> Vec<Vec<f32>> {
        normals
            .iter()
            .zip(canon)
            .zip(transforms)
            .map(|((n, p), t)| {
                let v = (centre - t.affine.transform_point3(*p)).normalize_or_zero();
                vec![(t.rotation * *n).normalize_or_zero().dot(v)]
            })
            .collect()
    };
    let nb = maps.len();
    let view = |(f, b): (Tensor<4>, Tensor<4>)| [host(f), host(b)].concat();
    close(
        view(inputs.body_view.clone()),
        host_input(
            &cosines(&maps.normals, &body_canon, &skinning[..nb]),
            &maps.pixels,
            maps.resolution,
            16,
        ),
        1e-5,
        "body view",
    );
    close(
        view(inputs.face_view.clone().unwrap()),
        host_input(
            &cosines(&head.normals, &face_canon, &skinning[nb..]),
            &head.pixels,
            head.size,
            16,
        ),
        1e-5,
        "face view",
    );
}
