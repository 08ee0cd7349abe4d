#!/usr/bin/env python3
"""Sums CubeCL's kernel profile (`F3G_KERNEL_PROFILE=FILE f3g …`) by kernel.

CubeCL's profiler (level `basic`) writes one `| <duration> | <kernel>` line per launch, timed
on the device, and a summary table at each synchronisation; this reads the launch lines only.
The launches are serialised while profiled, so the totals say where device time goes, not how
long a step takes.

    tools/kernel_profile.py profile.log [--json out.json] [--markdown out.md] [--top 30]
"""

import argparse
import json
import re
import sys

# A launch line; the kernel's name may hold `|` (CubeCL joins generic arguments with it).
LAUNCH = re.compile(r"^\| (?P<duration>[0-9.]+(?:ns|µs|us|ms|s))\s+\| (?P<kernel>.+)$")
UNIT_MS = {"ns": 1e-6, "µs": 1e-3, "us": 1e-3, "ms": 1.0, "s": 1e3}


def milliseconds(duration: str) -> float:
    value, unit = re.fullmatch(r"([0-9.]+)(ns|µs|us|ms|s)", duration).groups()
    return float(value) * UNIT_MS[unit]


def family(kernel: str) -> str:
    """The kernel's name without the hash of its compiled variant (`_1a2b3c4d`), its generic
    arguments shortened to the first and last (a matmul's run to twenty)."""
    parts = [p.strip() for p in re.sub(r"_[0-9a-f]{8}$", "", kernel.strip()).split("|")]
    return " · ".join(parts if len(parts) <= 3 else [parts[0], "…", parts[-1]])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log")
    parser.add_argument("--json")
    parser.add_argument("--markdown")
    parser.add_argument("--top", type=int, default=30)
    args = parser.parse_args()

    kernels: dict[str, dict] = {}
    with open(args.log, encoding="utf-8", errors="replace") as f:
        for line in f:
            m = LAUNCH.match(line.rstrip("\n"))
            if not m:
                continue
            entry = kernels.setdefault(m["kernel"].strip(), {"launches": 0, "ms": 0.0})
            entry["launches"] += 1
            entry["ms"] += milliseconds(m["duration"])
    if not kernels:
        print(f"{args.log}: no launch lines (was F3G_KERNEL_PROFILE set on a cuda build?)",
              file=sys.stderr)
        return 1

    total = sum(k["ms"] for k in kernels.values())
    families: dict[str, dict] = {}
    for name, k in kernels.items():
        entry = families.setdefault(family(name), {"launches": 0, "ms": 0.0})
        entry["launches"] += k["launches"]
        entry["ms"] += k["ms"]

    def ranked(table):
        return [
            {"kernel": name, "launches": k["launches"], "ms": round(k["ms"], 3),
             "share": round(k["ms"] / total, 4) if total else 0.0}
            for name, k in sorted(table.items(), key=lambda kv: -kv[1]["ms"])
        ]

    result = {
        "total_ms": round(total, 3),
        "launches": sum(k["launches"] for k in kernels.values()),
        "families": ranked(families),
        "kernels": ranked(kernels),
    }
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)
    rows = [f"Device time of the profiled launches: {total:.1f} ms in {result['launches']} "
            "launches.", "", "| kernel family | launches | ms | share |", "|---|---|---|---|"]
    rows += [f"| `{k['kernel']}` | {k['launches']} | {k['ms']:.1f} | {100 * k['share']:.1f} % |"
             for k in result["families"][: args.top]]
    # The compiled variants one by one (a family such as the matmuls holds dozens), with the
    # name shortened as for families and the variant's hash kept.
    rows += ["", "| kernel variant | launches | ms | ms per launch |", "|---|---|---|---|"]
    rows += [f"| `{family(k['kernel'])}` {k['kernel'].strip()[-8:]} | {k['launches']} | "
             f"{k['ms']:.1f} | {k['ms'] / k['launches']:.3f} |"
             for k in result["kernels"][: args.top]]
    text = "\n".join(rows) + "\n"
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
