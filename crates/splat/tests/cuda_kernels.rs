//! The offline CUDA kernel check: the CUDA C of every splat kernel (`src/cube/cuda_source.rs`)
//! compiled by NVRTC for `sm_90a` with the options cubecl-cuda uses at run time, then by
//! `ptxas -v` for its registers, spills and shared memory. It needs NVRTC and CUDA's headers,
//! not a GPU: `CUDA_PATH` names a directory with `include/` and `bin/ptxas`, and `libnvrtc` is on
//! the loader path. `tools/cuda-offline.sh` sets both up from PyPI (NVIDIA's 13.0 wheels) and
//! runs this test, as CI does:
//!
//! ```text
//! tools/cuda-offline.sh test     # or, by hand:
//! CUDA_PATH=… LD_LIBRARY_PATH=…/lib cargo test --release -p f3g-splat --features cuda-source \
//!     --test cuda_kernels -- --nocapture
//! ```
//!
//! With `--nocapture` it prints a table of every kernel: NVRTC time, registers, spills, shared
//! memory (BENCHMARKS.md "CUDA kernels, compiled offline").

use std::ffi::{CStr, CString};
use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use f3g_splat::cube::cuda_source::{CudaTarget, KernelSource};
use f3g_splat::cube::kernel_sources;

/// Where NVRTC's headers and ptxas are, from `CUDA_PATH` as cubecl-cuda reads it.
struct Toolkit {
    include: PathBuf,
    ptxas: PathBuf,
}

fn toolkit() -> Toolkit {
    let help = "the offline CUDA check needs CUDA 13.0's NVRTC, headers and ptxas (no GPU): \
                run `tools/cuda-offline.sh test`, or set CUDA_PATH to a directory with include/ \
                and bin/ptxas and put libnvrtc.so.13 on LD_LIBRARY_PATH";
    let root = PathBuf::from(std::env::var_os("CUDA_PATH").unwrap_or_else(|| panic!("{help}")));
    let toolkit = Toolkit {
        include: root.join("include"),
        ptxas: root.join("bin/ptxas"),
    };
    assert!(
        toolkit.include.join("cuda_runtime.h").is_file() && toolkit.ptxas.is_file(),
        "{}: no include/cuda_runtime.h or bin/ptxas; {help}",
        root.display()
    );
    // SAFETY: only tries to dlopen cudarc's candidate names for libnvrtc.
    let nvrtc = unsafe { cudarc::nvrtc::sys::is_culib_present() };
    assert!(nvrtc, "no libnvrtc; {help}");
    toolkit
}

fn nvrtc_version() -> (i32, i32) {
    let (mut major, mut minor) = (0, 0);
    // SAFETY: NVRTC writes two ints; the library was found by `toolkit`.
    unsafe { cudarc::nvrtc::sys::nvrtcVersion(&mut major, &mut minor) }
        .result()
        .expect("nvrtcVersion");
    (major, minor)
}

/// PTX for `source`, compiled as cubecl-cuda's `compile_to_ptx` compiles it, or NVRTC's log.
fn nvrtc(source: &str, architecture: &str, toolkit: &Toolkit) -> Result<String, String> {
    let mut options = vec![
        format!("--gpu-architecture={architecture}"),
        format!("--include-path={}", toolkit.include.display()),
        "-lineinfo".to_string(),
    ];
    let cccl = toolkit.include.join("cccl");
    if cccl.exists() {
        options.push(format!("--include-path={}", cccl.display()));
    }
    let c_source = CString::new(source).map_err(|err| err.to_string())?;
    let program = cudarc::nvrtc::result::create_program(&c_source, None)
        .map_err(|err| format!("nvrtcCreateProgram: {err}"))?;
    // SAFETY: `program` is live until destroyed below; the strings outlive the calls.
    let result = unsafe {
        match cudarc::nvrtc::result::compile_program(program, &options) {
            Ok(()) => cudarc::nvrtc::result::get_ptx(program)
                .map(|ptx| c_chars_to_string(&ptx))
                .map_err(|err| format!("nvrtcGetPTX: {err}")),
            Err(err) => Err(cudarc::nvrtc::result::get_program_log(program)
                .map(|log| c_chars_to_string(&log))
                .unwrap_or_else(|_| err.to_string())),
        }
    };
    // SAFETY: created above and not used after.
    unsafe { cudarc::nvrtc::result::destroy_program(program) }.expect("nvrtcDestroyProgram");
    result
}

fn c_chars_to_string(chars: &[std::ffi::c_char]) -> String {
    let bytes: Vec<u8> = chars.iter().map(|&c| c as u8).collect();
    CStr::from_bytes_until_nul(&bytes)
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|_| String::from_utf8_lossy(&bytes).into_owned())
}

/// What `ptxas -v` reports for a kernel.
#[derive(Debug, Default)]
struct Resources {
    registers: u32,
    spill_stores: u32,
    spill_loads: u32,
    stack_bytes: u32,
    static_shared_bytes: u32,
}

