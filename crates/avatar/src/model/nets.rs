//! The avatar model: the body StyleUNets, the three face StyleUNets, the canonical face model,
//! fusion, linear blend skinning of the Gaussians and rendering.
//!
//! Body branch ([`BodyNets`], laid out by [`super::BodyLayout`]): posed front/back maps
//! `[1, 6, R/2, R/2]` → 14 channels per side, resampled to `R` and read at the body Gaussians'
//! texels: offset `0.05 · o[0..3]` on the canonical position, colour `0.5 + o[3..6]`, opacity
//! logit `logit(initial_opacity) + o[6]`, log-scale `ln s₀ + o[7..10]`, rotation `q₀ + o[10..14]`
//! (normalised when rendered; `q₀` turns the Gaussian's thin axis to the surface normal) —
//! Animatable Gaussians' heads. Only the colour network sees the view direction (`split` and
//! `three` layouts), so the camera changes colours and never geometry; `single` (one
//! view-conditioned network for all 14 channels) is kept for comparison. With
//! `learn_canonical`, a learnable per-Gaussian table (step sizes scaled per attribute as 3DGS's
//! learning rates) is added to the networks' outputs: the per-texel detail that small CPU
//! networks cannot carry.
//!
//! Face branch (paper §3.4): the posed head maps `P` (`[1, 6, F, F]`) go through the position
//! network, `P̂ = P + 0.05 · 𝒫(P)`; the colour network (view-conditioned) and the auxiliary
//! network read `P̂`. Their outputs, resampled to the head map and read at the face Gaussians'
//! texels, are residuals on the canonical face model `𝒢` (the head region of the trained body
//! branch averaged over training frames, densified; [`FaceBase`]). Face scales are capped at
//! 0.15 m as in the reference.
//!
//! Every Gaussian's canonical position also moves with the frame's blend shapes and pose
//! correctives (the displacement of its template point), so expressions and correctives reach
//! the Gaussians through the posed template, as in the paper, before the networks' offsets.
//!
//! Fusion concatenates body and face Gaussians; the body keeps its own head Gaussians (the
//! paper concatenates the two sets and does not remove any), so the face branch adds detail on
//! top. The fused set is posed by LBS (means by the blended transform, rotations by its polar
//! rotation, scales unchanged) and splatted with SH degree 0.
//!
//! With `world_shading` (not in the paper; [`super::shading`]) the networks' colours are an
//! albedo, and the rendered colour is the albedo times the light fixed in the world on the
//! Gaussian's posed normal ([`Canonical::lit_colours`]).

use burn::module::{Module, Param};
use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Int, Tensor, TensorData};

use super::config::{ColourActivation, ModelConfig};
use super::host_values;
use super::inputs::{GaussianTables, NetInputs};
use super::posing::{Skinning, pose_gaussians};
use super::setup::Setup;
use super::shading;
use crate::AvatarError;
use f3g_nets::DualStyleUNet;
use f3g_nets::layers::resize;
use f3g_splat::{Camera, Gaussians, RenderOptions, Rendered, render};

/// Scale of the position outputs (metres per unit of network output).
pub const OFFSET_SCALE: f32 = 0.05;
/// Largest face Gaussian scale (metres).
pub const FACE_MAX_SCALE: f32 = 0.15;
const SH_C0: f32 = f3g_splat::sh::SH_C0 as f32;

/// `ln(p / (1 − p))`, unclamped: the model's opacities (`initial_opacity`) are checked to lie
/// in (0, 1). Readers of stored opacities, which may be exactly 0 or 1, clamp them first.
pub(crate) fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

/// The three face networks.
#[derive(Module, Debug)]
pub struct FaceNets {
    pub position: DualStyleUNet,
    pub colour: DualStyleUNet,
    pub aux: DualStyleUNet,
    /// Learnable per-Gaussian residuals `[N_f, 14]` (with `learn_canonical`).
    pub canonical: Option<Param<Tensor<2>>>,
}

/// The trainable networks.
#[derive(Module, Debug)]
pub struct AvatarNets {
    pub body: BodyNets,
    pub face: Option<FaceNets>,
}

