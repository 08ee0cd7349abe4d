#!/usr/bin/env python3
"""gsplat's twin of `f3g bench splat --device cuda`: the same kind of scene, timed the same way.

`f3g bench splat` (crates/cli/src/bench/splat.rs) renders N Gaussians on a 1 m sphere shell seen from
3 m (eye (0, 0.3, 3) looking at the origin, +Y up, focal length 1.2 x the image width, principal
point at the centre), scales 1-2 cm, quaternions uniform in [-1, 1]^4 (normalised), opacities
0.3-0.9, SH degree 0 with DC coefficients in [-1.5, 1.5], a white background, and times the
forward and the forward + backward of `(colour * weights).sum()` with random weights in [-1, 1].
This script draws a scene from the same distributions (numpy's generator, so not the same draw:
the Gaussian-tile intersection counts it prints agree to a fraction of a percent for N >= 10k)
and times gsplat 1.5.3's `rasterization` likewise: repetition 0 (gsplat compiles its CUDA on
first use) is not counted, the median of `--repeats` others is; `torch.cuda.synchronize()` ends
every timing.

Needs a CUDA GPU, PyTorch and gsplat 1.5.3 (pure Python: `pip install gsplat==1.5.3`, or the
wheel `tools/gpu-check.sh pack` carries). Run:

    python3 tools/bench_gsplat.py --gaussians 10000,100000,300000 --resolutions 512,1024 \
        --json gsplat.json
"""

import argparse
import json
import math
import time

import numpy as np
import torch
from gsplat import rasterization


def sphere_shell(n, rng):
    v = rng.uniform(-1, 1, (2 * n + 64, 3))
    r2 = (v * v).sum(1)
    v = v[(r2 > 1e-6) & (r2 <= 1)][:n]
    while len(v) < n:  # rejection left too few (tiny n): draw again
        more = rng.uniform(-1, 1, (n, 3))
        r2 = (more * more).sum(1)
        v = np.concatenate([v, more[(r2 > 1e-6) & (r2 <= 1)]])[:n]
    means = v / np.linalg.norm(v, axis=1, keepdims=True)
    scales = rng.uniform(0.01, 0.02, (n, 3))
    quats = rng.uniform(-1, 1, (n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    opacities = rng.uniform(0.3, 0.9, n)
    sh = rng.uniform(-1.5, 1.5, (n, 1, 3))
    return means, scales, quats, opacities, sh


def camera(width, height):
    """World-to-camera matrix (OpenCV: +z forward, +y down) and intrinsics of bench_camera."""
    eye = np.array([0.0, 0.3, 3.0])
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, -np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    view = np.eye(4)
    view[:3, :3] = r
    view[:3, 3] = -r @ eye
    f = 1.2 * width
    k = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    return view, k


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--gaussians", default="10000,100000,300000")
    p.add_argument("--resolutions", default="512,1024", help="N for NxN or WxH, comma-separated")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="write the results here")
    a = p.parse_args()
    dev = torch.device("cuda")
    rng = np.random.default_rng(a.seed)
    cases = []
    for n in (int(s) for s in a.gaussians.split(",")):
        means, scales, quats, opacities, sh = sphere_shell(n, rng)
        for res in a.resolutions.split(","):
            w, h = (int(v) for v in res.split("x")) if "x" in res else (int(res),) * 2
            view, k = camera(w, h)
            t = lambda x: torch.tensor(x, dtype=torch.float32, device=dev)
            params = [t(means), t(quats), t(np.log(scales)), t(np.log(opacities / (1 - opacities))), t(sh)]
            for q in params:
                q.requires_grad_(True)
            weights = t(rng.uniform(-1, 1, (1, h, w, 3)))
            viewmats, ks, bg = t(view)[None], t(k)[None], torch.ones(1, 3, device=dev)

            def render():
                m, q, ls, ol, c = params
                colour, _, meta = rasterization(
                    m, q, ls.exp(), torch.sigmoid(ol), c, viewmats, ks, w, h,
                    sh_degree=0, backgrounds=bg, packed=False)
                return colour, meta

            forward, both = [], []
            for rep in range(a.repeats + 1):
                torch.cuda.synchronize()
                start = time.perf_counter()
                with torch.no_grad():
                    colour, meta = render()
                torch.cuda.synchronize()
                fwd = 1e3 * (time.perf_counter() - start)
                start = time.perf_counter()
                colour, meta = render()
                (colour * weights).sum().backward()
                torch.cuda.synchronize()
                fwd_bwd = 1e3 * (time.perf_counter() - start)
                for q in params:
                    q.grad = None
                if rep > 0:
                    forward.append(fwd)
                    both.append(fwd_bwd)
            case = {
                "gaussians": n,
                "width": w,
                "height": h,
                "intersections": int(meta["flatten_ids"].numel()),
                "forward_ms": sorted(forward)[len(forward) // 2],
                "forward_backward_ms": sorted(both)[len(both) // 2],
            }
            print(json.dumps(case))
            cases.append(case)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"gsplat": __import__("gsplat").__version__, "cases": cases}, f, indent=1)


if __name__ == "__main__":
    main()
