//! `--device cpu|wgpu[:N]|cuda[:N]`: which machine a command computes on.
//!
//! The spelling is parsed by clap (so a typo is a usage error), and a device is created only
//! when a command asks for it: creating a CUDA device loads `libcuda` and creating a wgpu device
//! probes the graphics drivers, neither of which a CPU run should pay for or depend on. Asking
//! for a device that does not exist — or for a backend this binary was built without — is an
//! error that lists what does exist.
//!
//! - `cpu`: Burn's Flex backend (always built).
//! - `wgpu`: the adapter wgpu prefers; `wgpu:N`: the N-th adapter in the order listed by the
//!   error message (Vulkan/Metal/DX12 through WGSL; needs the `gpu` feature).
//! - `cuda` = `cuda:0`, `cuda:N`: an NVIDIA GPU through NVRTC (needs the `cuda` feature).

use std::fmt;
use std::str::FromStr;

use anyhow::Result;
#[cfg(not(all(feature = "gpu", feature = "cuda")))]
use anyhow::bail;
use burn::tensor::Device;
use f3g_avatar::train::AllReduce;

use crate::cuda_probe::{self, CudaVersion, Wanted};

/// `--device`, as every command that computes declares it (flattened into its arguments).
#[derive(clap::Args, Clone, Copy, Debug, PartialEq, Eq)]
pub struct DeviceArg {
    /// Device to compute on: cpu, wgpu[:N] or cuda[:N] (GPUs need a binary built with the
    /// `gpu` or `cuda` feature).
    #[arg(id = "device", long = "device", default_value = "cpu")]
    pub spec: DeviceSpec,
}

impl DeviceArg {
    /// Creates the device.
    pub fn open(&self) -> Result<Device> {
        self.spec.open()
    }
}

impl fmt::Display for DeviceArg {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.spec.fmt(f)
    }
}

/// A device as named on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum DeviceSpec {
    #[default]
    Cpu,
    /// `None`: the adapter wgpu prefers.
    Wgpu(Option<usize>),
    Cuda(usize),
}

impl FromStr for DeviceSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (kind, index) = match s.split_once(':') {
            Some((kind, index)) => {
                let index = index.parse::<usize>().map_err(|_| {
                    format!("`{index}` in `{s}` is not a device index (expected 0, 1, …)")
                })?;
                (kind, Some(index))
            }
            None => (s, None),
        };
        match (kind, index) {
            ("cpu", None) => Ok(Self::Cpu),
            ("cpu", Some(_)) => Err(format!("`{s}`: the CPU device takes no index")),
            ("wgpu", index) => Ok(Self::Wgpu(index)),
            ("cuda", index) => Ok(Self::Cuda(index.unwrap_or(0))),
            _ => Err(format!(
                "unknown device `{s}` (expected cpu, wgpu, wgpu:N, cuda or cuda:N)"
            )),
        }
    }
}

impl fmt::Display for DeviceSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Cpu => write!(f, "cpu"),
            Self::Wgpu(None) => write!(f, "wgpu"),
            Self::Wgpu(Some(i)) => write!(f, "wgpu:{i}"),
            Self::Cuda(i) => write!(f, "cuda:{i}"),
        }
    }
}

/// Pins Burn's default device to the CPU (`BURN_DEVICE=flex`) for this process. f3g names
/// every device it computes on (`--device`); Burn itself falls back to its default device in
/// one place, loading an optimiser's state (`ModuleOptimizer::load_record`, burn-optim 0.22.1),
/// whose tensors move to their parameters' device at the next step. Unpinned, the default is the
/// first GPU backend compiled in: a `cuda` build resuming a run on a machine without CUDA
/// panicked in cudarc, and a user's `BURN_DEVICE` naming a backend not built would too.
///
/// Call first in `main`, before any thread exists (the environment is process-wide).
pub fn pin_burn_default_device() {
    // SAFETY: called at the start of `main`, before f3g or its libraries start a thread, so
    // nothing reads the environment concurrently.
    unsafe { std::env::set_var("BURN_DEVICE", "flex") };
}

