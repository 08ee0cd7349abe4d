//! Choosing a body model on the command line: `builtin`, `smplx:PATH`, `mhr:DIR`, `gltf:PATH`.

use std::path::PathBuf;
use std::str::FromStr;

use crate::{Rig, RigError, builtin, gltf, mhr, smplx};

/// A body model and where to load it from.
#[derive(Clone, Debug, PartialEq)]
pub enum ModelSpec {
    /// The built-in MakeHuman body.
    Builtin,
    /// An SMPL-X model `.npz` (10 betas, 10 expression coefficients).
    Smplx(PathBuf),
    /// An MHR asset folder (level of detail 1).
    Mhr(PathBuf),
    /// A rigged glTF; a Momentum `.model` with the same stem next to it is used if present.
    Gltf(PathBuf),
}

impl FromStr for ModelSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let path = |p: &str| {
            if p.is_empty() {
                Err(format!("`{s}`: the path after the colon is empty"))
            } else {
                Ok(PathBuf::from(p))
            }
        };
        match s.split_once(':') {
            None if s == "builtin" => Ok(Self::Builtin),
            Some(("smplx", p)) => Ok(Self::Smplx(path(p)?)),
            Some(("mhr", p)) => Ok(Self::Mhr(path(p)?)),
            Some(("gltf", p)) => Ok(Self::Gltf(path(p)?)),
            _ => Err(format!(
                "unknown body model `{s}`: expected builtin, smplx:PATH, mhr:DIR or gltf:PATH"
            )),
        }
    }
}

impl std::fmt::Display for ModelSpec {
    /// The spelling [`FromStr`] reads back (`builtin`, `smplx:PATH`, …).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Builtin => write!(f, "builtin"),
            Self::Smplx(p) => write!(f, "smplx:{}", p.display()),
            Self::Mhr(p) => write!(f, "mhr:{}", p.display()),
            Self::Gltf(p) => write!(f, "gltf:{}", p.display()),
        }
    }
}

impl ModelSpec {
    /// Loads the model as a body model of the avatar pipeline: every required role resolved
    /// ([`Rig::check_body_model`]), or an error naming the missing one.
    pub fn load(&self) -> Result<Rig, RigError> {
        let rig = match self {
            Self::Builtin => builtin::load()?.rig,
            Self::Smplx(p) => smplx::load(p, 10, 10)?,
            Self::Mhr(p) => mhr::load(p, 1)?,
            Self::Gltf(p) => {
                let model = p.with_extension("model");
                gltf::load(p, model.exists().then_some(model.as_path()))?
            }
        };
        rig.check_body_model()?;
        Ok(rig)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_specs() {
        assert_eq!("builtin".parse::<ModelSpec>().unwrap(), ModelSpec::Builtin);
        assert_eq!(
            "smplx:/m/SMPLX_NEUTRAL.npz".parse::<ModelSpec>().unwrap(),
            ModelSpec::Smplx("/m/SMPLX_NEUTRAL.npz".into())
        );
        assert!("mhr:".parse::<ModelSpec>().unwrap_err().contains("empty"));
        for text in ["builtin", "smplx:/m/a.npz", "mhr:/m", "gltf:b.glb"] {
            assert_eq!(text.parse::<ModelSpec>().unwrap().to_string(), text);
        }
        assert!(
            "smpl:x"
                .parse::<ModelSpec>()
                .unwrap_err()
                .contains("unknown body model")
        );
    }
}