/// The body branch: one to three StyleUNets (see [`super::BodyLayout`]) and the
/// optional learnable canonical attributes.
#[derive(Module, Debug)]
pub struct BodyNets {
    /// All 14 channels (`single`), the geometry (`split`: offset ‖ other) or the position
    /// offset (`three`).
    pub net: DualStyleUNet,
    /// The view-conditioned colour network (`split`, `three`).
    pub colour: Option<DualStyleUNet>,
    /// Opacity, scale and rotation (`three`).
    pub other: Option<DualStyleUNet>,
    /// Learnable per-Gaussian canonical attributes `[N_b, 14]` (with `learn_canonical`).
    pub canonical: Option<Param<Tensor<2>>>,
    /// The light fixed in the world (with `world_shading`): `[9, 3]` parameters of
    /// [`shading::coefficients`]. Trained with the body networks, in the stages that train them.
    pub shading: Option<Param<Tensor<2>>>,
}

/// Per-column step multipliers of the learnable canonical attributes (3DGS's relative
/// learning rates: position, colour, opacity ×20, scale ×2, rotation ×0.4).
const CANONICAL_COLUMN_SCALE: [f32; 14] = [
    1.6, 1.6, 1.6, 1.0, 1.0, 1.0, 10.0, 2.0, 2.0, 2.0, 0.4, 0.4, 0.4, 0.4,
];

fn canonical_delta(p: &Param<Tensor<2>>, scale: f32) -> Tensor<2> {
    let v = p.val();
    let cols = Tensor::<2>::from_data(
        TensorData::new(
            CANONICAL_COLUMN_SCALE
                .iter()
                .map(|c| c * scale)
                .collect::<Vec<f32>>(),
            [1, 14],
        ),
        &v.device(),
    );
    v * cols
}

/// Namespaces of the parameter ids of the avatar's networks and of the discriminator (they meet
/// in the adversarial loss's gradients, so they must not share ids).
pub const AVATAR_PARAM_IDS: u64 = 1;
pub const DISCRIMINATOR_PARAM_IDS: u64 = 2;

impl AvatarNets {
    /// Networks of `config`, weights drawn from `seed`, parameter ids deterministic.
    pub fn new(
        config: &ModelConfig,
        seed: u64,
        setup: &Setup,
        device: &Device,
    ) -> Result<Self, AvatarError> {
        let zeros = |n: usize| {
            config
                .learn_canonical
                .then(|| Param::from_tensor(Tensor::<2>::zeros([n, 14], device)))
        };
        let face = if config.face_branch {
            let [p, c, a] = config.face_nets();
            Some(FaceNets {
                position: p.init(seed.wrapping_add(11), device)?,
                colour: c.init(seed.wrapping_add(12), device)?,
                aux: a.init(seed.wrapping_add(13), device)?,
                canonical: zeros(setup.face_count()),
            })
        } else {
            None
        };
        let mut body = config.body_nets().into_iter().enumerate().map(|(i, c)| {
            // The first network keeps the seed offset it always had.
            let seed = seed.wrapping_add(if i == 0 { 10 } else { 13 + i as u64 });
            c.init(seed, device)
        });
        let net = body.next().expect("at least one body network")?;
        let colour = body.next().transpose()?;
        let other = body.next().transpose()?;
        let nets = Self {
            body: BodyNets {
                net,
                colour,
                other,
                canonical: zeros(setup.body_count()),
                shading: config
                    .world_shading
                    .then(|| shading::initial_parameters(device)),
            },
            face,
        };
        Ok(f3g_nets::checkpoint::with_deterministic_ids(
            nets,
            AVATAR_PARAM_IDS,
        ))
    }
}

/// Canonical attributes of the face Gaussians (`𝒢`), host side.
#[derive(Clone, Debug, PartialEq)]
pub struct FaceBase {
    /// `[N_f, 3]` canonical positions.
    pub positions: Vec<f32>,
    /// `[N_f, 3]` colours.
    pub colours: Vec<f32>,
    /// `[N_f]` opacity logits.
    pub opacity_logits: Vec<f32>,
    /// `[N_f, 3]` natural-log scales.
    pub log_scales: Vec<f32>,
    /// `[N_f, 4]` rotations (w, x, y, z).
    pub quats: Vec<f32>,
}

impl FaceBase {
    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity_logits.is_empty()
    }
}

/// Per-Gaussian attributes of the body branch's output, host side (`[N, C]` row-major).
#[derive(Clone, Debug)]
pub struct BodyAttributes {
    pub positions: Vec<f32>,
    pub colours: Vec<f32>,
    pub opacity_logits: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub quats: Vec<f32>,
}

