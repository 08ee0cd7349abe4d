//! Interruption and write failures, with the real binary: `kill -9` at any moment of
//! `f3g train` (checkpoint writing included) leaves no half-written file under its final name
//! and a run that resumes to exactly the losses of an uninterrupted one; a write that fails
//! (a file-size limit stands in for a full disk: writes fail mid-file with `EFBIG`) is a clear
//! error that keeps the last good checkpoint and every earlier output. Unix only (signals,
//! resource limits).
#![cfg(unix)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::{losses, ok};
use f3g_avatar::infer::TrainedAvatar;

mod common;

fn f3g(dir: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_f3g"));
    c.current_dir(dir);
    c
}

/// A capture and the configuration in a fresh folder.
fn setup() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(&f3g(d)
        .args([
            "synth",
            "--out",
            "cap",
            "--frames",
            "5",
            "--resolution",
            "128",
        ])
        .output()
        .unwrap());
    // A checkpoint after every step, so that kills land in checkpoint writes too.
    let config = common::tiny_config([2, 2, 1, 3, 2], r#", "checkpoint_every": 1"#);
    std::fs::write(d.join("tiny.json"), config).unwrap();
    dir
}

const NEW_RUN: [&str; 7] = [
    "train",
    "--data",
    "cap",
    "--config",
    "tiny.json",
    "--out",
    "",
];

fn new_run(d: &Path, name: &str) -> Command {
    let mut args = NEW_RUN;
    args[6] = name;
    let mut c = f3g(d);
    c.args(args);
    c
}

fn files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            files(&p, out);
        } else {
            out.push(p);
        }
    }
}

/// Every file under its final name is whole: JSON parses, `.npz` archives and PNGs open, the
/// newest checkpoint loads with all its networks. Temporaries left by a kill are not final
/// names; they are counted (a resume sweeps them away).
fn check_whole(run: &Path) -> usize {
    let mut all = Vec::new();
    files(run, &mut all);
    let mut temporaries = 0;
    for p in &all {
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        if name.starts_with(f3g_io::TEMPORARY_PREFIX) {
            temporaries += 1;
        } else if name.ends_with(".json") {
            let text = std::fs::read_to_string(p).unwrap();
            serde_json::from_str::<serde_json::Value>(&text)
                .unwrap_or_else(|e| panic!("{} is not whole: {e}", p.display()));
        } else if name.ends_with(".npz") {
            f3g_io::Npz::open(p).unwrap_or_else(|e| panic!("{e}"));
        } else if name.ends_with(".png") {
            f3g_io::read_rgb(p).unwrap_or_else(|e| panic!("{e}"));
        }
    }
    if run.join("checkpoints/latest").exists() {
        TrainedAvatar::load(run, &burn::tensor::Device::flex())
            .unwrap_or_else(|e| panic!("after a kill: {e}"));
    }
    temporaries
}