/// How data-parallel replicas on `devices` sum their gradients: with NCCL when they are
/// distinct CUDA devices and `libnccl` loads, otherwise on the host's terms (which every device
/// has).
pub fn all_reduce_for(devices: &[DeviceSpec]) -> AllReduce {
    let cuda = devices.iter().all(|d| matches!(d, DeviceSpec::Cuda(_)));
    if devices.len() > 1 && cuda && distinct(devices) && nccl_present() {
        AllReduce::Collective
    } else {
        AllReduce::Host
    }
}

fn distinct(devices: &[DeviceSpec]) -> bool {
    devices
        .iter()
        .enumerate()
        .all(|(i, d)| !devices[..i].contains(d))
}

#[cfg(feature = "cuda")]
fn nccl_present() -> bool {
    // SAFETY: only tries to load the library.
    unsafe { cudarc::nccl::sys::is_culib_present() }
}

#[cfg(not(feature = "cuda"))]
fn nccl_present() -> bool {
    false
}

impl DeviceSpec {
    /// Creates the device (without autodiff).
    pub fn open(self) -> Result<Device> {
        match self {
            Self::Cpu => Ok(Device::flex()),
            Self::Wgpu(index) => open_wgpu(index),
            Self::Cuda(index) => open_cuda(index),
        }
    }
}

#[cfg(feature = "gpu")]
fn open_wgpu(index: Option<usize>) -> Result<Device> {
    use anyhow::anyhow;
    use burn::tensor::DeviceKind;
    use wgpu::DeviceType;

    let kind = match index {
        None => DeviceKind::DefaultDevice,
        Some(i) => {
            let adapters = wgpu_adapters();
            let info = adapters.get(i).ok_or_else(|| {
                anyhow!(
                    "there is no wgpu:{i}; the wgpu adapters of this machine are:\n{}",
                    adapter_listing(&adapters)
                )
            })?;
            // cubecl names an adapter by its type and its position among adapters of that type.
            let nth = adapters[..i]
                .iter()
                .filter(|a| a.device_type == info.device_type)
                .count();
            match info.device_type {
                DeviceType::DiscreteGpu => DeviceKind::DiscreteGpu(nth),
                DeviceType::IntegratedGpu => DeviceKind::IntegratedGpu(nth),
                DeviceType::VirtualGpu => DeviceKind::VirtualGpu(nth),
                DeviceType::Cpu => DeviceKind::Cpu,
                DeviceType::Other => {
                    return Err(anyhow!(
                        "wgpu:{i} ({}) is of an unknown type that cubecl cannot select",
                        info.name
                    ));
                }
            }
        }
    };
    // The adapters are listed only when something went wrong: probing them costs start-up time.
    Device::wgpu_options()
        .device_kind(kind)
        .init()
        .map_err(|e| {
            anyhow!(
                "creating the wgpu device: {e}; the wgpu adapters of this machine are:\n{}",
                adapter_listing(&wgpu_adapters())
            )
        })
}

/// The adapters of the primary graphics APIs (Vulkan, Metal, DX12), in wgpu's order. cubecl
/// counts adapters within one API; leaving out the GL fallback keeps one adapter from being
/// listed twice (once per API) and so keeps `wgpu:N` pointing where cubecl will look.
#[cfg(feature = "gpu")]
fn wgpu_adapters() -> Vec<wgpu::AdapterInfo> {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle());
    let adapters =
        futures_lite::future::block_on(instance.enumerate_adapters(wgpu::Backends::PRIMARY));
    adapters.iter().map(|a| a.get_info()).collect()
}