/// Canonical Gaussians as tensors, before posing.
pub struct Canonical {
    pub means: Tensor<2>,
    pub log_scales: Tensor<2>,
    pub quats: Tensor<2>,
    pub opacity_logits: Tensor<1>,
    /// `[N, 3]` albedo: what the networks predict, before the light fixed in the world.
    pub colours: Tensor<2>,
    /// `[N, 3]` the light on each Gaussian in this frame's pose (with `world_shading`):
    /// rendered colours are `colours · shading`.
    pub shading: Option<Tensor<2>>,
    /// `[N_b, 3]` body position offsets (for the offset regulariser).
    pub body_offsets: Tensor<2>,
    /// `[N_f, 3]` face position offsets, and all face residuals `[N_f, 14]`.
    pub face_offsets: Option<Tensor<2>>,
    pub face_residuals: Option<Tensor<2>>,
}

impl Canonical {
    /// `[N, 3]` the colours rendered: the albedo under this frame's light, when the model has
    /// one.
    pub fn lit_colours(&self) -> Tensor<2> {
        match &self.shading {
            Some(s) => self.colours.clone() * s.clone(),
            None => self.colours.clone(),
        }
    }
}

/// Constant tensors of the avatar on one device.
pub struct Constants {
    body_pixels: Tensor<1, Int>,
    body_log_scales: Tensor<2>,
    body_quats: Tensor<2>,
    face: Option<FaceConstants>,
    map_resolution: usize,
    /// What turns a frame's pose into the networks' inputs and the Gaussians' skinning
    /// ([`Constants::inputs`]).
    pub(super) tables: GaussianTables,
    initial_opacity_logit: f32,
    sigmoid_colours: bool,
    canonical_scale: f32,
}

struct FaceConstants {
    pixels: Tensor<1, Int>,
    size: usize,
    positions: Tensor<2>,
    colours: Tensor<2>,
    opacity_logits: Tensor<1>,
    log_scales: Tensor<2>,
    quats: Tensor<2>,
}

fn t2(values: Vec<f32>, cols: usize, device: &Device) -> Tensor<2> {
    let rows = values.len() / cols;
    Tensor::from_data(TensorData::new(values, [rows, cols]), device)
}

fn t1(values: Vec<f32>, device: &Device) -> Tensor<1> {
    let n = values.len();
    Tensor::from_data(TensorData::new(values, [n]), device)
}

fn index(values: &[usize], device: &Device) -> Tensor<1, Int> {
    let v: Vec<i64> = values.iter().map(|&p| p as i64).collect();
    let n = v.len();
    Tensor::from_data(TensorData::new(v, [n]), device)
}

impl Constants {
    /// Initial log-scales and rotations of the body Gaussians (`[N, 3]`, `[N, 4]`).
    pub(crate) fn initial_body(&self) -> (Tensor<2>, Tensor<2>) {
        (self.body_log_scales.clone(), self.body_quats.clone())
    }

    /// Uploads the setup (and the canonical face model, once it exists).
    pub fn new(
        setup: &Setup,
        config: &ModelConfig,
        face_base: Option<&FaceBase>,
        device: &Device,
    ) -> Self {
        let maps = &setup.maps;
        let face = match (&setup.head, face_base) {
            (Some(head), Some(base)) => Some(FaceConstants {
                pixels: index(&head.pixels, device),
                size: head.size,
                positions: t2(base.positions.clone(), 3, device),
                colours: t2(base.colours.clone(), 3, device),
                opacity_logits: t1(base.opacity_logits.clone(), device),
                log_scales: t2(base.log_scales.clone(), 3, device),
                quats: t2(base.quats.clone(), 4, device),
            }),
            _ => None,
        };
        Self {
            body_pixels: index(&maps.pixels, device),
            body_log_scales: t2(
                setup.initial_log_scales(config.initial_thickness),
                3,
                device,
            ),
            body_quats: t2(setup.initial_quats(config.initial_thickness), 4, device),
            face,
            map_resolution: config.map_resolution,
            tables: GaussianTables::new(
                setup,
                config.body_net.input_size,
                config.face_net.input_size,
                device,
            ),
            initial_opacity_logit: logit(config.initial_opacity),
            sigmoid_colours: config.colour_activation == ColourActivation::Sigmoid,
            canonical_scale: config.canonical_lr_scale,
        }
    }

    /// Whether the face Gaussians are part of the model.
    pub fn has_face(&self) -> bool {
        self.face.is_some()
    }
}

