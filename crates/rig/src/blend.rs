//! Linear blend shapes (identity and expression blocks).

use glam::Vec3;

use crate::RigError;

/// Named per-vertex offsets: `v = base + Σ_s c_s D_s`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BlendShapes {
    pub names: Vec<String>,
    /// `[shapes · vertices]`, shape-major.
    pub deltas: Vec<Vec3>,
}

impl BlendShapes {
    /// Checks that there are `names.len()` shapes of `vertices` finite offsets.
    pub fn new(names: Vec<String>, deltas: Vec<Vec3>, vertices: usize) -> Result<Self, RigError> {
        if deltas.len() != names.len() * vertices {
            return Err(RigError::Model(format!(
                "{} blend-shape offsets for {} shapes of {vertices} vertices",
                deltas.len(),
                names.len()
            )));
        }
        if let Some(i) = deltas.iter().position(|d| !d.is_finite()) {
            return Err(RigError::Model(format!(
                "blend shape `{}` has a non-finite offset",
                names[i / vertices.max(1)]
            )));
        }
        Ok(Self { names, deltas })
    }

    /// Number of shapes.
    pub fn len(&self) -> usize {
        self.names.len()
    }

    /// True without shapes.
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// Adds `Σ_s c_s D_s` to `vertices`.
    pub fn apply(&self, coefficients: &[f32], vertices: &mut [Vec3]) {
        let n = vertices.len();
        for (s, &c) in coefficients.iter().enumerate() {
            if c != 0.0 {
                for (v, d) in vertices.iter_mut().zip(&self.deltas[s * n..(s + 1) * n]) {
                    *v += *d * c;
                }
            }
        }
    }

    /// Offsets of one shape.
    pub fn shape(&self, s: usize, vertices: usize) -> &[Vec3] {
        &self.deltas[s * vertices..(s + 1) * vertices]
    }
}
