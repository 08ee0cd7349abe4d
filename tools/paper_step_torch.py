#!/usr/bin/env python3
"""PyTorch twin of one `paper` joint training step of f3g (`f3g bench train --preset paper`).

What it is for
--------------
`f3g bench train --preset paper --device cuda` (crates/cli/src/train_bench.rs) times f3g's
whole joint-stage training step with Burn, phase by phase. This script does the same work in
PyTorch on the same GPU -- the same six networks (the DualStyleUNets of
tools/bench_nets_torch.py, imported, not copied), the same numbers of Gaussians, renders of
the same sizes with gsplat 1.5.3's `rasterization`, LPIPS VGG, the adversarial loss and the
discriminator's own step, Adam -- so that f3g's step ÷ this step says how far f3g is from
what PyTorch makes of the same step (issue #47, item 4). Weights and images are random (they
do not change the work); shapes, pass counts and the order of the work follow f3g's step.

f3g's `paper` joint step, phase by phase, and its twin here
-----------------------------------------------------------
(crates/avatar/src/train/{parallel.rs,step.rs,losses.rs}, model.rs, inputs.rs, posing.rs; the
phase names are f3g's, `train/profile.rs`, and this script reports the same ones.)

| phase | f3g (`paper` preset) | twin |
|---|---|---|
| data | wait for the loader's worker (decode, crops, joint transforms, upload) | upload of the sample made on the host: body image and band 1536×2048, head crop and band 512², background, 2×163 joint transforms, 14 282 vertex displacements |
| inputs | per Gaussian (401 334 body + 94 032 face): displacement by barycentric taps, densified into the face, LBS blend of 163 joints (≤ 8 taps), nearest rotation (8 Newton polar iterations), quaternion (Shepperd); posed maps reduced to the nets' inputs [1,6,512²] and [1,6,256²], `n·v` view maps [1,1,512²]×2 and [1,1,256²]×2 | the same operations as tensors, no grad: 3-tap barycentric displacement from 14 282 vertices, 4-tap densification, 8-tap blend of 163 random joint transforms, the same 8 polar iterations and Shepperd, posed positions averaged into the input maps with `index_add` (the masked box filter), view maps the same way |
| networks | body: three DualStyleUNets 512→1024 (`three` layout: position 3 ch, colour 3 ch view-conditioned, other 8 ch; 6 input channels), each read at the body texels (`gather`); face: position net on the head map, `P̂ = P + 0.05·𝒫(P)`, colour (view) and aux nets on `P̂` (256→256), resampled to the head map and read at the face texels; fusion into 495 366 canonical Gaussians | the same six networks (bench_nets_torch.DualStyleUNet, `in_channels` 6), `index_select` at the same numbers of texels, the same heads (offset ×0.05, colour +0.5, opacity and scale offsets, face scale cap), `torch.cat` fusion |
| render | pose (means by the blended transform, quats by its rotation) and splat 1536×2048 (body view), then the head crop 512² with its own intrinsics; the boundary band replaced by the background | the same LBS of the means and quaternions, gsplat `rasterization` (SH degree 0, `packed=False`, classic) at 1536×2048 and 512², the band blend |
| lpips | L1 on the full render; LPIPS VGG on the mask box padded to a square, resized to 512²; LPIPS VGG on the 512² head crop | the same: L1, square crop by slicing + background padding, bilinear resize to 512², bench_nets_torch.Lpips(VGG) twice (each: features of render and ground truth) |
| adversarial | the discriminator (StyleGAN2, `paper(512)`: cm 2, 512 channels max), frozen, on the head render: non-saturating generator loss | the same discriminator class (bench_nets_torch.Discriminator, paper config) with `requires_grad` off for its weights during the generator's pass |
| readback | every loss term read back together (one `[terms]` tensor) | `torch.stack(terms).cpu()` |
| backward | one backward of the summed terms through LPIPS, the discriminator, both renders, skinning and the six networks | one `total.backward()` |
| optimiser | fused one-pass Adam of the body and of the face networks (β 0.9/0.999, ε 1e-8) | `torch.optim.Adam` (PyTorch's default implementation: `foreach` on CUDA; `--adam fused` for the fused kernel), body and face separately |
| discriminator | D(real), D(fake) on the detached head render and the real crop, softplus losses; every 16th discriminator step the lazy R1 estimate (two more D passes on real ± 0.01·u); loss read back; backward; Adam (β 0/0.99, ε 1e-5) | the same, with R1 on the same discriminator steps (counted from the first warm-up step, as f3g's `disc_steps`): R1 falls in the timed steps only when warm-up + steps > 16 |

What the twin simplifies, and why the timing does not move materially
----------------------------------------------------------------------
- *Geometry.* f3g's Gaussians sit on the texels of the template's two-sided 1024² position map
  of a synthetic human. Here the same number of texels is drawn at random inside a crude human
  silhouette (torso, legs, arms, head) on a 1024² front/back map, and its canonical positions
  are the map's coordinates on two slabs 1.7 m tall, ±0.1 m apart; the head's 94 032 face
  Gaussians are on an ellipsoid. The camera is the synthetic capture's (1536×2048, 3 m away,
  focal 0.5·2048·3/0.98 px), so the figure fills the image height as f3g's does, and the head
  crop's intrinsics put a 0.33 m box on 512 px (`face_padding` 1.3 of a 0.25 m head).
  The networks, LPIPS and the discriminator do not depend on the values; the render depends
  on the screen footprint and depth complexity, which are of the same order (isotropic
  Gaussians at the texel spacing, initial opacity 0.1, two layers), and is a small part of
  f3g's step (25-40 ms of 2.7-3.2 s on H100/H200).
- *Skinning* is a fixed random LBS: 163 joints, 8 taps per Gaussian (f3g pads its taps to the
  widest row, up to 8), random near-identity joint transforms, random weights; the operations
  per Gaussian (blend, 8 polar iterations, Shepperd, point and quaternion transforms) are
  f3g's, so the `inputs` and the posing's cost in `render` are the same kind of work.
- *Inputs* are averaged into the maps with `index_add` over one texel list instead of f3g's
  general tap tables (which also up-sample); the same amount of data moves.
- *The sample* is one fixed random view reused every step (f3g cycles the training views of a
  4-frame synthetic capture); the work per step does not depend on which view it is.
- *The pose PCA* is not applied (f3g applies it only at inference), nor the learnable
  canonical tables (`learn_canonical` is false in `paper`).

How to run it
-------------
On the GPU machine (PyTorch with CUDA, gsplat 1.5.3 whose CUDA extension is built):

    python3 tools/paper_step_torch.py --device cuda --steps 5 --warmup 1 --json step-torch.json
    f3g bench train --preset paper --device cuda --steps 5 --warmup 1 --json train-paper.json

(`tools/gpu-check.sh run` runs both and prints the ratio.) On a CPU, for a smoke test only:

    python3 tools/paper_step_torch.py --device cpu --small --steps 1 --warmup 0

gsplat's CUDA rasteriser does not run on a CPU, and its pure-PyTorch reference
(`gsplat.cuda._torch_impl._rasterize_to_pixels`) still calls a CUDA kernel
(`rasterize_to_indices_in_range`) and nerfacc; on `--device cpu` the twin projects with
gsplat's pure-PyTorch reference (`_quat_scale_to_covar_preci`, `_fully_fused_projection`,
loaded from the installed gsplat's file without importing the package) and composites with a
small dense front-to-back stand-in (every Gaussian against every pixel, depth-sorted; alpha
clamped at 0.99 and cut below 1/255 as gsplat does). It is only for `--small` smoke runs.

Protocol (as `bench_nets_torch.py` and `f3g bench train`): the networks, optimisers and the
sample are built once; `--warmup` steps are run and discarded (cuDNN autotuning:
`cudnn.benchmark = True`), then `--steps` steps are timed, each from a `torch.cuda.synchronize`
to one after it; the median step is reported as `step_ms` (the upper median, `v[len // 2]`),
with the mean as `step_ms_mean` (f3g's `step_ms` is the mean of its timed steps: that is the
one `tools/gpu-check.sh` divides by).
Phases are timed with CUDA events recorded at f3g's phase marks (no host synchronisation inside
the step besides the two readbacks f3g also has); `--sync-phases` synchronises at every mark
instead, exactly as f3g's timer does (its `step_ms` includes those synchronisations). Phase
times are means per timed step, as f3g reports them. `--json` writes the numbers, with the
phases in f3g's format (`{"phases": [["data", ms], ...]}`).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import sys
import time

import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_nets_torch import (  # noqa: E402
    VGG,
    Discriminator,
    DualStyleUNet,
    Lpips,
    expected_styleunet_params,
    styleunet_config,
)

PHASES = ["data", "inputs", "networks", "render", "lpips", "adversarial", "readback",
          "backward", "optimiser", "discriminator"]

OFFSET_SCALE = 0.05
FACE_MAX_SCALE = 0.15
SH_C0 = 0.28209479177387814
JOINTS = 163          # the built-in human's skeleton
SKIN_TAPS = 8         # f3g pads skinning taps to the widest row (up to 8 joints)
VERTICES = 14_282     # the built-in human's template vertices
POLAR_ITERATIONS = 8  # posing.rs

# The `paper` preset (crates/avatar/src/config.rs, TrainConfig::paper) and what
# `f3g bench train --preset paper` measures on its synthetic 1536×2048 capture.
PAPER = dict(
    name="paper",
    map_resolution=1024, body_gaussians=401_334, face_gaussians=94_032,
    head_map=256,  # side of the head map the face outputs are read at (≈ 2 · 1.1 · head box)
    width=1536, height=2048, face_crop=512, lpips_size=512,
    body_net=styleunet_config("paper_body", 3, False),
    face_net=styleunet_config("paper_face", 3, False),
    disc=dict(resolution=512, channel_multiplier=2, channel_base=16384, max_channels=512,
              stddev_group=4),
)
# `--small`: the cpu preset's network sizes and a tiny scene (CPU smoke test only).
SMALL = dict(
    name="small",
    map_resolution=128, body_gaussians=3_000, face_gaussians=600, head_map=32,
    width=48, height=64, face_crop=32, lpips_size=32,
    body_net=styleunet_config("cpu_body", 3, False),
    face_net=styleunet_config("cpu_face", 3, False),
    disc=dict(resolution=32, channel_multiplier=1, channel_base=1024, max_channels=64,
              stddev_group=4),
)
LOSS = dict(l1=1.0, lpips=0.1, offset=5e-3, face_l1=1.0, face_lpips=0.1, adversarial=5e-3,
            r1_gamma=10.0, r1_interval=16)
LR, LR_DISC, ADAM_EPS = 5e-4, 2e-3, 1e-8
INITIAL_OPACITY = 0.1
VIEW_NOISE = 0.1


def logit(p):
    return math.log(p / (1 - p))


def median(v):
    v = sorted(v)
    return v[len(v) // 2]


# --------------------------------------------------------------------------------------------
# The scene: a crude figure on a two-sided map, a head ellipsoid, the capture's camera


def body_mask(r: int) -> torch.Tensor:
    """[r, r] silhouette on a map spanning x in [-0.45, 0.45] m, y in [0.85, -0.85] m."""
    ys = 0.85 - (torch.arange(r) + 0.5) / r * 1.7
    xs = (torch.arange(r) + 0.5) / r * 0.9 - 0.45
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    torso = (x.abs() < 0.18) & (y > -0.05) & (y < 0.6)
    legs = ((x - 0.09).abs() < 0.08) | ((x + 0.09).abs() < 0.08)
    legs = legs & (y <= -0.05) & (y > -0.85)
    arms = (x.abs() >= 0.18) & (x.abs() < 0.26) & (y > -0.05) & (y < 0.58)
    neck = (x.abs() < 0.05) & (y >= 0.6) & (y < 0.64)
    head = ((x / 0.09) ** 2 + ((y - 0.72) / 0.11) ** 2) < 1
    return torso | legs | arms | neck | head


def pick(mask: torch.Tensor, n: int, g: torch.Generator) -> torch.Tensor:
    """n distinct texel indices of a [r, 2r] front/back map where `mask` ([r, r]) holds."""
    r = mask.shape[0]
    both = torch.cat([mask, mask], 1).reshape(-1).nonzero().reshape(-1)
    if both.numel() < n:
        raise SystemExit(f"the silhouette has {both.numel()} texels, {n} are needed")
    return both[torch.randperm(both.numel(), generator=g)[:n]].sort().values


def texel_coords(pixels: torch.Tensor, r: int):
    """(row, column within the side, side 0 front / 1 back) of texels of a [r, 2r] map."""
    row, col = pixels // (2 * r), pixels % (2 * r)
    return row, col % r, col // r


def look_at(eye, target):
    """World-to-camera (OpenCV: +z forward, +y down), [4, 4]."""
    eye, target = torch.tensor(eye), torch.tensor(target)
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, torch.tensor([0.0, -1.0, 0.0]))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    rot = torch.stack([x, y, z])
    view = torch.eye(4)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye
    return view


def project(view, k, points):
    pc = points @ view[:3, :3].T + view[:3, 3]
    uv = pc[:, :2] / pc[:, 2:3] * torch.stack([k[0, 0], k[1, 1]]) + torch.stack([k[0, 2], k[1, 2]])
    return uv


class Scene:
    """Constant tables (f3g's `Constants` and `GaussianTables`) and one sample, on the host."""

    def __init__(self, s: dict, seed: int):
        g = torch.Generator().manual_seed(seed)
        r, hs = s["map_resolution"], s["head_map"]
        nb, nf = s["body_gaussians"], s["face_gaussians"]
        self.s = s
        # Body texels and canonical positions (two slabs 0.2 m apart).
        self.body_pixels = pick(body_mask(r), nb, g)
        row, col, side = texel_coords(self.body_pixels, r)
        x = (col.float() + 0.5) / r * 0.9 - 0.45
        y = 0.85 - (row.float() + 0.5) / r * 1.7
        z = torch.where(side == 0, 0.1, -0.1) + 0.01 * torch.randn(nb, generator=g)
        self.body_positions = torch.stack([x, y, z], 1)
        self.body_normals = torch.stack([torch.zeros(nb), torch.zeros(nb),
                                         torch.where(side == 0, 1.0, -1.0)], 1)
        spacing = 1.7 / r / math.sqrt(nb / (2 * body_mask(r).sum().item()))
        self.body_log_scales = torch.full((nb, 3), math.log(spacing))
        self.body_quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(nb, 1)
        # Face texels on the head map's ellipse; canonical face model on an ellipsoid.
        ys = (torch.arange(hs) + 0.5) / hs * 2 - 1
        yy, xx = torch.meshgrid(ys, ys, indexing="ij")
        self.face_pixels = pick(xx ** 2 + yy ** 2 < 1, nf, g)
        row, col, side = texel_coords(self.face_pixels, hs)
        u = (col.float() + 0.5) / hs * 2 - 1
        v = (row.float() + 0.5) / hs * 2 - 1
        depth = torch.sqrt((1 - u ** 2 - v ** 2).clamp_min(0))
        sign = torch.where(side == 0, 1.0, -1.0)
        self.face_positions = torch.stack([0.08 * u, 0.72 - 0.11 * v, 0.09 * sign * depth], 1)
        normal = torch.stack([u, -v, sign * depth], 1)
        self.face_normals = normal / normal.norm(dim=1, keepdim=True).clamp_min(1e-6)
        self.face_colours = torch.full((nf, 3), 0.5)
        self.face_opacity = torch.full((nf,), logit(INITIAL_OPACITY))
        self.face_log_scales = torch.full((nf, 3), math.log(0.22 / hs))
        self.face_quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(nf, 1)
        # Barycentric taps into the template's vertices, densification taps (4 body Gaussians
        # per face Gaussian), skinning taps (tap-major [K, N]).
        self.bary_index = torch.randint(0, VERTICES, (3, nb), generator=g)
        bary = torch.rand(3, nb, generator=g)
        self.bary_weight = bary / bary.sum(0, keepdim=True)
        self.dense_index = torch.randint(0, nb, (4, nf), generator=g)
        self.dense_weight = torch.full((4, nf), 0.25)
        n = nb + nf
        self.skin_index = torch.randint(0, JOINTS, (SKIN_TAPS, n), generator=g)
        w = torch.rand(SKIN_TAPS, n, generator=g) ** 4
        self.skin_weight = w / w.sum(0, keepdim=True)
        # Network input pixels of every Gaussian (the masked box filter's one tap here).
        bi = s["body_net"]["input_size"]
        row, col, side = texel_coords(self.body_pixels, r)
        self.body_input_pixel = side * bi * bi + (row * bi // r) * bi + col * bi // r
        fi = s["face_net"]["input_size"]
        row, col, side = texel_coords(self.face_pixels, hs)
        self.face_input_pixel = side * fi * fi + (row * fi // hs) * fi + col * fi // hs
        # The capture's camera (synth.rs ring_cameras: 3 m, the figure fills the height) and
        # the head crop's intrinsics (0.33 m box on `face_crop` pixels).
        w_, h_ = s["width"], s["height"]
        eye, target = [0.0, 0.02, 3.0], [0.0, 0.02, 0.0]
        self.view = look_at(eye, target)
        f = 0.5 * h_ * 3.0 / 0.98
        self.k_body = torch.tensor([[f, 0, w_ / 2], [0, f, h_ / 2], [0, 0, 1.0]])
        fc = s["face_crop"]
        ff = fc * 3.0 / 0.33
        head = project(self.view, torch.tensor([[ff, 0, 0], [0, ff, 0], [0, 0, 1.0]]),
                       torch.tensor([[0.0, 0.72, 0.0]]))[0]
        self.k_face = torch.tensor([[ff, 0, fc / 2 - head[0]], [0, ff, fc / 2 - head[1]],
                                    [0, 0, 1.0]])
        self.centre = torch.tensor(eye).reshape(1, 3)
        # The LPIPS square: the figure's box, padded to a square with the background.
        uv = project(self.view, self.k_body, self.body_positions)
        x0, y0 = uv.min(0).values.floor().clamp_min(0).long().tolist()
        x1 = min(int(uv[:, 0].max().ceil()), w_)
        y1 = min(int(uv[:, 1].max().ceil()), h_)
        side_ = max(x1 - x0, y1 - y0)
        self.square = (x0, y0, x1, y1, side_, (side_ - (x1 - x0)) // 2, (side_ - (y1 - y0)) // 2)
        # The sample (made on the host, uploaded in the `data` phase).
        self.sample = dict(
            body_image=torch.rand(1, 3, h_, w_, generator=g),
            body_band=(torch.rand(1, 1, h_, w_, generator=g) < 0.01).float(),
            face_image=torch.rand(1, 3, fc, fc, generator=g),
            face_band=(torch.rand(1, 1, fc, fc, generator=g) < 0.01).float(),
            background=torch.rand(3, generator=g),
            joints=random_joints(g, 0.1),
            input_joints=random_joints(g, 0.1),
            displacement=0.005 * torch.randn(VERTICES, 3, generator=g),
            noise=VIEW_NOISE * torch.randn(n, 3, generator=g),
        )

    def to(self, device):
        for k, v in list(vars(self).items()):
            if isinstance(v, torch.Tensor):
                setattr(self, k, v.to(device))
        return self


def random_joints(g, angle):
    """[J, 3, 4] near-identity rigid transforms."""
    axis = torch.randn(JOINTS, 3, generator=g)
    axis = axis / axis.norm(dim=1, keepdim=True)
    theta = angle * torch.rand(JOINTS, 1, generator=g)
    kx = torch.zeros(JOINTS, 3, 3)
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    kx = kx - kx.transpose(1, 2)
    rot = (torch.eye(3) + torch.sin(theta)[..., None] * kx
           + (1 - torch.cos(theta))[..., None] * kx @ kx)
    t = 0.02 * torch.randn(JOINTS, 3, 1, generator=g)
    return torch.cat([rot, t], 2)


# --------------------------------------------------------------------------------------------
# posing.rs: blend, nearest rotation, quaternions


def blend(joints, index, weight):
    """[N, 3, 4] blended transforms: Σ_k w[k] · joints[index[k]] (taps tap-major)."""
    picked = joints.reshape(JOINTS, 12)[index.reshape(-1)].reshape(*index.shape, 12)
    return (picked * weight[..., None]).sum(0).reshape(-1, 3, 4)


def nearest_rotation(a):
    """Newton's polar iteration with determinant scaling, POLAR_ITERATIONS times."""
    x = a
    for _ in range(POLAR_ITERATIONS):
        m = lambda i, j: x[:, i, j]  # noqa: E731
        c = torch.stack([
            m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1), m(1, 2) * m(2, 0) - m(1, 0) * m(2, 2),
            m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0), m(2, 1) * m(0, 2) - m(0, 1) * m(2, 2),
            m(2, 2) * m(0, 0) - m(2, 0) * m(0, 2), m(2, 0) * m(0, 1) - m(2, 1) * m(0, 0),
            m(0, 1) * m(1, 2) - m(0, 2) * m(1, 1), m(0, 2) * m(1, 0) - m(0, 0) * m(1, 2),
            m(0, 0) * m(1, 1) - m(0, 1) * m(1, 0)], 1).reshape(-1, 3, 3)
        det = (x[:, 0] * c[:, 0]).sum(1)
        det = torch.where(det.abs() < 1e-20, torch.full_like(det, 1e-20), det)
        gamma = det.abs().pow(-1.0 / 3.0)
        x = x * (0.5 * gamma)[:, None, None] + c * (0.5 / (gamma * det))[:, None, None]
    return x


def quaternions(r):
    """Shepperd's method: (w, x, y, z) of rotations [N, 3, 3]."""
    e = lambda i, j: r[:, i, j]  # noqa: E731
    s01, s02, s12 = e(0, 1) + e(1, 0), e(0, 2) + e(2, 0), e(1, 2) + e(2, 1)
    d10, d02, d21 = e(1, 0) - e(0, 1), e(0, 2) - e(2, 0), e(2, 1) - e(1, 2)
    t = torch.stack([1 + e(0, 0) + e(1, 1) + e(2, 2), 1 + e(0, 0) - e(1, 1) - e(2, 2),
                     1 - e(0, 0) + e(1, 1) - e(2, 2), 1 - e(0, 0) - e(1, 1) + e(2, 2)], 1)
    cands = torch.stack([
        torch.stack([t[:, 0], d21, d02, d10], 1), torch.stack([d21, t[:, 1], s01, s02], 1),
        torch.stack([d02, s01, t[:, 2], s12], 1), torch.stack([d10, s02, s12, t[:, 3]], 1)], 1)
    best = t.argmax(1)
    q = cands.gather(1, best.reshape(-1, 1, 1).expand(-1, 1, 4)).reshape(-1, 4)
    return q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)


def quat_mul(a, b):
    aw, ax, ay, az = a.unbind(1)
    bw, bx, by, bz = b.unbind(1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], 1)