/// Reads `[1, C, R, R]` front and back outputs at the given texels of the `[R, 2R]` layout:
/// `[N, C]`.
///
/// A `gather` with the texel list repeated for every channel rather than a `select`: on GPUs
/// Burn 0.22.1 computes `select`'s gradient with one thread per channel walking all N texels
/// (47 ms per call for the `paper` preset's 400 k Gaussians on an H200, six calls a step), and
/// `gather`'s as a scatter-add with one atomic add per value.
fn gather(front: Tensor<4>, back: Tensor<4>, pixels: &Tensor<1, Int>) -> Tensor<2> {
    let [_, c, h, w] = front.dims();
    let n = pixels.dims()[0];
    let both = Tensor::cat(vec![front, back], 3).reshape([c, h * 2 * w]);
    let texels = pixels.clone().reshape([1, n]).expand([c, n]);
    both.gather(1, texels).transpose()
}

/// Columns `a..b` of `[N, C]`.
fn cols(t: &Tensor<2>, a: usize, b: usize) -> Tensor<2> {
    let n = t.dims()[0];
    t.clone().slice([0..n, a..b])
}

/// The networks' outputs that do not depend on the camera, for seeing one pose from several
/// views ([`canonical_seen`]): with the `Split` and `Three` body layouts only the colour
/// networks read the view maps, and in the face branch only its colour network, so another
/// view of the same pose needs only those (baking and the SH fit of an export evaluate a pose
/// from 4 to 97 directions).
pub struct ViewFree {
    /// The body's gathered view-free outputs: the geometry network's `[N_b, 11]` (`Split`) or
    /// its position `[N_b, 3]` and the other network's `[N_b, 8]` (`Three`); `None` for the
    /// `Single` layout, whose one network sees the view.
    body: Option<BodyViewFree>,
    /// The face branch's gathered position `[N_f, 3]` and aux `[N_f, 8]` outputs and the
    /// colour network's input (the offset head map).
    face: Option<FaceViewFree>,
}

/// [`ViewFree::body`]: the geometry network's outputs and the other network's, if any.
type BodyViewFree = (Tensor<2>, Option<Tensor<2>>);
/// [`ViewFree::face`]: position outputs, aux outputs, the colour network's input.
type FaceViewFree = (Tensor<2>, Tensor<2>, Tensor<4>);

/// Reads `[1, C, r, r]` front and back outputs of a body network (resized to the map
/// resolution when the network's output is smaller) at the body's texels: `[N_b, C]`.
fn read_body(
    net: &DualStyleUNet,
    constants: &Constants,
    inputs: &NetInputs,
    view: bool,
) -> Result<Tensor<2>, AvatarError> {
    let r = constants.map_resolution;
    let full = |t: Tensor<4>| {
        if t.dims()[2] == r { t } else { resize(t, r, r) }
    };
    let view = view.then(|| (inputs.body_view.0.clone(), inputs.body_view.1.clone()));
    let out = net.forward(inputs.body_map.clone(), view)?;
    Ok(gather(
        full(out.front),
        full(out.back),
        &constants.body_pixels,
    ))
}

/// Runs the networks that do not see the camera (`inputs`' view maps are not read).
pub fn view_free(
    nets: &AvatarNets,
    constants: &Constants,
    inputs: &NetInputs,
) -> Result<ViewFree, AvatarError> {
    let face = match (&nets.face, &constants.face) {
        (Some(face), Some(fc)) => Some(face_view_free(face, fc, inputs)?),
        _ => None,
    };
    Ok(ViewFree {
        body: body_view_free(&nets.body, constants, inputs)?,
        face,
    })
}

/// The body networks that do not see the camera ([`ViewFree::body`]).
fn body_view_free(
    body: &BodyNets,
    constants: &Constants,
    inputs: &NetInputs,
) -> Result<Option<BodyViewFree>, AvatarError> {
    Ok(match (&body.colour, &body.other) {
        (None, _) => None,
        (Some(_), None) => Some((read_body(&body.net, constants, inputs, false)?, None)),
        (Some(_), Some(other)) => Some((
            read_body(&body.net, constants, inputs, false)?,
            Some(read_body(other, constants, inputs, false)?),
        )),
    })
}

/// The body branch alone: per-Gaussian raw outputs `[N_b, 14]` (offset 3, colour 3, opacity
/// 1, scale 3, rotation 4), whatever the layout.
pub fn body_outputs(
    nets: &AvatarNets,
    constants: &Constants,
    inputs: &NetInputs,
) -> Result<Tensor<2>, AvatarError> {
    let free = body_view_free(&nets.body, constants, inputs)?;
    body_outputs_seen(&nets.body, constants, inputs, free.as_ref())
}

