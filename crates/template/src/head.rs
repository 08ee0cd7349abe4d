//! Head maps: the head's square of the position maps, densified (×2 in the reference) for the
//! face branch.
//!
//! The head region is where Gaussians are mostly skinned to the head joint and its
//! descendants (weight ≥ 0.5; the body model names its head, see `f3g_rig::body`). Its bounding box in the front map, enlarged by 10 % and made
//! square, is cropped from both the front and the back map (same columns), giving a
//! `[S, 2S]` head map. Densification is masked bilinear upsampling by the density d (sample positions as
//! `align_corners=False`): an output texel blends its four source texels, weighted by bilinear
//! weight × validity; it is kept when the interpolated validity is at least 0.5 (the F3G
//! reference's rule) and then renormalised by that validity (the reference does not
//! renormalise, which pulls border texels towards the origin). Each kept texel is one face
//! Gaussian, numbered row-major over the `[dS, 2dS]` head map; its position, normal and skin
//! weights are the same blend of its source Gaussians'.

use glam::Vec3;

use crate::TemplateError;
use crate::posmap::PositionMaps;
use f3g_rig::SkinWeights;

/// Densification factor of the reference (and the default): each head texel becomes 2 × 2.
pub const DENSIFY: usize = 2;
/// Minimum interpolated validity for a densified texel.
pub const VALIDITY: f32 = 0.5;

/// The densified face Gaussians and where they sit.
#[derive(Clone, Debug)]
pub struct HeadMaps {
    /// Crop in the front map: left column, top row, side S (pixels of the body maps).
    pub crop: [usize; 3],
    /// Side of one densified head map: `density · S`.
    pub size: usize,
    /// Texel index into the `[size, 2·size]` head map of every face Gaussian.
    pub pixels: Vec<usize>,
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub skin: SkinWeights,
    /// The up to four body Gaussians each face Gaussian blends, with weights summing to 1.
    pub sources: Vec<Vec<(usize, f32)>>,
}

impl HeadMaps {
    /// Finds the head region of `maps` (Gaussians skinned mostly to the `head` joints, the
    /// body model's [`f3g_rig::Rig::head_joints`]) and densifies it, each texel becoming
    /// `density × density` ([`DENSIFY`] in the reference).
    pub fn build(
        maps: &PositionMaps,
        head: &[usize],
        density: usize,
    ) -> Result<Self, TemplateError> {
        if density == 0 {
            return Err(TemplateError::Invalid(
                "the head maps' density must be at least 1".into(),
            ));
        }
        let r = maps.resolution;
        let (mut x0, mut x1, mut y0, mut y1) = (usize::MAX, 0, usize::MAX, 0);
        for (g, &p) in maps.pixels.iter().enumerate() {
            let weight: f32 = maps
                .skin
                .influences(g)
                .filter(|(j, _)| head.contains(j))
                .map(|(_, w)| w)
                .sum();
            if weight >= 0.5 {
                let (row, col) = (p / (2 * r), p % (2 * r) % r);
                (x0, x1, y0, y1) = (x0.min(col), x1.max(col), y0.min(row), y1.max(row));
            }
        }
        if x0 > x1 {
            return Err(TemplateError::Invalid(
                "no Gaussian of the position maps is skinned to the head".into(),
            ));
        }
        let side = (((x1 - x0 + 1).max(y1 - y0 + 1) as f32 * 1.1).ceil() as usize).min(r);
        let centre = ((x0 + x1) / 2, (y0 + y1) / 2);
        let left = centre.0.saturating_sub(side / 2).min(r - side);
        let top = centre.1.saturating_sub(side / 2).min(r - side);

        // Gaussian index of every body-map pixel.
        let mut gaussian_at = vec![usize::MAX; 2 * r * r];
        for (g, &p) in maps.pixels.iter().enumerate() {
            gaussian_at[p] = g;
        }
        let size = density * side;
        let mut out = Self {
            crop: [left, top, side],
            size,
            pixels: Vec::new(),
            positions: Vec::new(),
            normals: Vec::new(),
            skin: SkinWeights::default(),
            sources: Vec::new(),
        };
        let mut lists = Vec::new();
        for row in 0..size {
            for half in 0..2 {
                for col in 0..size {
                    // Source coordinates (align_corners = False), clamped at the crop's border.
                    let sx =
                        ((col as f32 + 0.5) / density as f32 - 0.5).clamp(0.0, (side - 1) as f32);
                    let sy =
                        ((row as f32 + 0.5) / density as f32 - 0.5).clamp(0.0, (side - 1) as f32);
                    let (ix, iy) = (sx.floor() as usize, sy.floor() as usize);
                    let (fx, fy) = (sx - ix as f32, sy - iy as f32);
                    let mut taps = Vec::with_capacity(4);
                    let mut validity = 0.0f32;
                    for (dx, dy, w) in [
                        (0, 0, (1.0 - fx) * (1.0 - fy)),
                        (1, 0, fx * (1.0 - fy)),
                        (0, 1, (1.0 - fx) * fy),
                        (1, 1, fx * fy),
                    ] {
                        let (cx, cy) = ((ix + dx).min(side - 1), (iy + dy).min(side - 1));
                        let p = (top + cy) * 2 * r + half * r + left + cx;
                        if w > 0.0 && gaussian_at[p] != usize::MAX {
                            validity += w;
                            taps.push((gaussian_at[p], w));
                        }
                    }
                    if validity < VALIDITY {
                        continue;
                    }
                    for t in &mut taps {
                        t.1 /= validity;
                    }
                    out.pixels.push(row * 2 * size + half * size + col);
                    out.positions
                        .push(taps.iter().map(|&(g, w)| maps.positions[g] * w).sum());
                    out.normals.push(
                        taps.iter()
                            .map(|&(g, w)| maps.normals[g] * w)
                            .sum::<Vec3>()
                            .normalize_or_zero(),
                    );
                    lists.push(
                        taps.iter()
                            .flat_map(|&(g, w)| {
                                maps.skin.influences(g).map(move |(j, x)| (j, x * w))
                            })
                            .fold(Vec::<(usize, f32)>::new(), |mut acc, (j, x)| {
                                match acc.iter_mut().find(|a| a.0 == j) {
                                    Some(a) => a.1 += x,
                                    None => acc.push((j, x)),
                                }
                                acc
                            }),
                    );
                    out.sources.push(taps);
                }
            }
        }
        let joints = maps
            .skin
            .joints
            .iter()
            .flatten()
            .map(|&j| j as usize + 1)
            .max()
            .unwrap_or(1);
        out.skin = SkinWeights::from_lists(&lists, joints)?;
        Ok(out)
    }

    /// Number of face Gaussians.
    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    /// True without face Gaussians.
    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }

    /// Per-face-Gaussian values blended from per-body-Gaussian values with the densification
    /// taps.
    pub fn from_body(&self, body: &[Vec3]) -> Vec<Vec3> {
        self.sources
            .iter()
            .map(|taps| taps.iter().map(|&(g, w)| body[g] * w).sum())
            .collect()
    }

    /// Scatters per-face-Gaussian values into a `[size, 2·size, C]` map.
    pub fn scatter<const C: usize>(&self, values: &[[f32; C]]) -> Vec<f32> {
        let mut map = vec![0.0f32; self.size * 2 * self.size * C];
        for (&p, v) in self.pixels.iter().zip(values) {
            map[p * C..(p + 1) * C].copy_from_slice(v);
        }
        map
    }
}
