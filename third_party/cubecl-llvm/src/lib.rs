//! Offline stub of `cubecl-llvm` 0.11.3, CubeCL's pliron/LLVM compiler.
//!
//! `cubecl-cuda` 0.11 always compiles and links its LLVM backend next to the CUDA C++ one, and
//! the real `cubecl-llvm` downloads a prebuilt LLVM from GitHub in its build script (through
//! `tracel-llvm-bundler`), which cannot work offline. The workspace's `[patch.crates-io]` puts
//! this crate in its place: same name, version and features, but only the items `cubecl-cuda`
//! (and `cubecl-hip`) name, and no LLVM.
//!
//! With `cubecl-cuda`'s `cpp` feature, CUDA C++ through NVRTC is the default backend, so the
//! LLVM one is never selected. Were it selected anyway, [`PlironCompiler`]'s `compile` returns a
//! [`CompilationError`](cubecl_runtime::compiler::CompilationError) saying so rather than a
//! module. Nothing here lowers, links or loads anything. The CPU target (`PlironEngine` and
//! the rest that `cubecl-cpu` uses) is not provided.

#[cfg(feature = "nvptx")]
pub mod nvptx;
pub mod shared;
pub mod target;

#[cfg(feature = "amdgpu")]
pub use shared::AmdGpuModule;
#[cfg(feature = "nvptx")]
pub use shared::NvptxModule;
pub use shared::{PlironArtifact, PlironCompiler, PlironOptions};
pub use target::LlvmTarget;