fn ptxas(ptx: &str, architecture: &str, toolkit: &Toolkit) -> Result<Resources, String> {
    let dir = tempfile::tempdir().map_err(|err| err.to_string())?;
    let input = dir.path().join("kernel.ptx");
    std::fs::write(&input, ptx).map_err(|err| err.to_string())?;
    let output = Command::new(&toolkit.ptxas)
        .arg(format!("-arch={architecture}"))
        .arg("-v")
        .arg(&input)
        .arg("-o")
        .arg(dir.path().join("kernel.cubin"))
        .output()
        .map_err(|err| format!("{}: {err}", toolkit.ptxas.display()))?;
    let report = String::from_utf8_lossy(&output.stderr).into_owned()
        + &String::from_utf8_lossy(&output.stdout);
    if !output.status.success() {
        return Err(report);
    }
    let mut resources = Resources::default();
    // "N bytes stack frame, N bytes spill stores, N bytes spill loads" and
    // "Used N registers, used N barriers, N bytes smem, N bytes cmem[0]".
    for part in report.split(['\n', ',']) {
        let words: Vec<&str> = part.split_whitespace().collect();
        let number = |at: usize| words.get(at).and_then(|w| w.parse::<u32>().ok());
        let ends = |suffix: &[&str]| words.ends_with(suffix);
        if let Some(i) = words.iter().position(|&w| w == "Used")
            && words.get(i + 2) == Some(&"registers")
        {
            resources.registers = words[i + 1].parse().unwrap_or(0);
        } else if ends(&["bytes", "stack", "frame"]) {
            resources.stack_bytes = number(words.len() - 4).unwrap_or(0);
        } else if ends(&["bytes", "spill", "stores"]) {
            resources.spill_stores = number(words.len() - 4).unwrap_or(0);
        } else if ends(&["bytes", "spill", "loads"]) {
            resources.spill_loads = number(words.len() - 4).unwrap_or(0);
        } else if ends(&["bytes", "smem"]) {
            resources.static_shared_bytes = number(words.len() - 3).unwrap_or(0);
        }
    }
    if resources.registers == 0 {
        return Err(format!("no register count in ptxas's report:\n{report}"));
    }
    Ok(resources)
}

/// Every kernel the splat op launches on CUDA compiles for `sm_90a`, and ptxas accepts it.
#[test]
fn every_splat_kernel_compiles_for_sm_90_with_nvrtc_and_ptxas() {
    let toolkit = toolkit();
    let target = CudaTarget::hopper();
    let architecture = target.architecture();
    let sources = kernel_sources(&target).unwrap();
    let (major, minor) = nvrtc_version();
    println!(
        "NVRTC {major}.{minor}, {architecture}, {} kernels\n",
        sources.len()
    );
    println!(
        "| kernel | NVRTC ms | registers | spill stores / loads (B) | stack (B) | shared memory (B, dynamic + static) |"
    );
    println!("|---|---|---|---|---|---|");
    let mut failures = Vec::new();
    let mut total = Duration::ZERO;
    for KernelSource {
        label,
        source,
        shared_memory_bytes,
        ..
    } in &sources
    {
        let started = Instant::now();
        let ptx = nvrtc(source, &architecture, &toolkit);
        let elapsed = started.elapsed();
        total += elapsed;
        match ptx.and_then(|ptx| ptxas(&ptx, &architecture, &toolkit)) {
            Ok(r) => println!(
                "| {label} | {:.0} | {} | {} / {} | {} | {shared_memory_bytes} + {} |",
                elapsed.as_secs_f64() * 1e3,
                r.registers,
                r.spill_stores,
                r.spill_loads,
                r.stack_bytes,
                r.static_shared_bytes
            ),
            Err(log) => failures.push(format!("{label}:\n{log}\n[source]\n{source}")),
        }
    }
    println!(
        "\nNVRTC total: {:.2} s for {} kernels",
        total.as_secs_f64(),
        sources.len()
    );
    assert!(
        failures.is_empty(),
        "{} of {} kernels failed:\n{}",
        failures.len(),
        sources.len(),
        failures.join("\n\n")
    );
}

/// The check fails on a kernel that does not compile: one kernel's source with a statement
/// NVRTC cannot resolve, put in as a change to a kernel would put it.
#[test]
fn a_kernel_that_does_not_compile_is_reported_with_nvrtcs_log() {
    let toolkit = toolkit();
    let target = CudaTarget::hopper();
    let sources = kernel_sources(&target).unwrap();
    let kernel = sources
        .iter()
        .find(|source| source.label == "gather")
        .unwrap();
    let body = kernel.source.rfind('{').unwrap() + 1;
    let mut broken = kernel.source.clone();
    broken.insert_str(body, "\nundeclared_in_cuda(0);\n");
    let log = nvrtc(&broken, &target.architecture(), &toolkit).unwrap_err();
    assert!(log.contains("undeclared_in_cuda"), "{log}");
    assert!(nvrtc(&kernel.source, &target.architecture(), &toolkit).is_ok());
}

/// Every `#[cube(launch)]` function of `src/cube` is in [`kernel_sources`], so a kernel added
/// without its entry there fails this test rather than escaping the check above.
#[test]
fn every_launched_kernel_has_its_source() {
    let files = [
        include_str!("../src/cube/backend.rs"),
        include_str!("../src/cube/bin.rs"),
        include_str!("../src/cube/project.rs"),
        include_str!("../src/cube/project_backward.rs"),
        include_str!("../src/cube/raster.rs"),
        include_str!("../src/cube/scan.rs"),
        include_str!("../src/cube/sort.rs"),
    ];
    let mut declared: Vec<String> = files
        .iter()
        .flat_map(|file| {
            file.split("#[cube(launch)]").skip(1).map(|after| {
                let name = after.split("pub fn ").nth(1).expect("a kernel function");
                name.split(['(', '<']).next().unwrap().trim().to_string()
            })
        })
        .collect();
    declared.sort();
    let sources = kernel_sources(&CudaTarget::hopper()).unwrap();
    let mut generated: Vec<String> = sources
        .iter()
        .map(|source| source.label.split(' ').next().unwrap().to_string())
        .collect();
    generated.sort();
    generated.dedup();
    assert_eq!(declared, generated);
    for source in &sources {
        assert!(
            source.source.contains(&source.entrypoint),
            "{}: no {} in its source",
            source.label,
            source.entrypoint
        );
    }
}
