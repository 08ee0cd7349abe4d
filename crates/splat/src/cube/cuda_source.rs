//! The CUDA C of a splat kernel, as cubecl-cuda would hand it to NVRTC on a Hopper GPU,
//! made without a device (each kernel file expands its own kernels with it; the parent's
//! `kernel_sources` gathers them): a CPU machine can then compile each one with NVRTC and read its
//! registers, spills and shared memory with `ptxas -v` (`tests/cuda_kernels.rs`, run in CI),
//! so a kernel that does not compile for `sm_90` is found before a GPU is at hand.
//!
//! The kernels are expanded as a launch would expand them: the same kernel structs the
//! `#[cube(launch)]` macro generates, with the same cube dims, comptime values and variants
//! the launch sites choose (for the backward, [`Accumulation::best`] on these properties: the
//! warp-sum path with float atomics that only CUDA takes), and compiled by cubecl-cuda's own
//! compiler with the options its runtime sets. The device is described as cubecl-cuda 0.11.3's
//! runtime describes an H100 (`DeviceService::init` in its `runtime.rs`), limited to what
//! these kernels can read: types, atomics, plane operations and the compiler's features.
//!
//! [`Accumulation::best`]: super::raster::Accumulation::best

use std::sync::Arc;

use burn_cubecl::cubecl::frontend::{
    BufferCompilationArg, TensorCompilationArg, TensorMetaCompilationArg,
};
use burn_cubecl::cubecl::ir::features::Plane;
use burn_cubecl::cubecl::ir::{
    AddressType, DeviceIdentity, DeviceProperties, HardwareProperties, MemoryDeviceProperties,
    TargetProperties,
};
use burn_cubecl::cubecl::prelude::{CubeDim, ExecutionMode, KernelSettings};
use burn_cubecl::cubecl::profile::TimingMethod;
// CubeCL exports its `Runtime` trait to its macros only; it is needed here for the CUDA
// runtime's (static) target properties.
use burn_cubecl::cubecl::__private::Runtime;
use burn_cubecl::cubecl::{Compiler, CubeKernel, define_kernel};
use cubecl_cuda::{CudaCompilationOptions, CudaCompiler, CudaRuntime};

/// One kernel's CUDA C, as NVRTC would receive it.
#[derive(Clone, Debug)]
pub struct KernelSource {
    /// The kernel and the variant, e.g. `project (SH degree 3)`.
    pub label: String,
    /// The `extern "C" __global__` function's name in [`source`](Self::source).
    pub entrypoint: String,
    /// The complete translation unit.
    pub source: String,
    /// Dynamic shared memory the launch reserves, in bytes.
    pub shared_memory_bytes: usize,
}

/// A CUDA device to compile for, described as cubecl-cuda's runtime describes it.
pub struct CudaTarget {
    compute_capability: u32,
    properties: Arc<DeviceProperties>,
    target: Arc<TargetProperties>,
    options: CudaCompilationOptions,
}

impl CudaTarget {
    /// An H100 (compute capability 9.0, 132 SMs, 227 KiB of shared memory per block).
    pub fn hopper() -> Self {
        let compute_capability = 90;
        let hardware = HardwareProperties {
            load_width: 128,
            vector_register_count: None,
            plane_size_min: 32,
            plane_size_max: 32,
            max_bindings: cubecl_cuda::CUDA_MAX_BINDINGS,
            max_shared_memory_size: 232_448,
            max_cube_count: (i32::MAX as u32, 65_535, 65_535),
            max_units_per_cube: 1024,
            max_cube_dim: (1024, 1024, 64),
            num_streaming_multiprocessors: Some(132),
            num_cpu_cores: None,
            last_level_cache_size: None,
            num_tensor_cores: None,
            min_tensor_cores_dim: None,
            max_vector_size: usize::MAX,
            cube_mma_reserved_shared_memory: 0,
        };
        let memory = MemoryDeviceProperties::new(80 << 30 >> 2, 512).with_max_memory(80 << 30);
        let mut properties = DeviceProperties::new(
            Default::default(),
            memory,
            hardware,
            TimingMethod::Device,
            DeviceIdentity {
                name: "NVIDIA H100 (offline)".into(),
                fingerprint: format!("ptx_sm{compute_capability}"),
                physical: None,
            },
        );
        cubecl_cpp::register_supported_types(&mut properties);
        let features = &mut properties.features;
        features.plane.insert(Plane::Ops);
        features.plane.insert(Plane::NonUniformControlFlow);
        features.plane.insert(Plane::Sync);
        features.memory_reinterpret = true;
        features.alignment = true;
        features.device_memory_scope = true;
        features.copy_async = true;
        features.cube_cluster = true;

        let mut options = CudaCompilationOptions::default();
        options.cpp.warp_size = 32;
        let supports = &mut options.cpp.supports_features;
        supports.fast_math = true;
        supports.dp4a = true;
        supports.grid_constants = true;
        supports.fast_tanh = true;
        supports.clusters = true;
        supports.elect_sync = true;
        Self {
            compute_capability,
            properties: Arc::new(properties),
            target: Arc::new(<CudaRuntime as Runtime>::target_properties()),
            options,
        }
    }

    /// NVRTC's `--gpu-architecture` value, as cubecl-cuda passes it (`sm_90a` from 9.0 on).
    pub fn architecture(&self) -> String {
        let suffix = if self.compute_capability >= 90 {
            "a"
        } else {
            ""
        };
        format!("sm_{}{suffix}", self.compute_capability)
    }

    /// The device's properties, as the kernels see them when they expand.
    pub fn properties(&self) -> &DeviceProperties {
        &self.properties
    }

    /// What a `#[cube(launch)]` kernel's constructor takes before its arguments.
    pub(crate) fn settings(
        &self,
        cube_dim: CubeDim,
    ) -> (KernelSettings, Arc<DeviceProperties>, Arc<TargetProperties>) {
        (
            KernelSettings::new(*cube_dim, ExecutionMode::Checked, AddressType::U32),
            self.properties.clone(),
            self.target.clone(),
        )
    }

    /// Expands `kernel` and compiles it to CUDA C as cubecl-cuda's runtime would.
    pub(crate) fn source(
        &self,
        label: impl Into<String>,
        kernel: impl CubeKernel,
    ) -> Result<KernelSource, String> {
        let label = label.into();
        let definition =
            define_kernel(&kernel).map_err(|err| format!("{label}: expansion failed: {err}"))?;
        let entrypoint = definition.settings.kernel_name.clone();
        let compiled = CudaCompiler::default()
            .compile(definition, &self.options)
            .map_err(|err| format!("{label}: CUDA C generation failed: {err}"))?;
        Ok(KernelSource {
            label,
            entrypoint,
            shared_memory_bytes: compiled.shared_memory_size(),
            source: compiled.to_string(),
        })
    }
}

/// A tensor argument as a launch registers it (its own buffer, not aliasing an input).
pub(crate) fn tensor() -> TensorCompilationArg {
    TensorCompilationArg {
        meta: TensorMetaCompilationArg { len: (), rank: () },
        buffer: BufferCompilationArg { inplace: None },
    }
}