def transform(linear, translation, x):
    return (linear @ x[..., None]).squeeze(-1) + translation


def reduce_to_map(values, pixel, size):
    """Mean of the Gaussians' values per input pixel: [1, 2·C, size, size] (front ‖ back)."""
    c = values.shape[1]
    sums = torch.zeros(2 * size * size, c, device=values.device).index_add_(0, pixel, values)
    counts = torch.zeros(2 * size * size, 1, device=values.device).index_add_(
        0, pixel, torch.ones_like(values[:, :1]))
    maps = (sums / counts.clamp_min(1)).reshape(2, size, size, c).permute(0, 3, 1, 2)
    return maps.reshape(1, 2 * c, size, size)


@torch.no_grad()
def net_inputs(scene: Scene, sample: dict):
    """inputs.rs `GaussianTables::inputs`: maps, view maps, displacement, skinning."""
    nb = scene.body_positions.shape[0]
    vd = sample["displacement"]
    body_disp = (vd[scene.bary_index] * scene.bary_weight[..., None]).sum(0)
    face_disp = (body_disp[scene.dense_index] * scene.dense_weight[..., None]).sum(0)
    blended = blend(sample["joints"], scene.skin_index, scene.skin_weight)
    linear, translation = blended[:, :, :3], blended[:, :, 3]
    rotation = nearest_rotation(linear)
    quat = quaternions(rotation)
    # The networks' inputs: the template posed by the input pose (no root motion).
    inp = blend(sample["input_joints"], scene.skin_index, scene.skin_weight)
    canonical = torch.cat([scene.body_positions + body_disp,
                           scene.face_positions + face_disp], 0)
    posed_input = transform(inp[:, :, :3], inp[:, :, 3], canonical)
    # n · v of every Gaussian for the view maps (noisy view directions, as in training).
    posed = transform(linear, translation, canonical)
    normals = (rotation @ torch.cat([scene.body_normals, scene.face_normals], 0)[..., None])
    v = scene.centre - posed + sample["noise"]
    v = v / v.norm(dim=1, keepdim=True).clamp_min(1e-12)
    ndotv = (normals.squeeze(-1) * v).sum(1, keepdim=True)
    bi, fi = scene.s["body_net"]["input_size"], scene.s["face_net"]["input_size"]
    bview = reduce_to_map(ndotv[:nb], scene.body_input_pixel, bi)
    fview = reduce_to_map(ndotv[nb:], scene.face_input_pixel, fi)
    return dict(
        body_map=reduce_to_map(posed_input[:nb], scene.body_input_pixel, bi),
        body_view=(bview[:, :1], bview[:, 1:]),
        face_map=reduce_to_map(posed_input[nb:], scene.face_input_pixel, fi),
        face_view=(fview[:, :1], fview[:, 1:]),
        displacement=torch.cat([body_disp, face_disp], 0),
        linear=linear, translation=translation, quat=quat,
    )


