//! LLVM compilation targets.

/// The target a [`PlironCompiler`](crate::PlironCompiler) would compile for.
///
/// The real crate's `Cpu` variant is left out: no user of this stub names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LlvmTarget {
    /// AMD GPUs, as `cubecl-hip` configures it.
    #[cfg(feature = "amdgpu")]
    AmdGpu,
    /// NVIDIA GPUs, as `cubecl-cuda` configures it.
    #[cfg(feature = "nvptx")]
    Nvptx,
}