/// [`body_outputs`] from the body's view-free outputs of the same pose and `inputs`' view
/// maps.
fn body_outputs_seen(
    body: &BodyNets,
    constants: &Constants,
    inputs: &NetInputs,
    free: Option<&BodyViewFree>,
) -> Result<Tensor<2>, AvatarError> {
    let raw = match (&body.colour, free) {
        (Some(colour), Some((geometry, other))) => {
            let colour = read_body(colour, constants, inputs, true)?;
            match other {
                None => Tensor::cat(vec![cols(geometry, 0, 3), colour, cols(geometry, 3, 11)], 1),
                Some(other) => Tensor::cat(vec![geometry.clone(), colour, other.clone()], 1),
            }
        }
        _ => read_body(&body.net, constants, inputs, true)?,
    };
    Ok(match &body.canonical {
        Some(p) => raw + canonical_delta(p, constants.canonical_scale),
        None => raw,
    })
}

/// Body attributes from raw outputs: (means, colours, opacity logits, log-scales, quats,
/// offsets).
fn body_attributes(
    raw: &Tensor<2>,
    constants: &Constants,
) -> (
    Tensor<2>,
    Tensor<2>,
    Tensor<1>,
    Tensor<2>,
    Tensor<2>,
    Tensor<2>,
) {
    let n = raw.dims()[0];
    let offsets = cols(raw, 0, 3) * OFFSET_SCALE;
    let means = constants.tables.body_positions().clone() + offsets.clone();
    let colours = if constants.sigmoid_colours {
        cols(raw, 3, 6)
    } else {
        cols(raw, 3, 6) + 0.5
    };
    let opacity = (cols(raw, 6, 7) + constants.initial_opacity_logit).reshape([n]);
    let log_scales = constants.body_log_scales.clone() + cols(raw, 7, 10);
    let quats = cols(raw, 10, 14) + constants.body_quats.clone();
    (means, colours, opacity, log_scales, quats, offsets)
}

/// The body branch's activated attributes on the host (used to build the canonical face
/// model).
pub fn body_attributes_host(raw: &Tensor<2>, constants: &Constants) -> BodyAttributes {
    let (means, colours, opacity, log_scales, quats, _) = body_attributes(raw, constants);
    BodyAttributes {
        positions: host_values(means),
        colours: host_values(colours),
        opacity_logits: host_values(opacity),
        log_scales: host_values(log_scales),
        quats: host_values(quats),
    }
}

/// Gathers `[1, C, r, r]` front and back outputs of a face network at the face Gaussians'
/// texels of the head maps: `[N_f, C]`.
fn read_face(fc: &FaceConstants, out: f3g_nets::DualOutput) -> Tensor<2> {
    let s = fc.size;
    gather(resize(out.front, s, s), resize(out.back, s, s), &fc.pixels)
}

/// The face networks that do not see the camera: the gathered position and aux outputs and
/// the colour network's input.
fn face_view_free(
    face: &FaceNets,
    fc: &FaceConstants,
    inputs: &NetInputs,
) -> Result<FaceViewFree, AvatarError> {
    let map = inputs
        .face_map
        .clone()
        .ok_or_else(|| AvatarError::Invalid("the face branch needs its head map".into()))?;
    let p = face.position.forward(map.clone(), None)?;
    let p_hat = map + Tensor::cat(vec![p.front.clone(), p.back.clone()], 1) * OFFSET_SCALE;
    let a = face.aux.forward(p_hat.clone(), None)?;
    Ok((read_face(fc, p), read_face(fc, a), p_hat))
}

/// The face networks' raw per-Gaussian outputs `[N_f, 14]` (position 3, colour 3, aux 8) from
/// their view-free outputs and `inputs`' view maps.
fn face_outputs_seen(
    face: &FaceNets,
    fc: &FaceConstants,
    inputs: &NetInputs,
    (position, aux, p_hat): &FaceViewFree,
    scale: f32,
) -> Result<Tensor<2>, AvatarError> {
    let view = inputs
        .face_view
        .clone()
        .ok_or_else(|| AvatarError::Invalid("the face branch needs its view maps".into()))?;
    let c = face.colour.forward(p_hat.clone(), Some(view))?;
    let raw = Tensor::cat(vec![position.clone(), read_face(fc, c), aux.clone()], 1);
    Ok(match &face.canonical {
        Some(p) => raw + canonical_delta(p, scale),
        None => raw,
    })
}