/// One adapter per line, as `--device` names it.
#[cfg(feature = "gpu")]
fn adapter_listing(adapters: &[wgpu::AdapterInfo]) -> String {
    if adapters.is_empty() {
        return "  (none)".into();
    }
    adapters
        .iter()
        .enumerate()
        .map(|(i, a)| {
            format!(
                "  wgpu:{i}  {} ({:?}, {:?})",
                a.name, a.device_type, a.backend
            )
        })
        .collect::<Vec<_>>()
        .join("\n")
}

#[cfg(not(feature = "gpu"))]
fn open_wgpu(_index: Option<usize>) -> Result<Device> {
    bail!(
        "this f3g was built without wgpu support; rebuild with `cargo build --release -p f3g-cli \
         --features gpu` (devices available here: cpu{})",
        if cfg!(feature = "cuda") { ", cuda" } else { "" }
    )
}

#[cfg(feature = "cuda")]
fn open_cuda(index: usize) -> Result<Device> {
    use anyhow::bail;

    let wanted = cuda_wanted();
    let problems = cuda_probe::probe(&wanted).problems(&wanted);
    if !problems.is_empty() {
        bail!(
            "cuda:{index} was asked for, but this machine cannot run CUDA kernels yet (`f3g devices` \
             shows what it has):\n- {}\nuse --device cpu{} meanwhile",
            problems.join("\n- "),
            if cfg!(feature = "gpu") {
                " or --device wgpu"
            } else {
                ""
            }
        );
    }
    let devices = cuda_devices()?;
    if index >= devices.len() {
        bail!(
            "there is no cuda:{index}; the CUDA devices of this machine are:\n{}",
            if devices.is_empty() {
                "  (none)".into()
            } else {
                devices
                    .iter()
                    .map(|d| format!("  {d}"))
                    .collect::<Vec<_>>()
                    .join("\n")
            }
        );
    }
    kernel_cache::configure();
    Ok(Device::cuda(index))
}

/// CubeCL's compilation cache for CUDA: compiled kernels (PTX) and autotune's choices kept
/// between processes, so only the first process on a machine pays for NVRTC and tuning.
pub mod kernel_cache {
    use std::path::{Path, PathBuf};

    #[cfg(feature = "cuda")]
    use burn::cubecl::config::cache::CacheConfig;
    #[cfg(feature = "cuda")]
    use burn::cubecl::config::memory::PersistentMemory;
    #[cfg(feature = "cuda")]
    use burn::cubecl::config::profiling::ProfilingLogLevel;
    #[cfg(feature = "cuda")]
    use burn::cubecl::config::{CubeClRuntimeConfig, RuntimeConfig};

    /// Where the cache goes: `F3G_KERNEL_CACHE` (a folder, or `off`), else
    /// `$XDG_CACHE_HOME/f3g/cubecl`, else `~/.cache/f3g/cubecl`.
    pub fn folder(var: impl Fn(&str) -> Option<String>) -> Option<PathBuf> {
        match var("F3G_KERNEL_CACHE").as_deref() {
            Some("off") => None,
            Some(dir) if !dir.is_empty() => Some(PathBuf::from(dir)),
            _ => var("XDG_CACHE_HOME")
                .filter(|d| !d.is_empty())
                .map(PathBuf::from)
                .or_else(|| var("HOME").map(|home| Path::new(&home).join(".cache")))
                .map(|cache| cache.join("f3g").join("cubecl")),
        }
    }

    /// The CubeCL configuration file CubeCL itself would read (`cubecl.toml`, or `burn.toml`
    /// with its `[cubecl]` section, in the working directory or above), if any.
    #[cfg(feature = "cuda")]
    fn users_file() -> Option<PathBuf> {
        let mut dir = std::env::current_dir().ok()?;
        loop {
            let names = CubeClRuntimeConfig::file_names().iter().copied().chain(
                CubeClRuntimeConfig::section_file_names()
                    .iter()
                    .map(|(name, _)| *name),
            );
            for name in names {
                if dir.join(name).is_file() {
                    return Some(dir.join(name));
                }
            }
            if !dir.pop() {
                return None;
            }
        }
    }

