#!/usr/bin/env python3
"""PyTorch twin of `f3g bench nets`: the same networks, timed the same way.

What it is for
--------------
`f3g bench nets --device cuda --paper` (crates/cli/src/bench/nets.rs, `run`) times the forward and
the forward+backward of f3g's networks with Burn. This script builds the SAME-SHAPED networks in
PyTorch -- the DualStyleUNet presets of crates/nets/src/styleunet.rs with the StyleGAN2 layers
of crates/nets/src/layers.rs (their element-wise chains: fused/portable.rs), the LPIPS backbones
of crates/nets/src/lpips.rs and the residual
discriminator of crates/nets/src/discriminator.rs -- and times them on the same GPU with the
same inputs, losses and protocol, so that the ratio Burn / PyTorch per row tells whether Burn's
convolutions (or its element-wise kernels) are the bottleneck. Weight values are random (they do
not matter for timing); shapes, layer order and the element-wise operations are mirrored
operation for operation (equalised-learning-rate weight scaling at run time, modulation and
demodulation recomputed every call, the slice-and-add [1, 3, 3, 1] blur, bilinear up-sampling,
Haar transforms built from reshape/slice/cat, ...). The parameter column is PyTorch's own count
and must equal the Rust table's for the StyleUNets and the discriminator (`--check` verifies
the counts against the ones derived by hand from the Rust code, on the `meta` device, without
timing anything). LPIPS prints 0 parameters as the Rust table does (its weights are frozen
constants there); the JSON also has the backbone's real count.

Protocol (as `time_loss` in bench/nets.rs): the network is built once; each repetition times (1) the
forward under `torch.no_grad()` up to the scalar loss read back with `.item()` (Burn's
`into_scalar`), then (2) forward + `backward()`; `torch.cuda.synchronize()` is called before and
after each timing. The inputs (the `ramp` tensor, value i -> ((i * 7919) % 97) / 97) are made on
the host and copied to the device inside the timed region, as the Rust closures do. Repetition 0
(warm-up, cuDNN autotuning: `cudnn.benchmark = True`) is discarded, and the median of the
`--repeats` others is reported (the upper median `v[len / 2]`, as bench/mod.rs `median`).
Losses: StyleUNet `front.mean() + back.mean()`, LPIPS `d(x, 0.5 * ramp).sum()` with x requiring grad (weights
frozen), discriminator `D(ramp).mean()`. Batch 1 everywhere.

How to run it on the GPU machine (needs only PyTorch; no torchvision, no numpy):

    python3 tools/bench_nets_torch.py --paper --json out.json
    f3g bench nets --device cuda --paper --image 512 --json burn.json   # the Rust side

(`--image` defaults to 512 here but to 128 in the Rust bench: pass the same value to both.)
Other options: `--repeats N` (5), `--device cuda|cuda:N|cpu`, `--tf32 on|off` (default: leave
PyTorch's defaults; the values used are printed), `--channels-last`, `--check`.

The JSON is an object: run metadata plus `rows`, each with the Rust bench's fields (`name`,
`parameters`, `forward_ms`, `forward_backward_ms`) and `trainable_parameters`,
`peak_memory_forward_bytes`, `peak_memory_forward_backward_bytes`
(`torch.cuda.max_memory_allocated`, null on the CPU).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

LRELU_GAIN = math.sqrt(2.0)

# Set by --channels-last: the run-time (modulated) conv weights are made channels-last too.
CHANNELS_LAST = False


def _conv_weight(w: torch.Tensor) -> torch.Tensor:
    return w.contiguous(memory_format=torch.channels_last) if CHANNELS_LAST else w


# --------------------------------------------------------------------------------------------
# Expected parameter counts, derived by hand from the Rust code (Burn's `num_params` counts
# every `Param`, the fixed noise maps included).
#
# cpu body, `StyleUNetConfig::cpu_body(out, view)`: 64 -> 128, cm 1, base 1024, max 32,
# style 64, n_mlp 2, middle 8; channels(r) = clamp(1024 / r, 1, 32) = 32 for r <= 32, 16 at 64.
#   mapping: 2 x EqualLinear 64->64 (w + b)                     2 x (4096 + 64)      =   8 320
#   conv_in: ConvLayer 3->32, 3x3, down, act (no conv bias, act bias)  864 + 32      =     896
#   encoder r = 32, 16: FromRgb 1x1 3->32 + bias (96 + 32)
#                       + ConvLayer 32->32 3x3 (9216 + 32) + ConvLayer 32->32 down (9216 + 32)
#                                                               2 x 18 624           =  37 248
#   decoder (one of two), levels r = 8, 16, 32 (StyledConv = modulated weight + modulation
#   EqualLinear style->cin (w + b) + noise strength 1 + noise map (2r)^2 + bias;
#   ToRgb = modulated 1x1 cin->4·out + modulation + bias 4·out), out = 3:
#     r=8 : comb 32->32 9 248; up 32->32 @16 9216+2080+1+256+32 = 11 585; conv 11 585;
#           to_rgb 384+2080+12 = 2 476                                               =  34 894
#     r=16: comb 64->32 18 464; up @32 9216+2080+1+1024+32 = 12 353; conv 12 353;
#           to_rgb 2 476                                                              =  45 646
#     r=32: comb 64->32 18 464; up 32->16 @64 4608+2080+1+4096+16 = 10 801;
#           conv 16->16 @64 2304+1040+1+4096+16 = 7 457; to_rgb 192+1040+12 = 1 244   =  37 966
#     two decoders                                              2 x 118 506          = 237 012
#   view branch: conv 1->16 4x4 + b (272), conv 16->32 4x4 + b (8 224)                =   8 496
#   total: 291 972 with the view branch, 283 476 without (BENCHMARKS.md quotes
#   "283 476 – 291 972 parameters per body network"); 8 outputs: 286 796.
# The other presets follow from the same formulas (`expected_styleunet_params` below):
# cpu face 771 224 (BENCHMARKS.md: "771 224 for a face network with n_mlp 4"),
# paper body (3, view) 94 001 128, paper face (8) 63 730 064. The cpu discriminator at 128² is
# 298 489 (BENCHMARKS.md), at 512² 299 075, at 64² 296 625.
EXPECTED = {
    "StyleUNet body cpu (colour, view) 64→128": 291_972,
    "StyleUNet body cpu (position) 64→128": 283_476,
    "StyleUNet body cpu (other) 64→128": 286_796,
    "StyleUNet face cpu (colour, view) 32→32": 771_224,
    "StyleUNet body paper (colour, view) 512→1024": 94_001_128,
    "StyleUNet face paper (other) 256→256": 63_730_064,
    "discriminator cpu 64²": 296_625,
    "discriminator cpu 128²": 298_489,
    "discriminator cpu 512²": 299_075,
}


# --------------------------------------------------------------------------------------------
# Configurations (styleunet.rs / discriminator.rs presets)


def styleunet_config(kind: str, out_channels: int, view: bool) -> dict:
    paper_body = dict(input_size=512, output_size=1024, in_channels=3, out_channels=out_channels,
                      channel_multiplier=2, channel_base=16384, max_channels=512, style_dim=512,
                      n_mlp=2, middle_size=8, view_conditioned=view)
    cpu_body = dict(input_size=64, output_size=128, in_channels=3, out_channels=out_channels,
                    channel_multiplier=1, channel_base=1024, max_channels=32, style_dim=64,
                    n_mlp=2, middle_size=8, view_conditioned=view)
    if kind == "paper_body":
        return paper_body
    if kind == "paper_face":
        return {**paper_body, "input_size": 256, "output_size": 256, "channel_multiplier": 1,
                "style_dim": 256, "n_mlp": 4}
    if kind == "cpu_body":
        return cpu_body
    if kind == "cpu_face":
        return {**cpu_body, "input_size": 32, "output_size": 32, "max_channels": 64,
                "middle_size": 4, "n_mlp": 4}
    raise ValueError(kind)


def channels_of(c: dict, r: int) -> int:
    return min(max(c["channel_base"] * c["channel_multiplier"] // r, 1), c["max_channels"])


def discriminator_config_cpu(resolution: int) -> dict:
    return dict(resolution=resolution, channel_multiplier=1, channel_base=1024, max_channels=64,
                stddev_group=4)


def expected_styleunet_params(c: dict) -> int:
    """Parameter count of a Rust DualStyleUNet, from the constructors in styleunet.rs."""
    ch = lambda r: channels_of(c, r)  # noqa: E731
    sd = c["style_dim"]
    conv = lambda a, b, k, bias: a * b * k * k + (b if bias else 0)  # noqa: E731
    conv_layer = lambda a, b, k, act: conv(a, b, k, not act) + (b if act else 0)  # noqa: E731
    linear = lambda a, b: a * b + b  # noqa: E731
    modulated = lambda a, b, k: a * b * k * k + linear(sd, a)  # noqa: E731
    styled = lambda a, b, size: modulated(a, b, 3) + 1 + size * size + b  # noqa: E731
    s, cin, cout = c["input_size"], c["in_channels"], c["out_channels"]
    n = conv_layer(cin, ch(s // 2), 3, True)
    r = s // 2
    while r > c["middle_size"]:
        n += conv(cin, ch(r), 1, False) + ch(r)
        n += conv_layer(ch(r), ch(r), 3, True) + conv_layer(ch(r), ch(r // 2), 3, True)
        r //= 2
    dec, r = 0, c["middle_size"]
    while r <= c["output_size"] // 4:
        comb_in = ch(r) if r == c["middle_size"] else 2 * ch(r)
        dec += conv_layer(comb_in, ch(r), 3, True)
        dec += styled(ch(r), ch(2 * r), 2 * r) + styled(ch(2 * r), ch(2 * r), 2 * r)
        dec += modulated(ch(2 * r), 4 * cout, 1) + 4 * cout
        r *= 2
    n += 2 * dec
    if c["view_conditioned"]:
        v = ch(s // 2)
        h = max(v // 2, 1)
        n += conv(1, h, 4, True) + conv(h, v, 4, True)
    return n + c["n_mlp"] * linear(sd, sd)


def expected_discriminator_params(c: dict) -> int:
    ch = lambda r: min(max(c["channel_base"] * c["channel_multiplier"] // r, 1),  # noqa: E731
                       c["max_channels"])
    conv = lambda a, b, k, bias: a * b * k * k + (b if bias else 0)  # noqa: E731
    conv_layer = lambda a, b, k, act: conv(a, b, k, not act) + (b if act else 0)  # noqa: E731
    n, r = 0, c["resolution"]
    while r > 4:
        n += conv_layer(ch(r), ch(r), 3, True) + conv_layer(ch(r), ch(r // 2), 3, True)
        n += conv_layer(ch(r), ch(r // 2), 1, False)
        r //= 2
    n += conv_layer(3, ch(c["resolution"]), 1, True) + conv_layer(ch(4) + 1, ch(4), 3, True)
    n += (16 * ch(4) * ch(4) + ch(4)) + (ch(4) + 1)
    return n


# --------------------------------------------------------------------------------------------
# layers.rs


def fused_lrelu(x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    return F.leaky_relu(x + bias.reshape(1, -1, 1, 1), 0.2) * LRELU_GAIN


def resize(x: torch.Tensor, height: int, width: int) -> torch.Tensor:
    return F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)


def upsample2(x: torch.Tensor) -> torch.Tensor:
    return resize(x, 2 * x.shape[2], 2 * x.shape[3])


_TAPS = (1.0 / 8.0, 3.0 / 8.0, 3.0 / 8.0, 1.0 / 8.0)


def blur(x: torch.Tensor, before: int, after: int) -> torch.Tensor:
    """The separable [1, 3, 3, 1] / 8 blur as fused/portable.rs builds it: pad, four slices per axis."""
    x = F.pad(x, (before, after, before, after))
    h, w = x.shape[2], x.shape[3]
    oh, ow = h - 3, w - 3
    rows = None
    for k, t in enumerate(_TAPS):
        v = x[:, :, :, k:k + ow] * t
        rows = v if rows is None else rows + v
    out = None
    for k, t in enumerate(_TAPS):
        v = rows[:, :, k:k + oh, :] * t
        out = v if out is None else out + v
    return out


class EqualConv2d(nn.Module):
    def __init__(self, cin: int, cout: int, kernel: int, stride: int, padding: int, bias: bool):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(cout, cin, kernel, kernel))
        self.bias = nn.Parameter(torch.zeros(cout)) if bias else None
        self.scale = 1.0 / math.sqrt(cin * kernel * kernel)
        self.stride, self.padding = stride, padding

    def forward(self, x):
        return F.conv2d(x, self.weight * self.scale, self.bias, self.stride, self.padding)


class EqualLinear(nn.Module):
    def __init__(self, cin: int, cout: int, bias_init: float, lr_mul: float, activate: bool):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(cout, cin) / lr_mul)
        self.bias = nn.Parameter(torch.full((cout,), bias_init / lr_mul))
        self.scale = lr_mul / math.sqrt(cin)
        self.lr_mul, self.activate = lr_mul, activate

    def forward(self, x):
        y = x.matmul((self.weight * self.scale).t()) + (self.bias * self.lr_mul).reshape(1, -1)
        return F.leaky_relu(y, 0.2) * LRELU_GAIN if self.activate else y


class ConvLayer(nn.Module):
    """Optional blur + stride-2 down-sampling, equalised conv, optional fused leaky ReLU."""

    def __init__(self, cin: int, cout: int, kernel: int, downsample: bool, activate: bool):
        super().__init__()
        stride, padding = (2, 0) if downsample else (1, kernel // 2)
        self.conv = EqualConv2d(cin, cout, kernel, stride, padding, not activate)
        self.activation_bias = nn.Parameter(torch.zeros(cout)) if activate else None
        self.downsample, self.kernel = downsample, kernel

    def forward(self, x):
        if self.downsample:
            p = 2 + self.kernel - 1
            x = blur(x, (p + 1) // 2, p // 2)
        y = self.conv(x)
        return fused_lrelu(y, self.activation_bias) if self.activation_bias is not None else y


class ModulatedConv2d(nn.Module):
    """Style-modulated (and optionally demodulated) conv; one style for the whole batch."""

    def __init__(self, cin, cout, kernel, style_dim, demodulate, upsample):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(cout, cin, kernel, kernel))
        self.modulation = EqualLinear(style_dim, cin, 1.0, 1.0, False)
        self.scale = 1.0 / math.sqrt(cin * kernel * kernel)
        self.demodulate, self.upsample = demodulate, upsample

    def forward(self, x, style):
        cout, cin, k, _ = self.weight.shape
        s = self.modulation(style).reshape(1, cin, 1, 1)
        w = self.weight * s * self.scale
        if self.demodulate:
            d = (w.pow(2).sum(1, keepdim=True).sum(2, keepdim=True).sum(3, keepdim=True)
                 + 1e-8).sqrt().reciprocal()
            w = w * d.reshape(cout, 1, 1, 1)
        if self.upsample:
            x = upsample2(x)
        return F.conv2d(x, _conv_weight(w), None, 1, k // 2)


class NoiseInjection(nn.Module):
    def __init__(self, size: int):
        super().__init__()
        self.strength = nn.Parameter(torch.zeros(1))
        # A parameter without gradient, as in Rust (counted by num_params there too).
        self.noise = nn.Parameter(torch.randn(1, 1, size, size), requires_grad=False)

    def forward(self, x):
        return x + self.noise * self.strength.reshape(1, 1, 1, 1)


class StyledConv(nn.Module):
    def __init__(self, cin, cout, style_dim, upsample, out_size):
        super().__init__()
        self.conv = ModulatedConv2d(cin, cout, 3, style_dim, True, upsample)
        self.noise = NoiseInjection(out_size)
        self.bias = nn.Parameter(torch.zeros(cout))

    def forward(self, x, style):
        return fused_lrelu(self.noise(self.conv(x, style)), self.bias)


def haar(x: torch.Tensor) -> torch.Tensor:
    b, c, h2, w2 = x.shape
    h, w = h2 // 2, w2 // 2
    x = x.reshape(b, c, h, 2, w, 2)

    def tap(i, j):
        return x[:, :, :, i:i + 1, :, j:j + 1].reshape(b, c, 1, h, w)

    p, q, r, s = tap(0, 0), tap(0, 1), tap(1, 0), tap(1, 1)
    ll = (p + q + r + s) * 0.5
    lh = (p + q - r - s) * 0.5
    hl = (p - q + r - s) * 0.5
    hh = (p - q - r + s) * 0.5
    return torch.cat([ll, lh, hl, hh], 2).reshape(b, 4 * c, h, w)


def inverse_haar(x: torch.Tensor) -> torch.Tensor:
    b, c4, h, w = x.shape
    c = c4 // 4
    x = x.reshape(b, c, 4, h, w)
    ll, lh, hl, hh = (x[:, :, k:k + 1] for k in range(4))
    p = (ll + lh + hl + hh) * 0.5
    q = (ll + lh - hl - hh) * 0.5
    r = (ll - lh + hl - hh) * 0.5
    s = (ll - lh - hl + hh) * 0.5

    def row(a, bb):
        return torch.cat([a.reshape(b, c, h, w, 1), bb.reshape(b, c, h, w, 1)], 4)

    top = row(p, q).reshape(b, c, h, 1, w, 2)
    bottom = row(r, s).reshape(b, c, h, 1, w, 2)
    return torch.cat([top, bottom], 3).reshape(b, c, 2 * h, 2 * w)


class ToRgb(nn.Module):
    def __init__(self, cin, cout, style_dim):
        super().__init__()
        self.conv = ModulatedConv2d(cin, 4 * cout, 1, style_dim, False, False)
        self.bias = nn.Parameter(torch.zeros(4 * cout))

    def forward(self, x, style, skip=None):
        out = self.conv(x, style) + self.bias.reshape(1, -1, 1, 1)
        if skip is not None:
            out = out + haar(upsample2(inverse_haar(skip)))
        return out


def pixel_norm(x: torch.Tensor) -> torch.Tensor:
    ms = x.pow(2).mean(1, keepdim=True)
    return x / (ms + 1e-8).sqrt()


class Mapping(nn.Module):
    def __init__(self, style_dim, n_mlp, lr_mul):
        super().__init__()
        self.layers = nn.ModuleList(
            EqualLinear(style_dim, style_dim, 0.0, lr_mul, True) for _ in range(n_mlp))

    def forward(self, z):
        x = pixel_norm(z)
        for layer in self.layers:
            x = layer(x)
        return x


# --------------------------------------------------------------------------------------------
# styleunet.rs


class FromRgb(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.conv = EqualConv2d(cin, cout, 1, 1, 0, False)
        self.bias = nn.Parameter(torch.zeros(cout))


class ConvBlock(nn.Module):
    def __init__(self, c_in, c_out):
        super().__init__()
        self.conv1 = ConvLayer(c_in, c_in, 3, False, True)
        self.conv2 = ConvLayer(c_in, c_out, 3, True, True)


class DecoderBlock(nn.Module):
    def __init__(self, comb_in, c_r, c_2r, style_dim, out_channels, size):
        super().__init__()
        self.comb = ConvLayer(comb_in, c_r, 3, False, True)
        self.up = StyledConv(c_r, c_2r, style_dim, True, size)
        self.conv = StyledConv(c_2r, c_2r, style_dim, False, size)
        self.to_rgb = ToRgb(c_2r, out_channels, style_dim)


class Decoder(nn.Module):
    def __init__(self, c: dict):
        super().__init__()
        ch = lambda r: channels_of(c, r)  # noqa: E731
        blocks, r = [], c["middle_size"]
        while r <= c["output_size"] // 4:
            comb_in = ch(r) if r == c["middle_size"] else 2 * ch(r)
            blocks.append(DecoderBlock(comb_in, ch(r), ch(2 * r), c["style_dim"],
                                       c["out_channels"], 2 * r))
            r *= 2
        self.blocks = nn.ModuleList(blocks)

    def forward(self, skips, style, view, view_level):
        x = skips[-1]
        rgb = None
        for level, block in enumerate(self.blocks):
            if level > 0:
                x = torch.cat([x, skips[len(skips) - 1 - level]], 1)
            x = block.comb(x)
            x = block.up(x, style)
            x = block.conv(x, style)
            if level == view_level and view is not None:
                x = x + view
                view = None
            rgb = block.to_rgb(x, style, rgb)
        return inverse_haar(rgb)


class ViewBranch(nn.Module):
    def __init__(self, c):
        super().__init__()
        half = max(c // 2, 1)
        self.conv1 = EqualConv2d(1, half, 4, 2, 1, True)
        self.conv2 = EqualConv2d(half, c, 4, 2, 1, True)


class DualStyleUNet(nn.Module):
    def __init__(self, c: dict):
        super().__init__()
        self.c = c
        ch = lambda r: channels_of(c, r)  # noqa: E731
        s, cin = c["input_size"], c["in_channels"]
        self.conv_in = ConvLayer(cin, ch(s // 2), 3, True, True)
        from_rgb, encoder, r = [], [], s // 2
        while r > c["middle_size"]:
            from_rgb.append(FromRgb(cin, ch(r)))
            encoder.append(ConvBlock(ch(r), ch(r // 2)))
            r //= 2
        self.from_rgb = nn.ModuleList(from_rgb)
        self.encoder = nn.ModuleList(encoder)
        self.front = Decoder(c)
        self.back = Decoder(c)
        self.view = ViewBranch(ch(s // 2)) if c["view_conditioned"] else None
        self.mapping = Mapping(c["style_dim"], c["n_mlp"], 0.01)

    def style(self, device):
        d = self.c["style_dim"]
        z = torch.ones(1, d, device=device) / math.sqrt(d)
        return self.mapping(z)

    def forward(self, inp, view=None):
        c = self.c
        s = c["input_size"]
        style = self.style(inp.device)
        skips = []
        x = self.conv_in(inp)
        r = s // 2
        for rgb, block in zip(self.from_rgb, self.encoder):
            factor = s // r
            small = inp if factor == 1 else F.avg_pool2d(inp, factor)
            x = x + fused_lrelu(rgb.conv(small), rgb.bias)
            skips.append(x)
            x = block.conv1(x)
            x = block.conv2(x)
            r //= 2
        skips.append(x)
        view_level = int(math.log2(s // 2 // c["middle_size"])) - 1
        vf = vb = None
        if self.view is not None:
            def feat(m):
                y = F.leaky_relu(self.view.conv1(m), 0.2)
                y = self.view.conv2(y)
                return resize(y, s // 2, s // 2)
            vf, vb = feat(view[0]), feat(view[1])
        return (self.front(skips, style, vf, view_level),
                self.back(skips, style, vb, view_level))


# --------------------------------------------------------------------------------------------
# discriminator.rs


class ResBlock(nn.Module):
    def __init__(self, c_r, c_half):
        super().__init__()
        self.conv1 = ConvLayer(c_r, c_r, 3, False, True)
        self.conv2 = ConvLayer(c_r, c_half, 3, True, True)
        self.skip = ConvLayer(c_r, c_half, 1, True, False)


def minibatch_stddev(x, group):
    b, c, h, w = x.shape
    g = min(group, b)
    g = next((k for k in range(g, 0, -1) if b % k == 0), 1)
    y = x.reshape(g, b // g, c, h, w)
    centred = y - y.mean(0, keepdim=True)
    std = (centred.pow(2).mean(0, keepdim=True) + 1e-8).sqrt()
    feature = std.reshape(b // g, c * h * w).mean(1, keepdim=True).reshape(1, b // g, 1, 1)
    per_sample = torch.cat([feature] * g, 0).reshape(b, 1, 1, 1)
    fmap = per_sample * torch.ones(b, 1, h, w, device=x.device, dtype=x.dtype)
    return torch.cat([x, fmap], 1)


class Discriminator(nn.Module):
    def __init__(self, c: dict):
        super().__init__()
        ch = lambda r: min(max(c["channel_base"] * c["channel_multiplier"] // r, 1),  # noqa: E731
                           c["max_channels"])
        blocks, r = [], c["resolution"]
        while r > 4:
            blocks.append(ResBlock(ch(r), ch(r // 2)))
            r //= 2
        self.blocks = nn.ModuleList(blocks)
        self.from_rgb = ConvLayer(3, ch(c["resolution"]), 1, False, True)
        self.final_conv = ConvLayer(ch(4) + 1, ch(4), 3, False, True)
        self.final_linear = EqualLinear(ch(4) * 16, ch(4), 0.0, 1.0, True)
        self.score = EqualLinear(ch(4), 1, 0.0, 1.0, False)
        self.stddev_group = c["stddev_group"]

    def forward(self, images):
        x = self.from_rgb(images * 2.0 - 1.0)
        for block in self.blocks:
            y = block.conv2(block.conv1(x))
            x = (y + block.skip(x)) / LRELU_GAIN
        x = self.final_conv(minibatch_stddev(x, self.stddev_group))
        b, c, h, w = x.shape
        return self.score(self.final_linear(x.reshape(b, c * h * w)))


# --------------------------------------------------------------------------------------------
# lpips.rs: (out, kernel, stride, padding, max pool (kernel, stride) before, tap)

ALEX = [
    (64, 11, 4, 2, None, True),
    (192, 5, 1, 2, (3, 2), True),
    (384, 3, 1, 1, (3, 2), True),
    (256, 3, 1, 1, None, True),
    (256, 3, 1, 1, None, True),
]
VGG = [
    (64, 3, 1, 1, None, False),
    (64, 3, 1, 1, None, True),
    (128, 3, 1, 1, (2, 2), False),
    (128, 3, 1, 1, None, True),
    (256, 3, 1, 1, (2, 2), False),
    (256, 3, 1, 1, None, False),
    (256, 3, 1, 1, None, True),
    (512, 3, 1, 1, (2, 2), False),
    (512, 3, 1, 1, None, False),
    (512, 3, 1, 1, None, True),
    (512, 3, 1, 1, (2, 2), False),
    (512, 3, 1, 1, None, False),
    (512, 3, 1, 1, None, True),
]


class Lpips(nn.Module):
    """LPIPS v0.1 with frozen random weights (the Rust side's are constants: no weight grads)."""

    def __init__(self, specs):
        super().__init__()
        self.specs = specs
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        cin = 3
        for out, k, _, _, _, _ in specs:
            std = math.sqrt(2.0 / (cin * k * k))
            self.weights.append(nn.Parameter(torch.randn(out, cin, k, k) * std, requires_grad=False))
            self.biases.append(nn.Parameter(torch.zeros(out), requires_grad=False))
            cin = out
        self.heads = nn.ParameterList(
            nn.Parameter(torch.rand(1, s[0], 1, 1) * 0.1, requires_grad=False)
            for s in specs if s[5])
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]))

    def features(self, x):
        x = ((x * 2.0 - 1.0) - self.shift.reshape(1, 3, 1, 1)) / self.scale.reshape(1, 3, 1, 1)
        taps = []
        for (_, _, stride, padding, pool, tap), w, b in zip(self.specs, self.weights, self.biases):
            if pool is not None:
                x = F.max_pool2d(x, pool[0], pool[1])
            x = F.relu(F.conv2d(x, w, b, stride, padding))
            if tap:
                norm = x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10
                taps.append(x / norm)
        return taps

    def forward(self, a, b):
        batch = a.shape[0]
        total = None
        for x, y, head in zip(self.features(a), self.features(b), self.heads):
            weighted = F.conv2d((x - y).pow(2), _conv_weight(head))
            h, w = weighted.shape[2], weighted.shape[3]
            term = weighted.reshape(batch, h * w).mean(1).reshape(batch)
            total = term if total is None else total + term
        return total