/// Waits until the run's log has more than `lines` lines or the process ends.
fn wait_for_step(run: &Path, lines: usize, child: &mut std::process::Child) -> bool {
    let deadline = Instant::now() + Duration::from_secs(120);
    while Instant::now() < deadline {
        if child.try_wait().unwrap().is_some() {
            return false;
        }
        if losses(run).len() > lines {
            return true;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    panic!("no training step within two minutes");
}

#[test]
fn runs_killed_at_any_moment_resume_to_the_same_losses() {
    let dir = setup();
    let d = dir.path();
    ok(&new_run(d, "whole").output().unwrap());
    let reference = losses(&d.join("whole"));
    assert_eq!(reference.len(), 10);

    // Kill after each logged step, after a delay that moves through the step: the log line is
    // written before validation and the checkpoint, so short delays land in checkpoint writes.
    let run = d.join("parts");
    let delays_ms = [0, 2, 5, 10, 20, 40, 80, 0, 3, 7, 15];
    let quiet = |mut c: Command| {
        c.stdout(Stdio::null()).stderr(Stdio::null());
        c.spawn().unwrap()
    };
    let mut child = quiet(new_run(d, "parts"));
    let (mut kills, mut temporaries) = (0, 0);
    loop {
        let seen = losses(&run).len();
        if !wait_for_step(&run, seen, &mut child) {
            break;
        }
        std::thread::sleep(Duration::from_millis(delays_ms[kills % delays_ms.len()]));
        child.kill().unwrap(); // SIGKILL
        let status = child.wait().unwrap();
        if status.success() {
            break; // it finished before the signal
        }
        kills += 1;
        temporaries += check_whole(&run);
        let mut resume = f3g(d);
        resume.args(["train", "--resume", "parts"]);
        child = quiet(resume);
    }
    let status = child.wait().unwrap();
    assert!(status.success(), "the last resume failed");
    assert!(kills >= 5, "only {kills} kills landed");
    // The last resume swept what earlier kills left behind.
    assert_eq!(check_whole(&run), 0);
    assert_eq!(losses(&run), reference, "after {kills} kills");
    eprintln!("{kills} kills, {temporaries} leftover temporaries seen");
}

/// Runs `cmd` with writes limited to files of `bytes` (`EFBIG` beyond, as a full disk fails a
/// write part-way; `SIGXFSZ` ignored so the write returns the error instead of killing).
fn with_file_size_limit(cmd: &mut Command, bytes: u64) -> Output {
    use std::os::unix::process::CommandExt;
    // SAFETY: between fork and exec only async-signal-safe calls are made.
    unsafe {
        cmd.pre_exec(move || {
            libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
            let limit = libc::rlimit {
                rlim_cur: bytes,
                rlim_max: bytes,
            };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &limit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    cmd.output().unwrap()
}

#[test]
fn a_failing_disk_is_a_clear_error_that_keeps_the_last_checkpoint() {
    let dir = setup();
    let d = dir.path();
    let run = d.join("run");
    ok(&new_run(d, "run")
        .args(["--max-steps", "3"])
        .output()
        .unwrap());
    let latest = std::fs::read_to_string(run.join("checkpoints/latest")).unwrap();
    let before = losses(&run);
    let nets = std::fs::metadata(run.join("checkpoints").join(latest.trim()).join("nets.bpk"))
        .unwrap()
        .len();

    // Files larger than a third of the networks cannot be written: the next checkpoint fails.
    let out = with_file_size_limit(f3g(d).args(["train", "--resume", "run"]), nets / 3);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("step-") && stderr.to_lowercase().contains("file too large"),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    eprintln!("the failed checkpoint: {stderr}");
    check_whole(&run);
    assert_eq!(
        std::fs::read_to_string(run.join("checkpoints/latest")).unwrap(),
        latest
    );

    // Exports fail the same way and leave nothing under the final name.
    let out = with_file_size_limit(f3g(d).args(["export-ply", "run", "--out", "a.ply"]), 4096);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("a.ply"));
    assert!(!d.join("a.ply").exists());

    // With room again the run resumes from the kept checkpoint and finishes as if nothing
    // had happened.
    ok(&f3g(d).args(["train", "--resume", "run"]).output().unwrap());
    let after = losses(&run);
    assert_eq!(after[..before.len()], before[..]);
    ok(&new_run(d, "whole").output().unwrap());
    assert_eq!(after, losses(&d.join("whole")));
}

/// Temporary files under `dir`, at any depth.
fn temporaries(dir: &Path) -> Vec<PathBuf> {
    let mut all = Vec::new();
    files(dir, &mut all);
    all.retain(|p| {
        p.file_name()
            .is_some_and(|n| n.to_string_lossy().starts_with(f3g_io::TEMPORARY_PREFIX))
    });
    all
}

/// SIGINT and SIGTERM in the middle of writing (`synth` writes images on every worker) end the
/// command with status 130 and no temporary file behind; a temporary that a killed process
/// left is removed by the next write into its folder.
#[test]
fn interrupts_remove_unfinished_files_and_kills_leave_none_for_long() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let synth = |out: &str| {
        let mut c = f3g(d);
        c.args([
            "synth",
            "--out",
            out,
            "--frames",
            "400",
            "--resolution",
            "256",
        ])
        .args(["--cameras", "8"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
        c.spawn().unwrap()
    };
    for (i, signal) in [libc::SIGINT, libc::SIGTERM, libc::SIGINT, libc::SIGTERM]
        .into_iter()
        .enumerate()
    {
        let out = format!("cap{i}");
        let child = synth(&out);
        // Once images are being written, wait a little more (moving through a write).
        let deadline = Instant::now() + Duration::from_secs(120);
        while !d.join(&out).join("cam00/00000001.jpg").exists() {
            assert!(
                Instant::now() < deadline,
                "synth wrote nothing in two minutes"
            );
            std::thread::sleep(Duration::from_millis(5));
        }
        std::thread::sleep(Duration::from_millis(50 + 37 * i as u64));
        // SAFETY: kill(2) with a child's pid and a valid signal number.
        assert_eq!(unsafe { libc::kill(child.id() as i32, signal) }, 0);
        let result = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&result.stderr);
        assert_eq!(result.status.code(), Some(130), "{stderr}");
        assert!(stderr.contains("interrupted"), "{stderr}");
        assert_eq!(temporaries(&d.join(&out)), Vec::<PathBuf>::new());
    }

    // SIGKILL cannot be caught: what it leaves goes with the next write into the folder.
    let folder = d.join("cap0");
    let left = folder.join(format!("{}4294967295-abcdef", f3g_io::TEMPORARY_PREFIX));
    std::fs::write(&left, b"half a file").unwrap();
    ok(&f3g(d)
        .args(["synth", "--out", "cap0", "--overwrite", "--frames", "1"])
        .args(["--cameras", "1", "--resolution", "64"])
        .output()
        .unwrap());
    assert!(!left.exists());
}
