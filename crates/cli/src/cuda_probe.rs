//! What a CUDA run needs from the machine, checked before Burn touches it.
//!
//! cudarc loads CUDA's libraries on first use and panics when one is missing or too old, and
//! cubecl-cuda panics at its first kernel compilation when it finds no CUDA include directory.
//! So `--device cuda` and `f3g devices` first load each library here (the file names cudarc
//! would try, in its order) and ask its version:
//! - the driver (`libcuda`): the CUDA version it supports must be at least the one this binary
//!   was built for (`CUDARC_CUDA_VERSION`), and it must export the entry points that version's
//!   bindings call (13.0's `cuEventElapsedTime_v2`: driver ≥ 580);
//! - NVRTC (`libnvrtc`), which compiles every kernel: not newer than the driver, whose PTX JIT
//!   has no minor-version compatibility (PTX from NVRTC 13.1 does not load on a 13.0 driver);
//! - an include directory (`CUDA_PATH`/include, else `/usr/local/cuda`, `/opt/cuda`, `/usr`),
//!   which NVRTC compiles against;
//! - NCCL (`libnccl`), optional: without it data-parallel replicas sum gradients on the host.
//!
//! The probe takes the file names and the include candidate as inputs, so tests drive it with
//! fake libraries built on the spot.

use std::fmt;
use std::path::PathBuf;

/// A CUDA version, as `cuDriverGetVersion` encodes it (`1000 · major + 10 · minor`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
pub struct CudaVersion {
    pub major: u32,
    pub minor: u32,
}

impl CudaVersion {
    /// From the driver's and `CUDARC_CUDA_VERSION`'s encoding (13000 = 13.0).
    pub fn from_encoded(v: u32) -> Self {
        Self {
            major: v / 1000,
            minor: (v % 1000) / 10,
        }
    }

    /// The encoding [`CudaVersion::from_encoded`] reads.
    pub fn encoded(self) -> u32 {
        1000 * self.major + 10 * self.minor
    }

    /// The oldest Linux driver release that supports this CUDA version, where known.
    fn minimum_driver(self) -> Option<u32> {
        match (self.major, self.minor) {
            (13, _) => Some(580),
            (12, m) if m >= 8 => Some(570),
            (12, _) => Some(525),
            _ => None,
        }
    }
}

impl fmt::Display for CudaVersion {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}.{}", self.major, self.minor)
    }
}

/// What to look for.
#[derive(Clone, Debug)]
pub struct Wanted {
    /// The CUDA version the binary's bindings were built for; `None` when unknown.
    pub built_for: Option<CudaVersion>,
    /// File names to try for each library, in order (cudarc's candidates).
    pub driver: Vec<String>,
    pub nvrtc: Vec<String>,
    pub nccl: Vec<String>,
    /// The CUDA installation cubecl-cuda would take, if any (its `include/` is used).
    pub cuda_path: Option<PathBuf>,
}

/// A library that loaded, and the version it reported.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Found {
    pub file: String,
    pub version: Option<CudaVersion>,
}

/// What the probe found.
#[derive(Clone, Debug)]
pub struct Findings {
    pub driver: Option<Found>,
    /// Driver entry points the bindings call that the driver does not export.
    pub missing_entry_points: Vec<&'static str>,
    pub nvrtc: Option<Found>,
    /// The include directory, when it exists.
    pub include: Option<PathBuf>,
    pub nccl: Option<Found>,
}

/// Loads the first of `names` that loads.
fn load(names: &[String]) -> Option<(String, libloading::Library)> {
    names.iter().find_map(|name| {
        // SAFETY: loading a CUDA library runs its initialisers, as cudarc's loading would.
        unsafe { libloading::Library::new(name) }
            .ok()
            .map(|lib| (name.clone(), lib))
    })
}