    /// Turns the cache on in [`folder`], serves weight-sized allocations from CubeCL's persistent
    /// pool, and with `F3G_KERNEL_PROFILE=FILE` CubeCL's kernel
    /// profile (each launch timed on the device, one `| duration | kernel` line per launch and
    /// a summary table at each synchronisation, in FILE; the launches are serialised, so only
    /// the shares mean anything), unless a CubeCL configuration file of the user's decides
    /// (then it is CubeCL's to read, untouched). Must run before the first CUDA device is
    /// created: CubeCL reads its configuration once per process.
    #[cfg(feature = "cuda")]
    pub fn configure() {
        if users_file().is_some() {
            return;
        }
        let mut config = CubeClRuntimeConfig::default().override_from_env();
        // Allocations of a size some weight already has are served from exact-size persistent
        // buckets (CubeCL's advice for training): the optimisers' per-parameter tensors no longer
        // search the sliced pool's pages, the largest host cost of a `paper` step (offline
        // driver: optimiser phase 163 -> 28-44 ms, step 1.26 -> 0.95-1.20 s of host time).
        config.memory.persistent_memory = PersistentMemory::SizeMatch;
        if let Some(folder) = folder(|name| std::env::var(name).ok()) {
            config.compilation.cache = true;
            config.environment.path = CacheConfig::Directory(folder);
        }
        if let Some(file) = std::env::var_os("F3G_KERNEL_PROFILE").filter(|f| !f.is_empty()) {
            // Basic unless CUBECL_DEBUG_OPTION asked for more (`profile-full` adds each
            // launch's cube count and comptime configuration).
            if matches!(config.profiling.logger.level, ProfilingLogLevel::Disabled) {
                config.profiling.logger.level = ProfilingLogLevel::Basic;
            }
            config.profiling.logger.file = Some(file.into());
            config.profiling.logger.append = false;
        }
        CubeClRuntimeConfig::try_set(config);
    }
}

/// One line per CUDA device: `cuda:N  name (compute capability, memory)`.
#[cfg(feature = "cuda")]
fn cuda_devices() -> Result<Vec<String>> {
    use cudarc::driver::CudaContext;

    let count = CudaContext::device_count()
        .map_err(|e| anyhow::anyhow!("asking the CUDA driver for its devices: {e}"))?;
    Ok((0..usize::try_from(count).unwrap_or(0))
        .map(|i| match CudaContext::new(i) {
            Ok(c) => {
                let name = c.name().unwrap_or_else(|e| format!("unnamed ({e})"));
                let (major, minor) = c.compute_capability().unwrap_or((0, 0));
                let gib = c.total_mem().unwrap_or(0) as f64 / (1u64 << 30) as f64;
                format!("cuda:{i}  {name} (sm_{major}{minor}, {gib:.0} GiB)")
            }
            Err(e) => format!("cuda:{i}  cannot be opened: {e}"),
        })
        .collect())
}

#[cfg(not(feature = "cuda"))]
fn cuda_devices() -> Result<Vec<String>> {
    Ok(Vec::new())
}

/// What this binary's CUDA support loads: cudarc's library names, the CUDA version its bindings
/// were built for and cubecl-cuda's CUDA installation.
#[cfg(feature = "cuda")]
fn cuda_wanted() -> Wanted {
    Wanted {
        built_for: built_for(),
        driver: cudarc::get_lib_name_candidates("cuda"),
        nvrtc: cudarc::get_lib_name_candidates("nvrtc"),
        nccl: cudarc::get_lib_name_candidates("nccl"),
        cuda_path: cubecl_cuda::install::cuda_path(),
    }
}