# --------------------------------------------------------------------------------------------
# model.rs: networks, fusion


def read_at(front, back, pixels, size):
    """model.rs `gather`: [1, C, R, R] front and back, read at texels of [R, 2R]: [N, C]."""
    if front.shape[2] != size:
        front = F.interpolate(front, size=(size, size), mode="bilinear", align_corners=False)
        back = F.interpolate(back, size=(size, size), mode="bilinear", align_corners=False)
    c = front.shape[1]
    both = torch.cat([front, back], 3).reshape(c, -1)
    return both.index_select(1, pixels).t()


def canonical(nets, scene: Scene, inp: dict):
    body_pos, body_col, body_oth, face_pos, face_col, face_aux = nets
    r, hs = scene.s["map_resolution"], scene.s["head_map"]
    bp = scene.body_pixels
    raw = torch.cat([read_at(*body_pos(inp["body_map"], None), bp, r),
                     read_at(*body_col(inp["body_map"], inp["body_view"]), bp, r),
                     read_at(*body_oth(inp["body_map"], None), bp, r)], 1)
    nb = raw.shape[0]
    body_offsets = raw[:, 0:3] * OFFSET_SCALE
    means = scene.body_positions + body_offsets + inp["displacement"][:nb]
    colours = raw[:, 3:6] + 0.5
    opacity = raw[:, 6] + logit(INITIAL_OPACITY)
    log_scales = scene.body_log_scales + raw[:, 7:10]
    quats = raw[:, 10:14] + scene.body_quats
    # Face branch (paper §3.4).
    fmap = inp["face_map"]
    p = face_pos(fmap, None)
    p_hat = fmap + torch.cat(p, 1) * OFFSET_SCALE
    c = face_col(p_hat, inp["face_view"])
    a = face_aux(p_hat, None)
    fp = scene.face_pixels
    r_ = torch.cat([read_at(*p, fp, hs), read_at(*c, fp, hs), read_at(*a, fp, hs)], 1)
    face_offsets = r_[:, 0:3] * OFFSET_SCALE
    f_means = scene.face_positions + face_offsets + inp["displacement"][nb:]
    f_log_scales = (scene.face_log_scales + r_[:, 7:10]).clamp_max(math.log(FACE_MAX_SCALE))
    return dict(
        means=torch.cat([means, f_means], 0),
        colours=torch.cat([colours, scene.face_colours + r_[:, 3:6]], 0),
        opacity=torch.cat([opacity, scene.face_opacity + r_[:, 6]], 0),
        log_scales=torch.cat([log_scales, f_log_scales], 0),
        quats=torch.cat([quats, scene.face_quats + r_[:, 10:14]], 0),
        body_offsets=body_offsets, face_offsets=face_offsets,
    )


