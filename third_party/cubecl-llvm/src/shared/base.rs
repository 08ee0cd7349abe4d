//! `PlironCompiler`, its options and what it would produce.

#[cfg(feature = "nvptx")]
use crate::nvptx::ptx_version::PtxVersion;
use crate::target::LlvmTarget;
use cubecl_core::ir::amd::GfxArch;
#[cfg(feature = "nvptx")]
use cubecl_core::ir::nvidia::SmArch;
use cubecl_environment::backtrace::BackTrace;
#[cfg(feature = "amdgpu")]
use cubecl_environment::bytes::Bytes;
use cubecl_runtime::{
    compiler::{CompilationError, Compiler},
    kernel::{BufferIOAttr, KernelDefinition},
};

/// The LLVM compiler. Its [`Compiler::compile`] always fails: this build has no LLVM.
#[derive(Clone, Debug)]
pub struct PlironCompiler {
    /// The target it would compile for.
    pub target: LlvmTarget,
}

/// Compilation options, with the fields the GPU runtimes set; the CPU-only ones are left out.
#[derive(Clone, Debug, Default)]
pub struct PlironOptions {
    /// AMDGPU architecture, or `None` for other targets.
    pub arch: Option<GfxArch>,
    /// NVPTX architecture, or `None` for other targets.
    #[cfg(feature = "nvptx")]
    pub sm_arch: Option<SmArch>,
    /// PTX version to emit, or `None` for the oldest the architecture accepts.
    #[cfg(feature = "nvptx")]
    pub ptx_version: Option<PtxVersion>,
    /// Pass scalars and static metadata in the kernel parameter block.
    pub grid_constants: bool,
}

/// Compiled AMDGPU module. Never built by this stub; `cubecl-hip` names its fields.
#[cfg(feature = "amdgpu")]
#[derive(Clone, Debug)]
pub struct AmdGpuModule {
    /// Loadable AMD code object.
    pub code_object: Bytes,
    /// IR for logging and cache keys.
    pub ir: String,
    /// Shared memory required per launch, in bytes.
    pub shared_memory_size: usize,
    /// Buffer access modes in binding order.
    pub io: Vec<BufferIOAttr>,
}

/// Compiled PTX module. Never built by this stub; `cubecl-cuda` names its fields.
#[cfg(feature = "nvptx")]
#[derive(Clone, Debug)]
pub struct NvptxModule {
    /// NUL-terminated PTX assembly.
    pub ptx: Vec<core::ffi::c_char>,
    /// IR for logging and cache keys.
    pub ir: String,
    /// Shared memory required per launch, in bytes.
    pub shared_memory_size: usize,
    /// Buffer access modes in binding order.
    pub io: Vec<BufferIOAttr>,
}

/// Compiled kernel artifact. The real crate's `Jit` (CPU) variant is left out.
#[derive(Clone)]
pub enum PlironArtifact {
    /// A linked AMD code object.
    #[cfg(feature = "amdgpu")]
    AmdGpuCode(AmdGpuModule),
    /// PTX for the CUDA driver.
    #[cfg(feature = "nvptx")]
    NvptxCode(NvptxModule),
}

impl PlironArtifact {
    /// The module's IR text.
    fn ir(&self) -> &str {
        match *self {
            #[cfg(feature = "amdgpu")]
            PlironArtifact::AmdGpuCode(ref module) => module.ir.as_str(),
            #[cfg(feature = "nvptx")]
            PlironArtifact::NvptxCode(ref module) => module.ir.as_str(),
        }
    }

    /// The module's buffer access modes, in binding order.
    fn io(&self) -> &[BufferIOAttr] {
        match *self {
            #[cfg(feature = "amdgpu")]
            PlironArtifact::AmdGpuCode(ref module) => module.io.as_slice(),
            #[cfg(feature = "nvptx")]
            PlironArtifact::NvptxCode(ref module) => module.io.as_slice(),
        }
    }
}

impl core::fmt::Display for PlironArtifact {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.ir())
    }
}

impl Compiler for PlironCompiler {
    type Representation = PlironArtifact;
    type CompilationOptions = PlironOptions;

    fn buffer_io(repr: &Self::Representation) -> Option<Vec<BufferIOAttr>> {
        Some(repr.io().to_vec())
    }

    /// Always an error: this `cubecl-llvm` is the offline stub, built without LLVM.
    fn compile(
        &mut self,
        kernel: KernelDefinition,
        _compilation_options: &Self::CompilationOptions,
    ) -> Result<Self::Representation, CompilationError> {
        Err(CompilationError::Generic {
            reason: format!(
                "cannot compile `{}` for {:?}: this cubecl-llvm is an offline stub built without \
                 LLVM; build cubecl-cuda (or cubecl-hip) with its `cpp` feature to compile \
                 through NVRTC (or HIP RTC) instead",
                kernel.settings.kernel_name, self.target
            ),
            backtrace: BackTrace::capture(),
        })
    }

    fn extension(&self) -> &'static str {
        "ll"
    }

    fn lang_tag(&self) -> &'static str {
        "llvm"
    }
}
