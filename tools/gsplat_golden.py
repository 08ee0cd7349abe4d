"""Golden renders from gsplat 1.5.3, for `crates/splat/tests/gsplat_golden.rs`.

Renders a few small random scenes with gsplat's CUDA rasteriser (the reference the splat crate
claims to match) and writes, per scene, an .npz holding the inputs in the splat crate's layout
(means, log-scales, quaternions (w, x, y, z), opacity logits, SH [N, K, 3], background, the
OpenCV camera) and gsplat's outputs (colour, alpha, depth, radii). The scenes cover SH degrees
0–3, occlusion, the alpha clamp and early stop (opacities up to 0.999), Gaussians crossing the
image border and the tile borders, an off-centre principal point and a near plane that cuts
through the cloud.

Needs a CUDA GPU, PyTorch and gsplat 1.5.3 (`pip install gsplat==1.5.3`; it compiles its CUDA
with the machine's nvcc on first use). Run:

    python3 tools/gsplat_golden.py crates/splat/tests/data/gsplat

gsplat is built with --use_fast_math, so agreement is to about 1e-6, not bit for bit.
"""

import argparse
import math
import os

import numpy as np
import torch
import gsplat
from gsplat import rasterization


def look_at(eye, target, up):
    """World→camera rotation and translation of an OpenCV camera (+z forward, +y down)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, -up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    return r, -r @ eye


def scene(seed, n, degree, max_opacity, width, height, spread=1.0, near=0.01):
    rng = np.random.default_rng(seed)
    eye = [rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 3.0]
    r, t = look_at(eye, [0, 0, 0], [0, 1, 0])
    fov = math.radians(rng.uniform(60, 90))
    f = 0.5 * width / math.tan(0.5 * fov)
    k = np.array(
        [
            [f, 0, width / 2 + rng.uniform(-3, 3)],
            [0, f * rng.uniform(0.9, 1.1), height / 2 + rng.uniform(-3, 3)],
            [0, 0, 1],
        ]
    )
    coeffs = (degree + 1) ** 2
    means = np.stack(
        [
            rng.uniform(-0.5, 0.5, n) * spread,
            rng.uniform(-0.4, 0.4, n) * spread,
            rng.uniform(-0.5, 0.5, n),
        ],
        axis=1,
    )
    log_scales = np.log(rng.uniform(0.02, 0.12, (n, 3)))
    quats = rng.uniform(-1, 1, (n, 4))
    o = rng.uniform(0.15, max_opacity, n)
    sh = rng.uniform(-0.15, 0.15, (n, coeffs, 3))
    sh[:, 0, :] = rng.uniform(0.3, 1.5, (n, 3))
    return {
        "means": means.astype(np.float32),
        "log_scales": log_scales.astype(np.float32),
        "quats": quats.astype(np.float32),
        "opacity_logits": np.log(o / (1 - o)).astype(np.float32),
        "sh": sh.astype(np.float32),
        "background": rng.uniform(0, 1, 3).astype(np.float32),
        "k": k,
        "r": r,
        "t": t,
        "size": np.array([width, height], dtype=np.int64),
        "near": np.array(near),
        "far": np.array(1e4),
    }


def render(s, device):
    def tensor(name):
        return torch.from_numpy(s[name]).to(device)

    width, height = (int(v) for v in s["size"])
    viewmat = np.eye(4)
    viewmat[:3, :3] = s["r"]
    viewmat[:3, 3] = s["t"]
    common = dict(
        means=tensor("means"),
        quats=tensor("quats"),
        scales=torch.exp(tensor("log_scales")),
        opacities=torch.sigmoid(tensor("opacity_logits")),
        colors=tensor("sh"),
        viewmats=torch.from_numpy(viewmat).float()[None].to(device),
        Ks=torch.from_numpy(s["k"]).float()[None].to(device),
        width=width,
        height=height,
        near_plane=float(s["near"]),
        far_plane=float(s["far"]),
        sh_degree=int(math.isqrt(s["sh"].shape[1])) - 1,
        packed=False,
    )
    rgb, alpha, meta = rasterization(
        **common, backgrounds=tensor("background")[None], render_mode="RGB"
    )
    depth, _, _ = rasterization(**common, render_mode="D")
    return {
        "color": rgb[0].cpu().numpy(),
        "alpha": alpha[0, ..., 0].cpu().numpy(),
        "depth": depth[0, ..., 0].cpu().numpy(),
        "radii": meta["radii"][0].cpu().numpy().astype(np.int32),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", help="directory for scene_*.npz")
    args = parser.parse_args()
    assert gsplat.__version__ == "1.5.3", f"gsplat {gsplat.__version__}, expected 1.5.3"
    os.makedirs(args.out, exist_ok=True)
    scenes = [
        scene(1, 150, 0, 0.95, 80, 60),
        scene(2, 200, 1, 0.999, 97, 70),
        scene(3, 300, 3, 0.999, 128, 96, spread=3.0),
        scene(4, 120, 2, 0.9, 61, 45, near=2.9),
    ]
    for i, s in enumerate(scenes):
        out = render(s, "cuda")
        path = os.path.join(args.out, f"scene_{i}.npz")
        np.savez(path, **s, **out)
        visible = int((out["radii"] > 0).any(axis=1).sum())
        print(f"{path}: {s['means'].shape[0]} Gaussians, {visible} visible, "
              f"alpha mean {out['alpha'].mean():.3f}")
    print(f"gsplat {gsplat.__version__}, torch {torch.__version__}")


if __name__ == "__main__":
    main()