# --------------------------------------------------------------------------------------------
# Rendering: gsplat on CUDA, gsplat's PyTorch projection + a dense compositor on the CPU


_TORCH_IMPL = None


def torch_impl():
    """gsplat's pure-PyTorch reference, loaded from its file (no package import: gsplat's
    `__init__` pulls in its CUDA wrappers and optional dependencies)."""
    global _TORCH_IMPL
    if _TORCH_IMPL is None:
        spec = importlib.util.find_spec("gsplat")
        if spec is None or not spec.submodule_search_locations:
            raise SystemExit("gsplat is not installed (pip install --no-deps gsplat==1.5.3): "
                             "the CPU stand-in uses its PyTorch projection")
        path = os.path.join(list(spec.submodule_search_locations)[0], "cuda", "_torch_impl.py")
        mod_spec = importlib.util.spec_from_file_location("gsplat_torch_impl", path)
        module = importlib.util.module_from_spec(mod_spec)
        mod_spec.loader.exec_module(module)
        _TORCH_IMPL = module
    return _TORCH_IMPL


def render_cpu(means, quats, scales, opacities, colours, view, k, width, height, background):
    """Dense front-to-back compositing of every Gaussian at every pixel (CPU smoke only)."""
    ti = torch_impl()
    covars, _ = ti._quat_scale_to_covar_preci(quats, scales, True, False, triu=False)
    radii, means2d, depths, conics, _ = ti._fully_fused_projection(
        means, covars, view[None], k[None], width, height)
    radii, means2d, depths, conics = radii[0], means2d[0], depths[0], conics[0]
    valid = (radii > 0).all(-1)
    order = torch.argsort(depths.detach())
    ys, xs = torch.meshgrid(torch.arange(height, dtype=means.dtype) + 0.5,
                            torch.arange(width, dtype=means.dtype) + 0.5, indexing="ij")
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)  # [P, 2]
    m2, cn = means2d[order], conics[order]
    d = pix[None] - m2[:, None]  # [N, P, 2]
    sigma = (0.5 * (cn[:, None, 0] * d[..., 0] ** 2 + cn[:, None, 2] * d[..., 1] ** 2)
             + cn[:, None, 1] * d[..., 0] * d[..., 1])
    alpha = (opacities[order, None] * torch.exp(-sigma)).clamp_max(0.99)
    alpha = alpha * ((alpha >= 1 / 255) & (sigma >= 0) & valid[order, None])
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:1]), 1 - alpha[:-1]], 0), 0)
    w = trans * alpha  # [N, P]
    rgb = w.t() @ colours[order] + (trans[-1] * (1 - alpha[-1]))[:, None] * background
    return rgb.reshape(height, width, 3), int(valid.sum())