# --------------------------------------------------------------------------------------------
# The bench (bench/nets.rs `run` and `time_loss`)


def ramp(shape, device):
    """Value i -> ((i * 7919) % 97) / 97, made on the host and copied (as bench/nets.rs `ramp`)."""
    n = math.prod(shape)
    i = torch.arange(n, dtype=torch.int64)
    v = ((i * 7919) % 97).to(torch.float32) / 97.0
    v = v.reshape(shape).to(device)
    return v.contiguous(memory_format=torch.channels_last) if CHANNELS_LAST else v


def param_counts(net: nn.Module):
    total = sum(p.numel() for p in net.parameters())
    trainable = sum(p.numel() for p in net.parameters() if p.requires_grad)
    return total, trainable


def median(v):
    v = sorted(v)
    return v[len(v) // 2]


def time_loss(repeats, device, net, loss):
    """(forward ms, forward+backward ms, peak forward bytes, peak forward+backward bytes)."""
    cuda = device.type == "cuda"

    def sync():
        if cuda:
            torch.cuda.synchronize(device)

    fwd, both, peak_f, peak_b = [], [], 0, 0
    for rep in range(repeats + 1):
        net.zero_grad(set_to_none=True)
        sync()
        if cuda:
            torch.cuda.reset_peak_memory_stats(device)
        start = time.perf_counter()
        with torch.no_grad():
            loss(net, device, False).item()
        sync()
        t_fwd = (time.perf_counter() - start) * 1e3
        if cuda:
            pf = torch.cuda.max_memory_allocated(device)
            torch.cuda.reset_peak_memory_stats(device)
        start = time.perf_counter()
        loss(net, device, True).backward()
        sync()
        t_both = (time.perf_counter() - start) * 1e3
        if cuda:
            pb = torch.cuda.max_memory_allocated(device)
        if rep > 0:
            fwd.append(t_fwd)
            both.append(t_both)
            if cuda:
                peak_f, peak_b = max(peak_f, pf), max(peak_b, pb)
    net.zero_grad(set_to_none=True)
    return (median(fwd), median(both), peak_f if cuda else None, peak_b if cuda else None)


def styleunet_presets(paper: bool):
    nets = [
        ("body cpu (colour, view)", styleunet_config("cpu_body", 3, True)),
        ("body cpu (position)", styleunet_config("cpu_body", 3, False)),
        ("body cpu (other)", styleunet_config("cpu_body", 8, False)),
        ("face cpu (colour, view)", styleunet_config("cpu_face", 3, True)),
    ]
    if paper:
        nets.append(("body paper (colour, view)", styleunet_config("paper_body", 3, True)))
        nets.append(("face paper (other)", styleunet_config("paper_face", 8, False)))
    return nets


def styleunet_row_name(name, c):
    return f"StyleUNet {name} {c['input_size']}→{c['output_size']}"


def disc_resolution(image: int) -> int:
    return max(1 << (image - 1).bit_length(), 8)


def check_counts(image: int) -> bool:
    """Builds every network on the meta device and compares its count with the derivations."""
    ok = True
    cases = []
    for name, c in styleunet_presets(True):
        with torch.device("meta"):
            net = DualStyleUNet(c)
        cases.append((styleunet_row_name(name, c), param_counts(net)[0],
                      expected_styleunet_params(c)))
    for r in sorted({64, 128, 512, disc_resolution(image)}):
        c = discriminator_config_cpu(r)
        with torch.device("meta"):
            net = Discriminator(c)
        cases.append((f"discriminator cpu {r}²", param_counts(net)[0],
                      expected_discriminator_params(c)))
    print("| network | PyTorch parameters | derived from the Rust code | stated | ok |")
    print("|---|---|---|---|---|")
    for name, got, derived in cases:
        stated = EXPECTED.get(name)
        good = got == derived and (stated is None or stated == got)
        ok &= good
        print(f"| {name} | {got} | {derived} | {stated if stated is not None else '—'} | "
              f"{'yes' if good else 'NO'} |")
    return ok


def main(argv=None) -> int:
    global CHANNELS_LAST
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=5, help="timed repetitions (median reported)")
    p.add_argument("--image", type=int, default=512,
                   help="side of the LPIPS / discriminator images, 32–2048 (Rust default: 128)")
    p.add_argument("--paper", action="store_true", help="also time the paper-sized StyleUNets")
    p.add_argument("--json", help="write the results as JSON to this path")
    p.add_argument("--device", default="cuda", help="cuda, cuda:N or cpu")
    p.add_argument("--tf32", choices=["on", "off"], default=None,
                   help="TF32 for matmul and cuDNN convolutions (default: PyTorch's defaults)")
    p.add_argument("--channels-last", action="store_true",
                   help="channels-last (NHWC) parameters, inputs and run-time conv weights")
    p.add_argument("--check", action="store_true",
                   help="only compare the parameter counts with the Rust-derived ones (meta "
                        "device, nothing timed); exit 1 on a mismatch")
    p.add_argument("--seed", type=int, default=0, help="seed of the random weights")
    a = p.parse_args(argv)
    if a.repeats < 1:
        p.error("--repeats must be at least 1")
    if not 32 <= a.image <= 2048:
        p.error("--image must be in 32..=2048")
    if a.check:
        return 0 if check_counts(a.image) else 1

    device = torch.device(a.device)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            print("CUDA is not available: use --device cpu", file=sys.stderr)
            return 2
        if device.index is None:  # torch.cuda.set_device needs an index
            device = torch.device("cuda", torch.cuda.current_device())
    CHANNELS_LAST = a.channels_last
    torch.backends.cudnn.benchmark = True
    if a.tf32 is not None:
        torch.backends.cuda.matmul.allow_tf32 = a.tf32 == "on"
        torch.backends.cudnn.allow_tf32 = a.tf32 == "on"
    tf32 = {
        "requested": a.tf32 or "default",
        "torch.backends.cuda.matmul.allow_tf32": torch.backends.cuda.matmul.allow_tf32,
        "torch.backends.cudnn.allow_tf32": torch.backends.cudnn.allow_tf32,
    }
    torch.manual_seed(a.seed)
    if device.type == "cuda":
        torch.cuda.set_device(device)

    rows = []

    def add_row(name, net, loss, shown_params=None, expected=None):
        net = net.to(device)
        if CHANNELS_LAST:
            net = net.to(memory_format=torch.channels_last)
        total, trainable = param_counts(net)
        fwd, both, pf, pb = time_loss(a.repeats, device, net, loss)
        params = total if shown_params is None else shown_params
        rows.append(dict(name=name, parameters=params, forward_ms=fwd, forward_backward_ms=both,
                         module_parameters=total, trainable_parameters=trainable,
                         expected_parameters=expected,
                         peak_memory_forward_bytes=pf, peak_memory_forward_backward_bytes=pb))
        print(f"  {name}: {fwd:.1f} / {both:.1f} ms", file=sys.stderr, flush=True)
        del net
        if device.type == "cuda":
            torch.cuda.empty_cache()

    for name, c in styleunet_presets(a.paper):
        s = c["input_size"]

        def su_loss(net, dev, _train, c=c, s=s):
            view = ((ramp((1, 1, s, s), dev), ramp((1, 1, s, s), dev))
                    if c["view_conditioned"] else None)
            front, back = net(ramp((1, 3, s, s), dev), view)
            return front.mean() + back.mean()

        add_row(styleunet_row_name(name, c), DualStyleUNet(c), su_loss,
                expected=expected_styleunet_params(c))

    size = a.image
    for net_name, specs in (("alex", ALEX), ("vgg", VGG)):
        def lp_loss(net, dev, train):
            x = ramp((1, 3, size, size), dev)
            if train:
                x.requires_grad_(True)
            return net(x, ramp((1, 3, size, size), dev) * 0.5).sum()

        # The Rust table prints 0 for LPIPS (frozen constants, not module parameters).
        add_row(f"LPIPS {net_name} {size}²", Lpips(specs), lp_loss, shown_params=0)

    dc = discriminator_config_cpu(disc_resolution(size))
    r = dc["resolution"]

    def d_loss(net, dev, _train):
        return net(ramp((1, 3, r, r), dev)).mean()

    add_row(f"discriminator cpu {r}²", Discriminator(dc), d_loss,
            expected=expected_discriminator_params(dc))

    print("| network | parameters | forward ms | forward+backward ms |\n|---|---|---|---|")
    for row in rows:
        print(f"| {row['name']} | {row['parameters']} | {row['forward_ms']:.1f} | "
              f"{row['forward_backward_ms']:.1f} |")
    dev_name = (torch.cuda.get_device_name(device) if device.type == "cuda"
                else f"cpu, {torch.get_num_threads()} threads")
    print(f"(PyTorch {torch.__version__}, {device}: {dev_name}; TF32: matmul "
          f"{tf32['torch.backends.cuda.matmul.allow_tf32']}, cuDNN "
          f"{tf32['torch.backends.cudnn.allow_tf32']} ({tf32['requested']}); channels-last "
          f"{a.channels_last}; cudnn.benchmark True)")
    mismatches = [r_ for r_ in rows if r_["expected_parameters"] is not None
                  and r_["expected_parameters"] != r_["module_parameters"]]
    for r_ in mismatches:
        print(f"WARNING: {r_['name']}: PyTorch counts {r_['module_parameters']} parameters, the "
              f"Rust network has {r_['expected_parameters']}")
    if a.json:
        meta = dict(torch=torch.__version__, device=str(device), device_name=dev_name,
                    tf32=tf32, channels_last=a.channels_last, cudnn_benchmark=True,
                    repeats=a.repeats, image=a.image, paper=a.paper, seed=a.seed, rows=rows)
        with open(a.json, "w") as f:
            json.dump(meta, f, indent=2, ensure_ascii=False)
            f.write("\n")
    return 1 if mismatches else 0


if __name__ == "__main__":
    sys.exit(main())
