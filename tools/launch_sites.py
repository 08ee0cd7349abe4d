#!/usr/bin/env python3
"""Counts kernel launches by kernel and by the f3g function that caused them, from
`perf script -F ip,sym` of uprobes on CubeCL's `Client::launch` (tools/launch_sites.sh).

Reads stdin: one block of frames (innermost first) per launch, blocks separated by blank lines.
Keeps the launches of the second step (from the first skinning launch after the warm-up's
first Adam launch on). A launch's kernel is the frame below CubeCL's `KernelLauncher`; its site
is the first frame in an f3g crate; its op the Burn tensor op or autodiff backward on the way.
"""

import collections
import re
import sys


def frames(block):
    out = []
    for line in block.strip().split("\n"):
        parts = line.strip().split(None, 1)
        if len(parts) == 2:
            out.append(parts[1])
    return out


def short(name, width=100):
    # `<T as Trait>::f` reads as `T::f` for the counts.
    return re.sub(r"<(\S+?) as \S+?>", r"\1", name)[:width]


def second_step(blocks):
    seen_adam = False
    for i, block in enumerate(blocks):
        if "adam" in block:
            seen_adam = True
        elif seen_adam and "posing::" in block:
            return blocks[i:]
    return blocks


def main():
    blocks = [b for b in sys.stdin.read().split("\n\n") if b.strip()]
    step = second_step(blocks)
    by_kernel, by_site, by_pair = (collections.Counter() for _ in range(3))
    for block in step:
        f = frames(block)
        kernel = re.sub(r"::launch_unchecked$|::launch$", "", f[2]) if len(f) > 2 else "?"
        op = "?"
        for frame in f:
            m = re.search(r"Dispatch>::(float_\w+|int_\w+|bool_\w+)", frame)
            if m:
                op = m.group(1)
                break
            m = re.search(r"::(\w+) as burn_autodiff::ops::backward::Backward", frame)
            if m:
                op = "backward of " + m.group(1)
                break
            if "burn_autodiff::ops::backward::" in frame:
                op = "backward of a " + frame.rsplit("::", 1)[-1] + " op"
                break
        site = next((short(x) for x in f if "f3g_" in x), "?")
        by_kernel[short(kernel, 80)] += 1
        by_site[site] += 1
        by_pair[(site, op)] += 1
    print(f"{len(step)} launches in the second step ({len(blocks)} recorded in all)\n")
    print("== by f3g function")
    for k, v in by_site.most_common(40):
        print(f"{v:6d}  {k}")
    print("\n== by kernel")
    for k, v in by_kernel.most_common(40):
        print(f"{v:6d}  {k}")
    print("\n== by f3g function and op")
    for (site, op), v in by_pair.most_common(60):
        print(f"{v:6d}  {site} | {op}")


main()