def render(g, inp, view, k, width, height, background, band, cpu):
    """model.rs `render_posed` + losses.rs `render_view`: [1, 3, H, W]."""
    means = transform(inp["linear"], inp["translation"], g["means"])
    quats = quat_mul(inp["quat"], g["quats"])
    scales = g["log_scales"].exp()
    opac = torch.sigmoid(g["opacity"])
    if cpu:
        sh = (g["colours"] - 0.5) / SH_C0
        colours = (sh * SH_C0 + 0.5).clamp_min(0)  # what gsplat's SH degree 0 gives
        qn = quats / quats.norm(dim=1, keepdim=True)
        img, hits = render_cpu(means, qn, scales, opac, colours, view, k, width, height,
                               background)
    else:
        from gsplat import rasterization
        img, _, meta = rasterization(
            means, quats, scales, opac, ((g["colours"] - 0.5) / SH_C0)[:, None, :],
            view[None], k[None], width, height, sh_degree=0, backgrounds=background[None],
            packed=False)
        img, hits = img[0], meta["flatten_ids"].numel()
    pred = img.permute(2, 0, 1)[None]
    return pred * (1 - band) + background.reshape(1, 3, 1, 1) * band, hits


def square_crop(t, square, background, size):
    """losses.rs `square_crop` then `resize` to the LPIPS size."""
    x0, y0, x1, y1, side, left, top = square
    region = t[:, :, y0:y1, x0:x1]
    h, w = y1 - y0, x1 - x0
    fill = lambda hh, ww: background.reshape(1, 3, 1, 1).expand(1, 3, hh, ww)  # noqa: E731
    row = [region]
    if left > 0:
        row.insert(0, fill(h, left))
    if side - w - left > 0:
        row.append(fill(h, side - w - left))
    col = [torch.cat(row, 3)]
    if top > 0:
        col.insert(0, fill(top, side))
    if side - h - top > 0:
        col.append(fill(side - h - top, side))
    sq = torch.cat(col, 2)
    return F.interpolate(sq, size=(size, size), mode="bilinear", align_corners=False)