/// What a `cuda` build for CUDA 13.0 (the README's) would load: cudarc's Linux file names and
/// cubecl-cuda's search for a CUDA installation, neither of which this build links.
#[cfg(not(feature = "cuda"))]
fn cuda_wanted() -> Wanted {
    let names = |lib: &str| -> Vec<String> {
        ["", ".13", ".12", ".1"]
            .iter()
            .map(|v| format!("lib{lib}.so{v}"))
            .collect()
    };
    let exists = |p: &str| std::path::Path::new(p).exists();
    let cuda_path = std::env::var_os("CUDA_PATH")
        .map(std::path::PathBuf::from)
        .or_else(|| {
            ["/usr/local/cuda", "/opt/cuda"]
                .into_iter()
                .find(|p| exists(p))
                .or(exists("/usr/bin/nvcc").then_some("/usr"))
                .map(std::path::PathBuf::from)
        });
    Wanted {
        built_for: Some(CudaVersion::from_encoded(13000)),
        driver: names("cuda"),
        nvrtc: names("nvrtc"),
        nccl: names("nccl"),
        cuda_path,
    }
}

/// `CUDARC_CUDA_VERSION` as this binary was built with (13000 = 13.0); `None` when cudarc took
/// the version from an installed toolkit instead.
#[cfg(feature = "cuda")]
fn built_for() -> Option<CudaVersion> {
    option_env!("CUDARC_CUDA_VERSION")
        .and_then(|v| v.parse().ok())
        .map(CudaVersion::from_encoded)
}

