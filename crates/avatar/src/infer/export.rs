//! Standard 3DGS `.ply` export of a posed avatar that keeps its view-dependent colour.
//!
//! The colour network sees the direction to the camera, so an avatar has no single colour per
//! Gaussian. Export renders the colour network's output for many view directions (a Fibonacci
//! sphere of distant cameras around the posed body) and fits, per Gaussian and channel, the SH
//! coefficients `f` of 3DGS's colour model `0.5 + Σ_k Y_k(d) f_k` by least squares (`d` the unit
//! direction from the camera to the Gaussian, the basis of [`f3g_splat::sh`]). The fit error is
//! measured on a second set of directions that the fit did not see.
//!
//! Files always carry degree-3 coefficients (45 `f_rest_*`, zero above the fitted degree): the
//! reference 3DGS loader and the SIBR viewer read exactly that layout.
//!
//! Up: f3g's world is +Y up. Most 3DGS scenes (COLMAP) are −Y up, and editors such as
//! SuperSplat assume it; [`Up::NegY`] turns the avatar by 180° about X (positions, rotations
//! and the directions the SH are fitted in), a proper rotation that keeps handedness.

use std::f64::consts::PI;

use faer::Mat;
use faer::prelude::SolveLstsq;
use glam::{DQuat, DVec3};

use super::TrainedAvatar;
use crate::AvatarError;
use crate::model::{host_values, pose};
use f3g_rig::RigParams;
use f3g_splat::sh::{basis, num_coeffs};
use f3g_splat::{Camera, GaussianCloud};

/// Which world axis is up in the exported file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Up {
    /// f3g's own convention (and three.js, glTF): +Y up.
    Y,
    /// COLMAP's and most 3DGS scenes': −Y up (the avatar turned by 180° about X).
    NegY,
}

impl Up {
    fn rotation(self) -> DQuat {
        match self {
            Up::Y => DQuat::IDENTITY,
            Up::NegY => DQuat::from_rotation_x(PI),
        }
    }
}

/// What the export did and how well the SH reproduce the colour network.
#[derive(Clone, Debug)]
pub struct ShFit {
    /// Fitted SH degree (0..=3; the file holds degree 3 either way).
    pub degree: usize,
    /// View directions the fit used, and the held-out ones the error is measured on.
    pub fit_directions: usize,
    pub check_directions: usize,
    /// RMS and largest absolute colour error (colours in [0, 1]) on the held-out directions.
    pub rms: f64,
    pub max: f64,
}

/// Export options.
#[derive(Clone, Copy, Debug)]
pub struct ExportOptions {
    /// SH degree to fit, 0..=3 (0: the mean colour over all directions).
    pub degree: usize,
    /// View directions of the fit (as many again check it).
    pub directions: usize,
    pub up: Up,
    /// Colours under the light fixed in the world, in the pose exported (what a render of
    /// that pose shows), or the albedo (what a baked avatar shades per frame itself).
    pub lit: bool,
}

/// Unit directions `i = 0..n` of a Fibonacci sphere; `offset` in [0, 1) shifts the spiral so
/// that two sets interleave.
fn fibonacci(n: usize, offset: f64) -> Vec<DVec3> {
    let golden = PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let y = 1.0 - 2.0 * (i as f64 + 0.5 + offset) / (n as f64 + 1.0);
            let r = (1.0 - y * y).max(0.0).sqrt();
            let phi = golden * (i as f64 + offset);
            DVec3::new(r * phi.cos(), y, r * phi.sin())
        })
        .collect()
}