/// Calls `symbol(int*) -> status` and returns the integer when the status is 0.
fn query_one(lib: &libloading::Library, symbol: &[u8]) -> Option<i32> {
    // SAFETY: the CUDA driver's and NCCL's version queries take one `int*` and return a status.
    unsafe {
        let f = lib
            .get::<unsafe extern "C" fn(*mut i32) -> i32>(symbol)
            .ok()?;
        let mut v = 0;
        (f(&mut v) == 0).then_some(v)
    }
}

/// Entry points of the driver that the bindings for `built_for` call beyond older drivers'.
fn entry_points(built_for: Option<CudaVersion>) -> &'static [&'static str] {
    match built_for {
        Some(v) if v.major >= 13 => &["cuDriverGetVersion", "cuEventElapsedTime_v2"],
        _ => &["cuDriverGetVersion"],
    }
}

/// Looks for everything in `wanted`.
pub fn probe(wanted: &Wanted) -> Findings {
    let mut missing_entry_points = Vec::new();
    let driver = load(&wanted.driver).map(|(file, lib)| {
        for &name in entry_points(wanted.built_for) {
            let symbol = format!("{name}\0");
            // SAFETY: only looks the symbol up.
            if unsafe { lib.get::<*const ()>(symbol.as_bytes()) }.is_err() {
                missing_entry_points.push(name);
            }
        }
        let version = query_one(&lib, b"cuDriverGetVersion\0")
            .and_then(|v| u32::try_from(v).ok())
            .map(CudaVersion::from_encoded);
        Found { file, version }
    });
    let nvrtc = load(&wanted.nvrtc).map(|(file, lib)| {
        // SAFETY: `nvrtcResult nvrtcVersion(int* major, int* minor)`.
        let version = unsafe {
            lib.get::<unsafe extern "C" fn(*mut i32, *mut i32) -> i32>(b"nvrtcVersion\0")
                .ok()
                .and_then(|f| {
                    let (mut major, mut minor) = (0, 0);
                    (f(&mut major, &mut minor) == 0).then_some((major, minor))
                })
        }
        .and_then(|(major, minor)| {
            Some(CudaVersion {
                major: u32::try_from(major).ok()?,
                minor: u32::try_from(minor).ok()?,
            })
        });
        Found { file, version }
    });
    let nccl = load(&wanted.nccl).map(|(file, lib)| Found {
        file,
        // NCCL encodes 2.27.3 as 22703: shown as major.minor of NCCL, not of CUDA.
        version: query_one(&lib, b"ncclGetVersion\0")
            .and_then(|v| u32::try_from(v).ok())
            .map(|v| CudaVersion {
                major: v / 10000,
                minor: (v % 10000) / 100,
            }),
    });
    let include = wanted
        .cuda_path
        .as_ref()
        .map(|p| p.join("include"))
        .filter(|p| p.is_dir());
    Findings {
        driver,
        missing_entry_points,
        nvrtc,
        include,
        nccl,
    }
}