/// Options of `f3g devices`.
#[derive(clap::Args, Debug)]
pub struct DevicesArgs {
    /// Print what was found as JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `f3g devices`: what this binary can compute on, and what CUDA needs from this machine.
pub fn devices(a: &DevicesArgs) -> Result<()> {
    let wanted = cuda_wanted();
    let found = cuda_probe::probe(&wanted);
    let problems = found.problems(&wanted);
    let built = cfg!(feature = "cuda");
    let cuda = if built && problems.is_empty() {
        cuda_devices()?
    } else {
        Vec::new()
    };
    let wgpu = wgpu_listing();
    let threads = rayon::current_num_threads();
    if a.json {
        let json = serde_json::json!({
            "cpu": { "threads": threads },
            "wgpu": wgpu,
            "cuda": {
                "built": built,
                "built_for": wanted.built_for.map(|v| v.to_string()),
                "driver": found.driver,
                "nvrtc": found.nvrtc,
                "include": found.include,
                "nccl": found.nccl,
                "kernel_cache": kernel_cache::folder(|name| std::env::var(name).ok()),
                "problems": problems,
                "devices": cuda,
            },
        });
        println!("{}", serde_json::to_string_pretty(&json)?);
        return Ok(());
    }
    println!("cpu  Burn Flex, {threads} threads");
    match wgpu {
        Some(adapters) if adapters.is_empty() => println!("wgpu  no adapter"),
        Some(adapters) => adapters.iter().for_each(|a| println!("{a}")),
        None => println!("wgpu  not built in (cargo build --release -p f3g-cli --features gpu)"),
    }
    match (built, wanted.built_for) {
        (true, Some(v)) => println!("CUDA  built for CUDA {v}"),
        (true, None) => println!("CUDA  built for the CUDA toolkit of the build machine"),
        (false, _) => println!(
            "CUDA  not built in (CUDARC_CUDA_VERSION=13000 cargo build --release -p f3g-cli \
             --features cuda); what such a build would find here:"
        ),
    }
    for line in found.describe().lines() {
        println!("  {line}");
    }
    match kernel_cache::folder(|name| std::env::var(name).ok()) {
        Some(dir) => println!(
            "  kernel cache {} (F3G_KERNEL_CACHE=off to disable)",
            dir.display()
        ),
        None => println!("  kernel cache off"),
    }
    for p in &problems {
        println!("  missing: {p}");
    }
    cuda.iter().for_each(|d| println!("{d}"));
    Ok(())
}

/// The wgpu adapters as `--device` names them, or `None` without the `gpu` feature.
#[cfg(feature = "gpu")]
fn wgpu_listing() -> Option<Vec<String>> {
    let adapters = wgpu_adapters();
    Some(if adapters.is_empty() {
        Vec::new()
    } else {
        adapter_listing(&adapters)
            .lines()
            .map(|l| l.trim_start().to_string())
            .collect()
    })
}

#[cfg(not(feature = "gpu"))]
fn wgpu_listing() -> Option<Vec<String>> {
    None
}

#[cfg(not(feature = "cuda"))]
fn open_cuda(index: usize) -> Result<Device> {
    bail!(
        "cuda:{index} was asked for, but this f3g was built without CUDA support; rebuild with \
         `CUDARC_CUDA_VERSION=13000 cargo build --release -p f3g-cli --features cuda` (devices \
         available here: cpu{})",
        if cfg!(feature = "gpu") { ", wgpu" } else { "" }
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_kernel_cache_goes_where_the_environment_says() {
        use std::path::PathBuf;
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |name: &str| {
                pairs
                    .iter()
                    .find(|(k, _)| *k == name)
                    .map(|(_, v)| v.to_string())
            }
        };
        let folder = kernel_cache::folder;
        assert_eq!(
            folder(env(&[("HOME", "/home/a")])),
            Some(PathBuf::from("/home/a/.cache/f3g/cubecl"))
        );
        assert_eq!(
            folder(env(&[("HOME", "/home/a"), ("XDG_CACHE_HOME", "/c")])),
            Some(PathBuf::from("/c/f3g/cubecl"))
        );
        assert_eq!(
            folder(env(&[("HOME", "/home/a"), ("F3G_KERNEL_CACHE", "/k")])),
            Some(PathBuf::from("/k"))
        );
        assert_eq!(
            folder(env(&[("HOME", "/h"), ("F3G_KERNEL_CACHE", "off")])),
            None
        );
        assert_eq!(folder(env(&[])), None);
    }
    #[test]
    fn device_names_parse_and_print_back() {
        for (text, spec) in [
            ("cpu", DeviceSpec::Cpu),
            ("wgpu", DeviceSpec::Wgpu(None)),
            ("wgpu:1", DeviceSpec::Wgpu(Some(1))),
            ("cuda:3", DeviceSpec::Cuda(3)),
        ] {
            assert_eq!(text.parse::<DeviceSpec>(), Ok(spec));
            assert_eq!(spec.to_string(), text);
        }
        assert_eq!("cuda".parse::<DeviceSpec>(), Ok(DeviceSpec::Cuda(0)));
        for bad in ["gpu", "cuda:x", "cpu:0", "cuda:-1", ""] {
            let err = bad.parse::<DeviceSpec>().unwrap_err();
            assert!(err.contains(bad) || bad.is_empty(), "{err}");
        }
    }

    #[test]
    fn the_cpu_device_always_opens() {
        let device = DeviceSpec::Cpu.open().unwrap();
        assert!(!device.is_autodiff());
    }

    #[test]
    fn replicas_use_nccl_only_on_distinct_cuda_devices() {
        let specs =
            |s: &str| -> Vec<DeviceSpec> { s.split(',').map(|d| d.parse().unwrap()).collect() };
        for host in ["cpu,cpu", "cuda:0,cuda:0", "cuda:0,wgpu", "cuda:1"] {
            assert_eq!(all_reduce_for(&specs(host)), AllReduce::Host, "{host}");
        }
        let expected = if nccl_present() {
            AllReduce::Collective
        } else {
            AllReduce::Host
        };
        assert_eq!(all_reduce_for(&specs("cuda:0,cuda:1")), expected);
    }

    #[cfg(not(feature = "cuda"))]
    #[test]
    fn asking_for_cuda_without_the_feature_says_how_to_build_it() {
        let err = DeviceSpec::Cuda(0).open().unwrap_err().to_string();
        assert!(err.contains("--features cuda"), "{err}");
        assert!(err.contains("available here: cpu"), "{err}");
    }
}
