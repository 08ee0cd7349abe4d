#!/usr/bin/env python3
"""Sums CubeCL's kernel profile (`F3G_KERNEL_PROFILE=FILE f3g …`) by kernel.

CubeCL's profiler writes one entry per launch, timed on the device, and a summary table at each
synchronisation; this reads the launch entries only. At level `basic` (f3g's default) an entry
is one `| <duration> | <kernel>_<variant hash>` line. At level `full`
(`CUBECL_DEBUG_OPTION=profile-full` as well) it is the kernel's type, its compile-time
configuration and its cube count over several lines; then each variant is described by what
those say — a convolution's pass (`Forward`, `BackwardWeight`, `BackwardData`), a reduction's
operation and routine, the grid — instead of by its hash. The launches are serialised while
profiled, so the totals say where device time goes, not how long a step takes.

    tools/kernel_profile.py profile.log [--json out.json] [--markdown out.md] [--top 30]
"""

import argparse
import json
import re
import sys

# The first line of a launch entry; the kernel's name may hold `|` (CubeCL joins generic
# arguments with it at level `basic`).
LAUNCH = re.compile(r"^\| (?P<duration>[0-9.]+(?:ns|µs|us|ms|s))\s+\| (?P<kernel>.+)$")
UNIT_MS = {"ns": 1e-6, "µs": 1e-3, "us": 1e-3, "ms": 1.0, "s": 1e3}


def milliseconds(duration: str) -> float:
    value, unit = re.fullmatch(r"([0-9.]+)(ns|µs|us|ms|s)", duration).groups()
    return float(value) * UNIT_MS[unit]


def launches(path: str):
    """Yields (milliseconds, first line's kernel text, the entry's further lines) per launch."""
    entry = None
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            m = LAUNCH.match(line.rstrip("\n"))
            if m:
                if entry:
                    yield entry
                entry = [milliseconds(m["duration"]), m["kernel"].strip(), ""]
            elif entry is not None:
                if line.startswith("|"):  # a summary table: the entry has ended
                    yield entry
                    entry = None
                else:
                    entry[2] += line
    if entry:
        yield entry


def family(kernel: str) -> str:
    """The kernel without what tells its compiled variants apart. `basic`: the name without its
    hash (`_1a2b3c4d`), generic arguments shortened to the first and last (a matmul's run to
    twenty); `full`: the type's last path segment, without generic arguments."""
    if "::" in kernel:
        head = kernel.split(": ", 1)[0]
        return re.sub(r"<.*", "", head).split("::")[-1]
    parts = [p.strip() for p in re.sub(r"_[0-9a-f]{8}$", "", kernel).split("|")]
    return " · ".join(parts if len(parts) <= 3 else [parts[0], "…", parts[-1]])


def variant(kernel: str, rest: str) -> str:
    """One compiled variant: `basic`, the family and its hash; `full`, the family and what its
    configuration says (a convolution's pass, a reduction's operation and routine) and grid."""
    if "::" not in kernel:
        return f"{family(kernel)} {kernel[-8:]}"
    text = kernel + "\n" + rest
    details = []
    reduce = family(kernel).startswith("Reduce")
    for pattern in (r"config: (\w+)", r"global: (\w+)") if reduce else (r"operation: (\w+)",):
        m = re.search(pattern, text)
        if m:
            details.append(m.group(1))
    m = re.search(r"CubeCount \(([^)]*)\)", text)
    if m:
        details.append("cubes " + " × ".join(m.group(1).split(", ")))
    return f"{family(kernel)} [{', '.join(details)}]" if details else family(kernel)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log")
    parser.add_argument("--json")
    parser.add_argument("--markdown")
    parser.add_argument("--top", type=int, default=30)
    args = parser.parse_args()

    families: dict[str, dict] = {}
    variants: dict[str, dict] = {}
    for ms, kernel, rest in launches(args.log):
        for table, key in ((families, family(kernel)), (variants, variant(kernel, rest))):
            entry = table.setdefault(key, {"launches": 0, "ms": 0.0})
            entry["launches"] += 1
            entry["ms"] += ms
    if not families:
        print(f"{args.log}: no launch lines (was F3G_KERNEL_PROFILE set on a cuda build?)",
              file=sys.stderr)
        return 1

    total = sum(k["ms"] for k in families.values())

    def ranked(table):
        return [
            {"kernel": name, "launches": k["launches"], "ms": round(k["ms"], 3),
             "share": round(k["ms"] / total, 4) if total else 0.0}
            for name, k in sorted(table.items(), key=lambda kv: -kv[1]["ms"])
        ]

    result = {
        "total_ms": round(total, 3),
        "launches": sum(k["launches"] for k in families.values()),
        "families": ranked(families),
        "variants": ranked(variants),
    }
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)
    rows = [f"Device time of the profiled launches: {total:.1f} ms in {result['launches']} "
            "launches.", "", "| kernel family | launches | ms | share |", "|---|---|---|---|"]
    rows += [f"| `{k['kernel']}` | {k['launches']} | {k['ms']:.1f} | {100 * k['share']:.1f} % |"
             for k in result["families"][: args.top]]
    rows += ["", "| kernel variant | launches | ms | ms per launch |", "|---|---|---|---|"]
    rows += [f"| `{k['kernel']}` | {k['launches']} | {k['ms']:.1f} | "
             f"{k['ms'] / k['launches']:.3f} |" for k in result["variants"][: args.top]]
    text = "\n".join(rows) + "\n"
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