/// Runs the networks: the fused canonical Gaussians (body, then face when present).
pub fn canonical(
    nets: &AvatarNets,
    constants: &Constants,
    inputs: &NetInputs,
) -> Result<Canonical, AvatarError> {
    canonical_seen(
        nets,
        constants,
        inputs,
        &view_free(nets, constants, inputs)?,
    )
}

/// [`canonical`] from the view-free outputs of the same pose ([`view_free`]) and `inputs`'
/// view maps: equal to it, running only the networks that see the camera.
pub fn canonical_seen(
    nets: &AvatarNets,
    constants: &Constants,
    inputs: &NetInputs,
    free: &ViewFree,
) -> Result<Canonical, AvatarError> {
    let raw = body_outputs_seen(&nets.body, constants, inputs, free.body.as_ref())?;
    let (means, colours, opacity, log_scales, quats, body_offsets) =
        body_attributes(&raw, constants);
    let nb = means.dims()[0];
    let total = inputs.displacement.dims()[0];
    let means = means + inputs.displacement.clone().slice([0..nb, 0..3]);
    let mut out = Canonical {
        means,
        log_scales,
        quats,
        opacity_logits: opacity,
        colours,
        shading: None,
        body_offsets,
        face_offsets: None,
        face_residuals: None,
    };
    if let (Some(face), Some(fc), Some(face_free)) = (&nets.face, &constants.face, &free.face) {
        let r = face_outputs_seen(face, fc, inputs, face_free, constants.canonical_scale)?;
        let n = r.dims()[0];
        let offsets = cols(&r, 0, 3) * OFFSET_SCALE;
        let means = fc.positions.clone()
            + offsets.clone()
            + inputs.displacement.clone().slice([nb..total, 0..3]);
        let colours = fc.colours.clone() + cols(&r, 3, 6);
        let opacity = fc.opacity_logits.clone() + cols(&r, 6, 7).reshape([n]);
        let log_scales = (fc.log_scales.clone() + cols(&r, 7, 10)).clamp_max(FACE_MAX_SCALE.ln());
        let quats = fc.quats.clone() + cols(&r, 10, 14);
        out = Canonical {
            means: Tensor::cat(vec![out.means, means], 0),
            log_scales: Tensor::cat(vec![out.log_scales, log_scales], 0),
            quats: Tensor::cat(vec![out.quats, quats], 0),
            opacity_logits: Tensor::cat(vec![out.opacity_logits, opacity], 0),
            colours: Tensor::cat(vec![out.colours, colours], 0),
            shading: None,
            body_offsets: out.body_offsets,
            face_offsets: Some(offsets),
            face_residuals: Some(r),
        };
    }
    if constants.sigmoid_colours {
        out.colours = sigmoid(out.colours);
    }
    if let Some(p) = &nets.body.shading {
        out.shading = Some(shading::shade(shading::coefficients(p), &inputs.normals));
    }
    Ok(out)
}

/// Poses canonical Gaussians with their skinning: `(means, quats)`.
pub fn pose(canonical: &Canonical, skinning: &Skinning) -> (Tensor<2>, Tensor<2>) {
    pose_gaussians(canonical.means.clone(), canonical.quats.clone(), skinning)
}

/// Poses and renders the canonical Gaussians from `camera` over `background`.
pub fn render_posed(
    canonical: &Canonical,
    skinning: &Skinning,
    camera: &Camera,
    background: [f32; 3],
    device: &Device,
) -> Result<Rendered, AvatarError> {
    let (means, quats) = pose(canonical, skinning);
    let n = means.dims()[0];
    let gaussians = Gaussians {
        means,
        log_scales: canonical.log_scales.clone(),
        quats,
        opacity_logits: canonical.opacity_logits.clone(),
        sh: ((canonical.lit_colours() - 0.5) / SH_C0).reshape([n, 1, 3]),
    };
    let bg = t1(background.to_vec(), device);
    Ok(render(&gaussians, camera, bg, &RenderOptions::default())?)
}

/// A rendered `[H, W, 3]` colour as `[1, 3, H, W]`.
pub fn nchw(color: Tensor<3>) -> Tensor<4> {
    color.permute([2, 0, 1]).unsqueeze()
}
