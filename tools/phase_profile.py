#!/usr/bin/env python3
"""Where a GPU `paper` step's device time goes, phase by phase.

A GPU's kernel profile (`F3G_KERNEL_PROFILE`, CubeCL's `basic` level: one entry per launch, in
launch order, timed on the device) says how long each launch took but not which phase of the
step made it; the offline CUDA driver's trace of the same command says which phase each launch
belongs to but not how long it takes. This joins the two by walking both launch sequences in
order on the kernels' names. The offline driver never reaches the splat op's raster kernels
(its intersection count reads 0): such GPU-only launches join the phase of the launch before
them.

    tools/phase_profile.py trace F3G TRACE        # on the CPU machine, with a `cuda` build
    tools/phase_profile.py join TRACE[.xz] PROFILE [--json OUT] [--markdown OUT]

`trace` runs `F3G bench train --preset paper --device cuda --steps 1 --warmup 1` against the
offline driver (tools/cuda-offline.sh) with F3G_OFFLINE_TRACE and F3G_PHASE_TRACE both set to
TRACE: the driver appends a line per launch, the bench a line per phase mark. The GPU profile
must come from the same binary and command (tools/gpu-check.sh's profile-train-paper step at
`basic` level). `join` reports the last step of both.
"""

import argparse
import collections
import json
import lzma
import os
import re
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import kernel_profile  # noqa: E402

BENCH = ["bench", "train", "--preset", "paper", "--device", "cuda", "--steps", "1", "--warmup", "1"]
HASH = re.compile(r"_([0-9a-f]{8})$")


def snake(name):
    return re.sub(r"(?<!^)(?=[A-Z])", "_", name).lower()


def same_kernel(profiled, traced):
    """Whether a profile entry and a traced launch (a CUDA entry name: the kernel's function,
    its generic arguments, its variant hash) are the same kernel: at `basic` level by the
    variant hash both end in, at `full` level by the kernel type's name (`MatmulEntry` is
    `matmul_entry_…`)."""
    if "::" in profiled:
        return traced.startswith(snake(kernel_profile.family(profiled)))
    a, b = HASH.search(profiled.strip()), HASH.search(traced)
    return bool(a and b and a.group(1) == b.group(1))


def traced_steps(path):
    """Per step (from each `P start`), the launches as (kernel, phase): a launch belongs to the
    phase whose mark follows it."""
    steps, pending = [], []
    opener = lzma.open if path.endswith(".xz") else open
    with opener(path, "rt", encoding="utf-8", errors="replace") as f:
        for line in f:
            kind, _, rest = line.rstrip("\n").partition(" ")
            if kind == "P" and rest == "start":
                steps.append([])
                pending = []
            elif kind == "P" and steps:
                steps[-1].extend((name, rest) for name in pending)
                pending = []
            elif kind == "L":
                pending.append(rest.split(" ")[0])
    return steps


def join(trace, profile):
    steps = traced_steps(trace)
    if not steps:
        sys.exit(f"{trace}: no `P start` mark (was F3G_PHASE_TRACE set to it?)")
    last = steps[-1]
    launches = [(ms, name) for ms, name, _ in kernel_profile.launches(profile)]
    # The last traced step ends the process's launches on both sides: walk back from the ends.
    i, j = len(last) - 1, len(launches) - 1
    unmatched_gpu, unmatched_trace = 0, 0
    pairs = []
    while i >= 0 and j >= 0:
        name, phase = last[i]
        if same_kernel(launches[j][1], name):
            pairs.append((j, phase))
            i, j = i - 1, j - 1
            continue
        # A GPU-only launch (the splat op's raster) or a traced one the GPU did not make.
        ahead = next((k for k in range(j - 1, max(j - 400, -1), -1)
                      if same_kernel(launches[k][1], name)), None)
        if ahead is None:
            unmatched_trace += 1
            i -= 1
        else:
            unmatched_gpu += j - ahead
            j = ahead
    pairs.reverse()
    if not pairs:
        sys.exit("no launch of the trace's last step matched the profile's")
    # From the step's first matched launch on, each launch in its match's phase or, GPU-only,
    # in the phase of the launch before it.
    matched = dict(pairs)
    phase = pairs[0][1]
    by_phase = {}
    kernels = collections.defaultdict(collections.Counter)
    for k in range(pairs[0][0], len(launches)):
        phase = matched.get(k, phase)
        ms, name = launches[k]
        row = by_phase.setdefault(phase, {"launches": 0, "device_ms": 0.0})
        row["launches"] += 1
        row["device_ms"] += ms
        kernels[phase][name.strip()] += ms
    result = {
        "phases": [{"phase": p, **r, "top": [{"kernel": n, "ms": round(m, 3)}
                                             for n, m in kernels[p].most_common(5)]}
                   for p, r in by_phase.items()],
        "device_ms": sum(r["device_ms"] for r in by_phase.values()),
        "launches": sum(r["launches"] for r in by_phase.values()),
        "traced_launches": len(last),
        "gpu_only_launches": unmatched_gpu,
        "traced_not_profiled": unmatched_trace,
    }
    return result


def markdown(r):
    rows = [f"Last step: {r['device_ms']:.1f} ms of device time in {r['launches']} launches "
            f"({r['traced_launches']} traced offline; {r['gpu_only_launches']} GPU-only, "
            f"{r['traced_not_profiled']} traced but not profiled).", "",
            "| phase | launches | device ms | largest kernels (ms) |", "|---|---|---|---|"]
    for p in r["phases"]:
        top = "; ".join(f"`{t['kernel'][:60]}` {t['ms']:.1f}" for t in p["top"][:3])
        rows.append(f"| {p['phase']} | {p['launches']} | {p['device_ms']:.1f} | {top} |")
    return "\n".join(rows) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="mode", required=True)
    t = sub.add_parser("trace", help="the offline step's launches and phase marks")
    t.add_argument("f3g")
    t.add_argument("trace")
    j = sub.add_parser("join", help="a GPU's profile placed in the trace's phases")
    j.add_argument("trace")
    j.add_argument("profile")
    j.add_argument("--json")
    j.add_argument("--markdown")
    a = parser.parse_args()
    if a.mode == "trace":
        if os.path.exists(a.trace):
            os.remove(a.trace)
        env = dict(os.environ, F3G_OFFLINE_TRACE=a.trace, F3G_PHASE_TRACE=a.trace)
        tool = os.path.join(os.path.dirname(os.path.abspath(__file__)), "cuda-offline.sh")
        sys.exit(subprocess.call([tool, "run", a.f3g, *BENCH], env=env))
    r = join(a.trace, a.profile)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(r, f, indent=1)
    text = markdown(r)
    if a.markdown:
        with open(a.markdown, "w") as f:
            f.write(text)
    print(text, end="")


if __name__ == "__main__":
    main()