/// A camera far along `dir` from `centre`, so that every Gaussian sees it in direction `dir`.
fn distant_camera(centre: DVec3, dir: DVec3) -> Camera {
    let eye = centre + 1000.0 * dir;
    let up = if dir.y.abs() > 0.9 {
        [0.0, 0.0, 1.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    Camera::look_at(eye.to_array(), centre.to_array(), up, 500.0, 64, 64)
}

/// The posed Gaussians of `params` with SH colour fitted to the colour network, in the `up`
/// convention; `use_pca` projects the pose onto the training poses first (unseen poses).
pub fn export_cloud(
    avatar: &TrainedAvatar,
    params: &RigParams,
    use_pca: bool,
    options: &ExportOptions,
) -> Result<(GaussianCloud, ShFit), AvatarError> {
    if options.degree > 3 {
        return Err(AvatarError::Invalid(format!(
            "SH degree {} is not in 0..=3",
            options.degree
        )));
    }
    if options.directions < num_coeffs(options.degree) {
        return Err(AvatarError::Invalid(format!(
            "{} view directions cannot determine {} SH coefficients: give at least that many",
            options.directions,
            num_coeffs(options.degree)
        )));
    }
    // Geometry does not depend on the camera (the colour networks alone see it): those run
    // for each direction, the others once.
    let views = avatar.views_of(params, use_pca)?;
    let (c, inputs) = views.seen_from(&distant_camera(DVec3::ZERO, DVec3::Z))?;
    let (means, quats) = pose(&c, &inputs.skinning);
    let (means, quats) = (host_values(means), host_values(quats));
    let n = means.len() / 3;
    let centre = means.chunks_exact(3).fold(DVec3::ZERO, |a, m| {
        a + DVec3::new(m[0] as f64, m[1] as f64, m[2] as f64)
    }) / n.max(1) as f64;
    let colours_from = |dir: DVec3| -> Result<Vec<f32>, AvatarError> {
        let (c, _) = views.seen_from(&distant_camera(centre, dir))?;
        Ok(host_values(if options.lit {
            c.lit_colours()
        } else {
            c.colours
        }))
    };
    let rotation = options.up.rotation();
    let k = num_coeffs(options.degree);
    // The basis at the direction 3DGS evaluates: from the camera to the Gaussian, in the
    // exported frame.
    let basis_row = |dir: DVec3| {
        let d = rotation * -dir;
        let mut row = [0.0f64; 16];
        basis(k, [d.x, d.y, d.z], &mut row);
        row
    };
    // The fit holds every direction's colours of every Gaussian in f64, and the least-squares
    // solve a copy of them.
    let fit_bytes = 2 * options.directions as u64 * 3 * n as u64 * 8;
    f3g_io::memory::ensure_available(
        fit_bytes,
        &format!(
            "an SH fit over {} view directions (--directions) of {n} Gaussians",
            options.directions
        ),
    )?;
    let fit_dirs = fibonacci(options.directions, 0.0);
    let check_dirs = fibonacci(options.directions, 0.5);
    // Least squares A f = c − 0.5 for every Gaussian and channel at once (one QR of A).
    let m = fit_dirs.len();
    let a = Mat::<f64>::from_fn(m, k, |i, j| basis_row(fit_dirs[i])[j]);
    let mut b = Mat::<f64>::zeros(m, 3 * n);
    for (i, &dir) in fit_dirs.iter().enumerate() {
        let colours = colours_from(dir)?;
        for (j, v) in colours.iter().enumerate() {
            b[(i, j)] = *v as f64 - 0.5;
        }
    }
    let coeffs = a.qr().solve_lstsq(&b);
    // Held-out error of the colour the renderer shows (clamped like the network's output).
    let (mut sum, mut max, mut count) = (0.0f64, 0.0f64, 0usize);
    for &dir in &check_dirs {
        let truth = colours_from(dir)?;
        let row = basis_row(dir);
        for (j, t) in truth.iter().enumerate() {
            let fitted = 0.5 + (0..k).map(|l| row[l] * coeffs[(l, j)]).sum::<f64>();
            let e = (fitted.clamp(0.0, 1.0) - (*t as f64).clamp(0.0, 1.0)).abs();
            sum += e * e;
            max = max.max(e);
            count += 1;
        }
    }
    // `[N, k, 3]` coefficients, padded to degree 3 below.
    let mut sh = vec![0.0f32; n * k * 3];
    for g in 0..n {
        for l in 0..k {
            for ch in 0..3 {
                sh[(g * k + l) * 3 + ch] = coeffs[(l, 3 * g + ch)] as f32;
            }
        }
    }
    let (mut out_means, mut out_quats) = (means, quats);
    if options.up != Up::Y {
        for m in out_means.chunks_exact_mut(3) {
            let p = rotation * DVec3::new(m[0] as f64, m[1] as f64, m[2] as f64);
            m.copy_from_slice(&[p.x as f32, p.y as f32, p.z as f32]);
        }
        for q in out_quats.chunks_exact_mut(4) {
            let r = rotation * DQuat::from_xyzw(q[1] as f64, q[2] as f64, q[3] as f64, q[0] as f64);
            q.copy_from_slice(&[r.w as f32, r.x as f32, r.y as f32, r.z as f32]);
        }
    }
    let cloud = GaussianCloud {
        means: out_means,
        log_scales: host_values(c.log_scales),
        quats: out_quats,
        opacity_logits: host_values(c.opacity_logits),
        sh,
        sh_degree: options.degree,
    }
    .padded_to_degree(3);
    let fit = ShFit {
        degree: options.degree,
        fit_directions: m,
        check_directions: check_dirs.len(),
        rms: (sum / count.max(1) as f64).sqrt(),
        max,
    };
    Ok((cloud, fit))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fibonacci_directions_are_unit_and_spread() {
        let (a, b) = (fibonacci(48, 0.0), fibonacci(48, 0.5));
        for d in a.iter().chain(&b) {
            assert!((d.length() - 1.0).abs() < 1e-9);
        }
        // Both hemispheres of every axis are covered, and the two sets do not coincide.
        for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
            assert!(a.iter().any(|d| d.dot(axis) > 0.7) && a.iter().any(|d| d.dot(axis) < -0.7));
        }
        let closest = a
            .iter()
            .map(|d| b.iter().map(|e| d.distance(*e)).fold(f64::MAX, f64::min))
            .fold(f64::MAX, f64::min);
        assert!(closest > 1e-3, "{closest}");
    }

    #[test]
    fn turning_y_down_is_a_proper_rotation_that_flips_y_and_z() {
        let r = Up::NegY.rotation();
        let p = r * DVec3::new(1.0, 2.0, 3.0);
        assert!((p - DVec3::new(1.0, -2.0, -3.0)).length() < 1e-12);
        assert_eq!(Up::Y.rotation(), DQuat::IDENTITY);
    }
}