impl Findings {
    /// Each requirement that is not met, as a sentence saying which library, what version and
    /// what to install or set. Empty when a CUDA device can be created.
    pub fn problems(&self, wanted: &Wanted) -> Vec<String> {
        let mut problems = Vec::new();
        let built = wanted.built_for.map_or_else(
            || "this build's CUDA version".into(),
            |v| format!("CUDA {v}"),
        );
        let driver_release = wanted
            .built_for
            .and_then(CudaVersion::minimum_driver)
            .map_or_else(String::new, |r| format!(" (release {r} or newer)"));
        match &self.driver {
            None => problems.push(format!(
                "the NVIDIA driver library was not found (tried {}): install the NVIDIA driver{driver_release}, or add the directory holding libcuda.so.1 to LD_LIBRARY_PATH",
                wanted.driver.join(", ")
            )),
            Some(d) => {
                match (d.version, wanted.built_for) {
                    (None, _) => problems.push(format!(
                        "{} did not report its CUDA version (cuDriverGetVersion failed): it is not a working NVIDIA driver",
                        d.file
                    )),
                    (Some(have), Some(need)) if have < need => problems.push(format!(
                        "the NVIDIA driver ({}) supports CUDA {have}, older than the {built} this f3g was built for: install a driver{driver_release}, or rebuild with CUDARC_CUDA_VERSION={}",
                        d.file,
                        have.encoded()
                    )),
                    _ => {}
                }
                if !self.missing_entry_points.is_empty() {
                    problems.push(format!(
                        "the NVIDIA driver ({}) lacks {}, which f3g's {built} bindings call: install a driver{driver_release}",
                        d.file,
                        self.missing_entry_points.join(", ")
                    ));
                }
            }
        }
        match &self.nvrtc {
            None => problems.push(format!(
                "NVRTC, CUDA's run-time compiler, was not found (tried {}): install it (the CUDA toolkit, or pip's nvidia-cuda-nvrtc) and add its lib directory to LD_LIBRARY_PATH",
                wanted.nvrtc.join(", ")
            )),
            Some(n) => match (n.version, self.driver.as_ref().and_then(|d| d.version)) {
                (None, _) => problems.push(format!(
                    "{} did not report its version (nvrtcVersion failed): it is not a working NVRTC",
                    n.file
                )),
                (Some(nvrtc), Some(driver)) if nvrtc > driver => problems.push(format!(
                    "NVRTC {nvrtc} ({}) is newer than the driver's CUDA {driver}: the kernels it compiles would not load (PTX has no minor-version compatibility); use an NVRTC of CUDA {driver} or older, or update the driver",
                    n.file
                )),
                _ => {}
            },
        }
        if self.include.is_none() {
            problems.push(match &wanted.cuda_path {
                Some(p) => format!(
                    "{} has no include directory, which NVRTC compiles the kernels against: set CUDA_PATH to a CUDA installation (its include/ holds cuda_fp16.h)",
                    p.display()
                ),
                None => "no CUDA installation was found for NVRTC's headers (CUDA_PATH is unset and /usr/local/cuda, /opt/cuda and /usr/bin/nvcc are absent): set CUDA_PATH to a directory whose include/ holds CUDA's headers".into(),
            });
        }
        problems
    }

    /// One line per requirement, for `f3g devices`.
    pub fn describe(&self) -> String {
        let library = |found: &Option<Found>, what: &str| match found {
            Some(Found {
                file,
                version: Some(v),
            }) => format!("{what}: {file}, {v}"),
            Some(Found {
                file,
                version: None,
            }) => format!("{what}: {file}, version unknown"),
            None => format!("{what}: not found"),
        };
        let mut lines = [
            library(&self.driver, "driver (CUDA version it supports)"),
            library(&self.nvrtc, "NVRTC"),
            match &self.include {
                Some(p) => format!("include directory: {}", p.display()),
                None => "include directory: not found".into(),
            },
            library(&self.nccl, "NCCL"),
        ];
        if self.nccl.is_none() {
            lines[3] += " (data-parallel replicas on several GPUs sum gradients on the host)";
        }
        lines.join("\n")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;
    use std::process::Command;

    /// Builds a shared library from C source into `dir`, returning its path.
    fn fake_library(dir: &Path, name: &str, source: &str) -> String {
        let c = dir.join(format!("{name}.c"));
        let so = dir.join(format!("{name}.so"));
        std::fs::write(&c, source).unwrap();
        let status = Command::new("cc")
            .args(["-shared", "-fPIC", "-o"])
            .arg(&so)
            .arg(&c)
            .status()
            .expect("a C compiler (cc) builds the fake CUDA libraries");
        assert!(status.success());
        so.to_str().unwrap().to_string()
    }

    fn driver(dir: &Path, name: &str, version: u32, v2: bool) -> String {
        let v2 = if v2 {
            "int cuEventElapsedTime_v2(float* ms, void* a, void* b) { return 0; }"
        } else {
            ""
        };
        fake_library(
            dir,
            name,
            &format!("int cuDriverGetVersion(int* v) {{ *v = {version}; return 0; }}\n{v2}\n"),
        )
    }

    fn nvrtc(dir: &Path, name: &str, major: u32, minor: u32) -> String {
        fake_library(
            dir,
            name,
            &format!(
                "int nvrtcVersion(int* a, int* b) {{ *a = {major}; *b = {minor}; return 0; }}\n"
            ),
        )
    }

    fn wanted(dir: &Path, driver: &str, nvrtc: &str, nccl: &str) -> Wanted {
        Wanted {
            built_for: Some(CudaVersion::from_encoded(13000)),
            driver: vec![
                dir.join("absent.so").to_str().unwrap().into(),
                driver.into(),
            ],
            nvrtc: vec![nvrtc.into()],
            nccl: vec![nccl.into()],
            cuda_path: Some(dir.to_path_buf()),
        }
    }

    #[test]
    fn a_machine_that_has_everything_passes() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::create_dir(d.join("include")).unwrap();
        let w = wanted(
            d,
            &driver(d, "cuda13", 13000, true),
            &nvrtc(d, "nvrtc13", 13, 0),
            &fake_library(
                d,
                "nccl",
                "int ncclGetVersion(int* v) { *v = 22703; return 0; }",
            ),
        );
        let found = probe(&w);
        assert_eq!(found.problems(&w), Vec::<String>::new());
        assert_eq!(
            found.driver.as_ref().unwrap().version,
            Some(CudaVersion {
                major: 13,
                minor: 0
            })
        );
        let text = found.describe();
        assert!(
            text.contains("cuda13.so, 13.0") && text.contains("NVRTC: "),
            "{text}"
        );
        assert!(text.contains("NCCL: ") && text.contains(", 2.27"), "{text}");
        assert!(text.contains(&d.join("include").display().to_string()));
    }

