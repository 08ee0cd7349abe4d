//! LPIPS against the reference values of the LPIPS project's own examples, SSIM/PSNR against
//! scikit-image (`tools/metrics_golden.py`), and gradients through the losses.

use std::path::Path;

use burn::tensor::{Device, Tensor};
use f3g_nets::lpips::{Lpips, LpipsNet, weights_dir, weights_file};
use f3g_nets::metrics::{dssim_loss, image_tensor, psnr, ssim_images, ssim_skimage};

fn data(name: &str) -> f3g_io::Image {
    f3g_io::read_rgb(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(name),
    )
    .unwrap()
}

fn lpips_pair(lpips: &Lpips, a: &str, b: &str) -> f32 {
    let device = Device::flex();
    let d = lpips
        .forward(
            image_tensor(&data(a), &device),
            image_tensor(&data(b), &device),
        )
        .unwrap();
    d.into_data().try_into_vec::<f32>().unwrap()[0]
}

#[test]
fn lpips_alex_matches_the_reference() {
    let lpips = Lpips::load(LpipsNet::Alex, &Device::flex()).unwrap();
    let p0 = lpips_pair(&lpips, "ex_ref.png", "ex_p0.png");
    let p1 = lpips_pair(&lpips, "ex_ref.png", "ex_p1.png");
    assert!((p0 - 0.7219).abs() < 1e-3, "d(ref, p0) = {p0}");
    assert!((p1 - 0.1376).abs() < 1e-3, "d(ref, p1) = {p1}");
    assert!(lpips_pair(&lpips, "ex_ref.png", "ex_ref.png").abs() < 1e-6);
}

/// The VGG weights are fetched, not committed: CI installs them (`.ci/run`), and there this test
/// must run; elsewhere it says loudly that it could not.
#[test]
fn lpips_vgg_matches_the_reference() {
    let path = weights_dir().join(weights_file(LpipsNet::Vgg));
    if !path.exists() {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI must install the LPIPS VGG weights at {} (f3g weights lpips --net vgg)",
            path.display()
        );
        eprintln!(
            "NOT RUN: LPIPS VGG weights absent at {}; install them with `f3g weights lpips --net vgg`",
            path.display()
        );
        return;
    }
    let lpips = Lpips::load(LpipsNet::Vgg, &Device::flex()).unwrap();
    let p0 = lpips_pair(&lpips, "ex_ref.png", "ex_p0.png");
    let p1 = lpips_pair(&lpips, "ex_ref.png", "ex_p1.png");
    assert!((p0 - 0.5686).abs() < 1e-3, "d(ref, p0) = {p0}");
    assert!((p1 - 0.4217).abs() < 1e-3, "d(ref, p1) = {p1}");
}

#[test]
fn missing_vgg_weights_say_how_to_get_them() {
    let dir = tempfile::tempdir().unwrap();
    let e = Lpips::from_file(
        LpipsNet::Vgg,
        &dir.path().join("none.safetensors"),
        &Device::flex(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("none.safetensors"), "{e}");
    std::fs::write(dir.path().join("bad.safetensors"), b"not weights").unwrap();
    let e = Lpips::from_file(
        LpipsNet::Vgg,
        &dir.path().join("bad.safetensors"),
        &Device::flex(),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("bad.safetensors") && e.contains("safetensors"),
        "{e}"
    );
}

#[test]
fn ssim_both_conventions_and_psnr_match_scikit_image() {
    let golden: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/metrics_golden.json"),
        )
        .unwrap(),
    )
    .unwrap();
    let pairs = golden["pairs"].as_array().unwrap();
    assert_eq!(pairs.len(), 4);
    for p in pairs {
        let (a, b) = (
            data(p["a"].as_str().unwrap()),
            data(p["b"].as_str().unwrap()),
        );
        let s = ssim_images(&a, &b).unwrap();
        let k = ssim_skimage(&a, &b).unwrap();
        let q = psnr(&a, &b).unwrap();
        let (es, ek, eq) = (
            p["ssim_3dgs"].as_f64().unwrap(),
            p["ssim"].as_f64().unwrap(),
            p["psnr"].as_f64().unwrap(),
        );
        assert!((s - es).abs() < 2e-5, "{p}: 3DGS SSIM {s} vs {es}");
        // Only the f32 storage of the 8-bit values separates the two.
        assert!((k - ek).abs() < 1e-7, "{p}: scikit-image SSIM {k} vs {ek}");
        assert!((q - eq).abs() < 1e-4, "{p}: PSNR {q} vs {eq}");
    }
}

#[test]
fn gradients_through_lpips_and_dssim_are_finite_and_descend() {
    let device = Device::flex().autodiff();
    let lpips = Lpips::load(LpipsNet::Alex, &device).unwrap();
    let target = image_tensor(&data("ex_ref.png"), &device);
    let start = image_tensor(&data("ex_p0.png"), &device);
    let x = start.clone().require_grad();
    let loss = lpips.forward(x.clone(), target.clone()).unwrap().sum()
        + dssim_loss(x.clone(), target.clone());
    let before = loss.clone().into_scalar::<f32>();
    let grads = loss.backward();
    let g: Tensor<4> = x.grad(&grads).unwrap();
    let values = g.clone().into_data().try_into_vec::<f32>().unwrap();
    assert!(values.iter().all(|v| v.is_finite()));
    assert!(values.iter().any(|v| *v != 0.0));
    // A small step against the gradient lowers the loss.
    let step = start.inner() - g * 0.5;
    let x2 = Tensor::from_inner(step);
    let after = (lpips.forward(x2.clone(), target.clone()).unwrap().sum() + dssim_loss(x2, target))
        .into_scalar::<f32>();
    assert!(after < before, "{after} !< {before}");
}