def offset_norm(o):
    return (o.pow(2).sum(1) + 1e-12).sqrt().mean()


# --------------------------------------------------------------------------------------------
# The step


class Timer:
    """Marks at f3g's phase boundaries: CUDA events, or a synchronisation and the wall clock."""

    def __init__(self, device, sync_phases):
        self.cuda = device.type == "cuda"
        self.events = self.cuda and not sync_phases
        self.device = device
        self.totals = {p: 0.0 for p in PHASES}

    def sync(self):
        if self.cuda:
            torch.cuda.synchronize(self.device)

    def start(self):
        self.sync()
        self.marks = []
        self.t0 = time.perf_counter()
        if self.events:
            e = torch.cuda.Event(enable_timing=True)
            e.record()
            self.first = e
        else:
            self.last = self.t0

    def mark(self, phase):
        if self.events:
            e = torch.cuda.Event(enable_timing=True)
            e.record()
            self.marks.append((phase, e))
        else:
            self.sync()
            now = time.perf_counter()
            self.marks.append((phase, (now - self.last) * 1e3))
            self.last = now

    def finish(self, keep):
        self.sync()
        wall = (time.perf_counter() - self.t0) * 1e3
        if keep:
            prev = self.first if self.events else None
            for phase, m in self.marks:
                if self.events:
                    self.totals[phase] += prev.elapsed_time(m)
                    prev = m
                else:
                    self.totals[phase] += m
        return wall


