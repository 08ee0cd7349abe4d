//! Skinned body models behind one rig abstraction.
//!
//! Every model — the built-in human, SMPL-X, MHR, any rigged glTF — loads into a [`Rig`]:
//! a skeleton with rest offsets and pre-rotations, a pose parameterisation (Momentum's linear
//! parameter transform, or axis-angle per joint), a template mesh, identity and expression blend
//! shapes, sparse skin weights (≤ 8 influences), optional pose correctives, and optionally a
//! joint model that moves the rest skeleton with the shape. [`Rig::pose`] evaluates it.
//!
//! Conventions: metres, +Y up, right-handed; Momentum joint parameters
//! `[tx, ty, tz, rx, ry, rz, s]` with `R = Rz·Ry·Rx` after the pre-rotation and scale `2^s`;
//! skinning transforms map rest-space points to posed points.

pub mod blend;
pub mod body;
pub mod builtin;
pub mod choreography;
pub mod correctives;
mod error;
pub mod file;
pub mod fit;
pub mod glb;
pub mod gltf;
pub mod mhr;
pub mod obj;
pub mod params;
pub mod rig;
pub mod roles;
pub mod sequence;
mod shape_roles;
pub mod skeleton;
pub mod skin;
pub mod smplx;
pub mod spec;

pub use blend::BlendShapes;
pub use body::CanonicalPose;
pub use error::RigError;
pub use params::{ModelDefinition, ParameterTransform, parse_model, read_model_file};
pub use rig::{JointModel, Mesh, Parameterization, Posed, Rig, RigParams, vertex_normals};
pub use roles::{Role, RoleMap, Roles};
pub use skeleton::{Joint, JointPose, PARAMS_PER_JOINT, Similarity, Skeleton, euler_xyz};
pub use skin::{MAX_INFLUENCES, PointTransform, SkinWeights, point_transforms, skin_points};
pub use spec::ModelSpec;