    #[test]
    fn each_missing_or_old_library_is_named_with_what_to_do() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        // A CUDA 12.4 driver without 13.0's entry point, an NVRTC newer than it, no NCCL, no
        // include directory.
        let w = wanted(
            d,
            &driver(d, "cuda124", 12040, false),
            &nvrtc(d, "nvrtc131", 13, 1),
            "absent-nccl.so",
        );
        let found = probe(&w);
        let problems = found.problems(&w);
        assert_eq!(problems.len(), 4, "{problems:#?}");
        assert!(
            problems[0].contains("supports CUDA 12.4")
                && problems[0].contains("release 580")
                && problems[0].contains("CUDARC_CUDA_VERSION=12040"),
            "{}",
            problems[0]
        );
        assert!(
            problems[1].contains("cuEventElapsedTime_v2"),
            "{}",
            problems[1]
        );
        assert!(
            problems[2].contains("NVRTC 13.1") && problems[2].contains("CUDA 12.4"),
            "{}",
            problems[2]
        );
        assert!(problems[3].contains("CUDA_PATH"), "{}", problems[3]);
        assert!(found.describe().contains("NCCL: not found (data-parallel"));

        // Nothing at all: the driver and NVRTC are named with the files tried.
        let none = Wanted {
            driver: vec!["libcuda-absent.so.1".into()],
            nvrtc: vec!["libnvrtc-absent.so.13".into()],
            cuda_path: None,
            ..w
        };
        let problems = probe(&none).problems(&none);
        assert_eq!(problems.len(), 3, "{problems:#?}");
        assert!(
            problems[0].contains("libcuda-absent.so.1") && problems[0].contains("LD_LIBRARY_PATH")
        );
        assert!(problems[1].contains("libnvrtc-absent.so.13"));
        assert!(problems[2].contains("CUDA_PATH is unset"));
    }

    #[test]
    fn a_library_that_is_not_cuda_is_not_taken_for_one() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let other = fake_library(d, "other", "int unrelated(void) { return 1; }");
        std::fs::create_dir(d.join("include")).unwrap();
        let w = wanted(d, &other, &other, &other);
        let problems = probe(&w).problems(&w);
        assert!(
            problems
                .iter()
                .any(|p| p.contains("not a working NVIDIA driver"))
                && problems.iter().any(|p| p.contains("not a working NVRTC")),
            "{problems:#?}"
        );
    }
}
