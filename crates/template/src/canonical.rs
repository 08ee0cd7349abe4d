//! The canonical pose: the body model's zero pose with the legs apart and a configurable arm
//! angle ([`f3g_rig::Rig::canonical_params`], through the body model's roles), and root-free
//! posing.

use f3g_rig::{Parameterization, Rig, RigParams};

pub use f3g_rig::CanonicalPose;

/// `params` with the root's global rotation and translation removed (posed maps are
/// root-relative, as in Animatable Gaussians).
pub fn without_root(rig: &Rig, params: &RigParams) -> RigParams {
    let mut p = params.clone();
    let roots: Vec<usize> = rig
        .skeleton
        .joints()
        .iter()
        .enumerate()
        .filter(|(_, j)| j.parent.is_none())
        .map(|(i, _)| i)
        .collect();
    match &rig.parameterization {
        Parameterization::AxisAngle => {
            for &r in &roots {
                p.pose[3 * r..3 * r + 3].fill(0.0);
            }
            let n = p.pose.len();
            p.pose[n - 3..].fill(0.0);
        }
        Parameterization::Momentum(t) => {
            for e in &t.entries {
                if roots.contains(&(e.0 as usize / f3g_rig::PARAMS_PER_JOINT)) {
                    p.pose[e.1 as usize] = 0.0;
                }
            }
        }
    }
    p
}