class Twin:
    def __init__(self, s, device, adam, seed):
        self.s, self.device = s, device
        torch.manual_seed(seed)
        self.scene = Scene(s, seed).to(device)
        self.host_sample = self.scene.sample  # pageable host memory, copied every step
        body = lambda out, view: {**s["body_net"], "in_channels": 6,  # noqa: E731
                                  "out_channels": out, "view_conditioned": view}
        face = lambda out, view: {**s["face_net"], "in_channels": 6,  # noqa: E731
                                  "out_channels": out, "view_conditioned": view}
        self.configs = [body(3, False), body(3, True), body(8, False),
                        face(3, False), face(3, True), face(8, False)]
        with torch.device(device):
            self.nets = [DualStyleUNet(c) for c in self.configs]
            self.lpips = Lpips(VGG)
            self.disc = Discriminator(s["disc"])
        trainable = lambda ms: [p for m in ms for p in m.parameters() if p.requires_grad]  # noqa
        kw = {}
        if adam == "fused":
            kw["fused"] = True
        elif adam == "foreach":
            kw["foreach"] = True
        self.opt_body = torch.optim.Adam(trainable(self.nets[:3]), lr=LR, betas=(0.9, 0.999),
                                         eps=ADAM_EPS, **kw)
        self.opt_face = torch.optim.Adam(trainable(self.nets[3:]), lr=LR, betas=(0.9, 0.999),
                                         eps=ADAM_EPS, **kw)
        self.opt_disc = torch.optim.Adam(trainable([self.disc]), lr=LR_DISC, betas=(0.0, 0.99),
                                         eps=1e-5, **kw)
        self.disc_steps = 0
        self.hits = (0, 0)
        self.r1_steps = []

    def params(self):
        return [sum(p.numel() for p in n.parameters()) for n in self.nets]

    def step(self, t: Timer, index: int):
        s, scene, dev = self.s, self.scene, self.device
        cpu = dev.type == "cpu"
        sample = {k: v.to(dev, non_blocking=False) for k, v in self.host_sample.items()}
        bg = sample["background"]
        t.mark("data")
        inp = net_inputs(scene, sample)
        t.mark("inputs")
        g = canonical(self.nets, scene, inp)
        t.mark("networks")
        terms = []
        # losses.rs `body`
        pred, hb = render(g, inp, scene.view, scene.k_body, s["width"], s["height"], bg,
                          sample["body_band"], cpu)
        t.mark("render")
        gt = sample["body_image"]
        terms.append((pred - gt).abs().mean() * LOSS["l1"])
        crop = lambda x: square_crop(x, scene.square, bg, s["lpips_size"])  # noqa: E731
        terms.append(self.lpips(crop(pred), crop(gt)).mean() * LOSS["lpips"])
        t.mark("lpips")
        terms.append((offset_norm(g["body_offsets"]) + offset_norm(g["face_offsets"]))
                     * LOSS["offset"])
        # losses.rs `face`
        fc = s["face_crop"]
        fake, hf = render(g, inp, scene.view, scene.k_face, fc, fc, bg, sample["face_band"],
                          cpu)
        t.mark("render")
        real = sample["face_image"]
        terms.append((fake - real).abs().mean() * LOSS["face_l1"])
        terms.append(self.lpips(fake, real).mean() * LOSS["face_lpips"])
        t.mark("lpips")
        for p in self.disc.parameters():
            p.requires_grad_(False)
        terms.append(F.softplus(-self.disc(fake)).mean() * LOSS["adversarial"])
        t.mark("adversarial")
        values = torch.stack([x.reshape(()) for x in terms]).detach().cpu()
        if not torch.isfinite(values).all():
            raise SystemExit(f"non-finite loss terms: {values.tolist()}")
        t.mark("readback")
        total = terms[0]
        for x in terms[1:]:
            total = total + x
        total.backward()
        t.mark("backward")
        self.opt_body.step()
        self.opt_face.step()
        self.opt_body.zero_grad(set_to_none=True)
        self.opt_face.zero_grad(set_to_none=True)
        t.mark("optimiser")
        # parallel.rs `discriminator_step`
        for p in self.disc.parameters():
            p.requires_grad_(True)
        fake = fake.detach()
        loss = F.softplus(self.disc(fake)).mean() + F.softplus(-self.disc(real)).mean()
        r1 = self.disc_steps % LOSS["r1_interval"] == 0 and LOSS["r1_gamma"] > 0
        if r1:
            self.r1_steps.append(index)
            eps = 1e-2
            u = torch.randn(real.shape).to(dev)  # drawn on the host and uploaded, as f3g
            plus = self.disc(real + u * eps)
            minus = self.disc(real - u * eps)
            penalty = ((plus - minus) / (2 * eps)).pow(2).mean() * (LOSS["r1_gamma"] / 2)
            loss = loss + penalty * LOSS["r1_interval"]
        value = loss.item()
        if not math.isfinite(value):
            raise SystemExit(f"non-finite discriminator loss {value}")
        loss.backward()
        self.opt_disc.step()
        self.opt_disc.zero_grad(set_to_none=True)
        self.disc_steps += 1
        t.mark("discriminator")
        self.hits = (hb, hf)
        return values


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda", help="cuda, cuda:N or cpu")
    p.add_argument("--steps", type=int, default=5, help="timed steps (median reported)")
    p.add_argument("--warmup", type=int, default=1, help="untimed steps first")
    p.add_argument("--json", help="write the results as JSON to this path")
    p.add_argument("--small", action="store_true",
                   help="tiny sizes (cpu-preset networks, a 48×64 image): a CPU smoke run")
    p.add_argument("--sync-phases", action="store_true",
                   help="synchronise at every phase mark, as f3g's timer (default: CUDA events)")
    p.add_argument("--adam", choices=["default", "foreach", "fused"], default="default",
                   help="torch.optim.Adam's implementation (default: PyTorch's choice)")
    p.add_argument("--tf32", choices=["on", "off"], default=None,
                   help="TF32 for matmul and cuDNN (default: PyTorch's defaults)")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.steps < 1 or a.warmup < 0:
        p.error("--steps must be at least 1 and --warmup at least 0")
    device = torch.device(a.device)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            print("CUDA is not available: use --device cpu --small", file=sys.stderr)
            return 2
        if device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        torch.cuda.set_device(device)
    elif not a.small:
        print("note: the paper sizes on the CPU stand-in renderer need a dense "
              "[Gaussians × pixels] matrix: use --small", file=sys.stderr)
        return 2
    torch.backends.cudnn.benchmark = True
    if a.tf32 is not None:
        torch.backends.cuda.matmul.allow_tf32 = a.tf32 == "on"
        torch.backends.cudnn.allow_tf32 = a.tf32 == "on"
    s = SMALL if a.small else PAPER
    t_build = time.perf_counter()
    twin = Twin(s, device, a.adam, a.seed)
    build_s = time.perf_counter() - t_build
    params = twin.params()
    expected = [expected_styleunet_params(c) for c in twin.configs]
    nb, nf = s["body_gaussians"], s["face_gaussians"]
    print(f"{s['name']}: {nb} body + {nf} face Gaussians, body view {s['width']}×{s['height']}, "
          f"head crop {s['face_crop']}², LPIPS VGG {s['lpips_size']}², discriminator "
          f"{s['disc']['resolution']}²; network parameters {params} (built in {build_s:.1f} s)",
          file=sys.stderr, flush=True)
    timer = Timer(device, a.sync_phases)
    walls = []
    t_warm = time.perf_counter()
    for i in range(a.warmup + a.steps):
        if i == a.warmup:
            warmup_ms = (time.perf_counter() - t_warm) * 1e3
        timer.start()
        values = twin.step(timer, i)
        wall = timer.finish(i >= a.warmup)
        if i >= a.warmup:
            walls.append(wall)
        print(f"  step {i}{' (warm-up)' if i < a.warmup else ''}: {wall:.1f} ms, loss terms "
              f"{[round(v, 4) for v in values.tolist()]}", file=sys.stderr, flush=True)
    if a.warmup == 0:
        warmup_ms = 0.0
    phases = [(ph, timer.totals[ph] / a.steps) for ph in PHASES]
    step_ms = median(walls)
    print(f"{'phase':<14} {'ms/step':>10}")
    for ph, ms in phases:
        print(f"{ph:<14} {ms:>10.1f}")
    print(f"{'step':<14} {step_ms:>10.1f}  median wall clock per step (mean "
          f"{sum(walls) / len(walls):.1f}; phases sum to {sum(m for _, m in phases):.1f})")
    peak = (torch.cuda.max_memory_reserved(device) / 2 ** 20 if device.type == "cuda"
            else None)
    dev_name = (torch.cuda.get_device_name(device) if device.type == "cuda"
                else f"cpu, {torch.get_num_threads()} threads")
    try:  # the installed distribution's version (the CPU stand-in does not import gsplat)
        import importlib.metadata
        gs_version = importlib.metadata.version("gsplat")
    except Exception:  # noqa: BLE001 (gsplat on PYTHONPATH without its metadata, or absent)
        gs_version = getattr(sys.modules.get("gsplat"), "__version__", None)
    print(f"(PyTorch {torch.__version__}, {device}: {dev_name}; gsplat {gs_version}; "
          f"{'synchronised phases' if a.sync_phases or device.type != 'cuda' else 'CUDA events'}"
          f"; R1 in timed steps: {[i for i in twin.r1_steps if i >= a.warmup]}; peak "
          f"{'-' if peak is None else f'{peak:.0f} MiB'})")
    mismatch = [(pp, e) for pp, e in zip(params, expected) if pp != e]
    if mismatch:
        print(f"WARNING: parameter counts {params} differ from the Rust-derived {expected}",
              file=sys.stderr)
    if a.json:
        result = dict(
            device=str(device), device_name=dev_name, torch=torch.__version__,
            gsplat=gs_version, preset=s["name"], stage="Joint", steps=a.steps,
            warmup=a.warmup, step_ms=step_ms, step_ms_mean=sum(walls) / len(walls),
            step_ms_all=walls, phases={"phases": [[ph, ms] for ph, ms in phases]},
            phase_timing="sync" if a.sync_phases or device.type != "cuda" else "cuda-events",
            peak_mib=peak, warmup_ms=warmup_ms, build_s=build_s,
            body_gaussians=nb, face_gaussians=nf,
            intersections={"body": twin.hits[0], "head": twin.hits[1]},
            network_parameters=params, expected_network_parameters=expected,
            discriminator_parameters=sum(p.numel() for p in twin.disc.parameters()),
            loss_terms=values.tolist(),
            r1_timed_steps=[i for i in twin.r1_steps if i >= a.warmup],
            adam=a.adam, cudnn_benchmark=True,
            tf32={"matmul": torch.backends.cuda.matmul.allow_tf32,
                  "cudnn": torch.backends.cudnn.allow_tf32},
        )
        with open(a.json, "w") as f:
            json.dump(result, f, indent=2, ensure_ascii=False)
            f.write("\n")
    return 1 if mismatch else 0


if __name__ == "__main__":
    sys.exit(main())
