#!/usr/bin/env python3
"""Golden SSIM/PSNR values for crates/nets/tests (scikit-image, independent of our code).

"ssim": scikit-image's structural_similarity(a, b, channel_axis=-1, data_range=1) with its
defaults (7x7 uniform window, sample covariance): what Animatable Gaussians' eval/score.py,
hence the paper's tables, report.

"ssim_3dgs": SSIM in the 3DGS convention (11-tap Gaussian window, sigma 1.5, zero padding, mean over the
whole map) equals scikit-image's SSIM on images zero-padded by 5 pixels, with
gaussian_weights=True, use_sample_covariance=False, data_range=1 and channel_axis=-1:
scikit-image then crops exactly the 5-pixel border it pads, and every kept window sees the zeros.

Writes two synthetic image pairs (a gradient with noise, a checkerboard shifted and blurred) as
8-bit PNGs beside the LPIPS examples, then the values for every pair to metrics_golden.json.

Usage: pip install numpy scikit-image pillow; python3 tools/metrics_golden.py crates/nets/tests/data
"""
import json
import sys

import numpy as np
from PIL import Image
from skimage.metrics import peak_signal_noise_ratio, structural_similarity


def load(path):
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0


def save(path, img):
    Image.fromarray(np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)).save(path)


def ssim_3dgs(a, b):
    pad = ((5, 5), (5, 5), (0, 0))
    return structural_similarity(
        np.pad(a, pad), np.pad(b, pad), gaussian_weights=True, sigma=1.5,
        use_sample_covariance=False, data_range=1.0, channel_axis=-1,
    )


def main(folder):
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:48, 0:40] / 48.0
    grad = np.stack([x, y, 0.5 * (x + y)], -1)
    save(f"{folder}/grad_a.png", grad)
    save(f"{folder}/grad_b.png", grad + rng.normal(0, 0.05, grad.shape))
    checker = ((np.mgrid[0:32, 0:56][0] // 4 + np.mgrid[0:32, 0:56][1] // 4) % 2).astype(float)
    checker = np.stack([checker, 1 - checker, 0.3 * np.ones_like(checker)], -1)
    shifted = np.roll(checker, 1, axis=1) * 0.8 + 0.1
    save(f"{folder}/checker_a.png", checker)
    save(f"{folder}/checker_b.png", shifted)
    pairs = [("ex_ref.png", "ex_p0.png"), ("ex_ref.png", "ex_p1.png"),
             ("grad_a.png", "grad_b.png"), ("checker_a.png", "checker_b.png")]
    out = []
    for a, b in pairs:
        ia, ib = load(f"{folder}/{a}"), load(f"{folder}/{b}")
        out.append({"a": a, "b": b,
                    "ssim": structural_similarity(ia, ib, channel_axis=-1, data_range=1.0),
                    "ssim_3dgs": ssim_3dgs(ia, ib),
                    "psnr": peak_signal_noise_ratio(ia, ib, data_range=1.0)})
    with open(f"{folder}/metrics_golden.json", "w") as f:
        json.dump({"generator": "tools/metrics_golden.py (scikit-image)", "pairs": out}, f, indent=1)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main(sys.argv[1])
