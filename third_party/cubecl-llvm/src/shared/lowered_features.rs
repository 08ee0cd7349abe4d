//! What a device advertises, narrowed to what the LLVM backend lowers for it.
//!
//! The GPU runtimes call [`restrict_features`] only when the LLVM backend is their default
//! (`cubecl-cuda`/`cubecl-hip` built without `cpp`). This stub's backend compiles nothing, so
//! there is nothing to narrow to and the properties are left as the C++ backend reported them.

use cubecl_core::ir::DeviceProperties;
#[cfg(feature = "amdgpu")]
use cubecl_core::ir::amd::AmdWmma;

/// The GPU target a device's features are narrowed for, with what its lowering depends on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GpuTarget {
    /// NVIDIA GPUs.
    #[cfg(feature = "nvptx")]
    Nvptx,
    /// `wmma` is the part's WMMA generation, `None` on a part without one.
    #[cfg(feature = "amdgpu")]
    AmdGpu { wmma: Option<AmdWmma> },
}

/// Leaves `props` unchanged: the stub lowers nothing for any `target`, and every compile it is
/// asked for fails, so narrowing the advertisement would change nothing that runs.
pub fn restrict_features(props: &mut DeviceProperties, target: GpuTarget) {
    let _ = (props, target);
}
