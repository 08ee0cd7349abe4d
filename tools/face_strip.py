#!/usr/bin/env python3
"""Frontal head crops side by side, for the README: the ground truth, then each run's render.

    python3 tools/face_strip.py --out strip.png --image cam00_00000004 \
        RUN_A/eval/novel-view RUN_B/eval/novel-view ...

Each argument is an `f3g eval` output folder; the row holds `images/<IMAGE>_head_gt.png` of
the first folder and `images/<IMAGE>_head.png` of every folder, in order. `--image` may be
given several times: one row per image. Needs Pillow (`pip install pillow`).
"""

import argparse
import sys
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("evals", nargs="+", type=Path, help="f3g eval output folders")
    parser.add_argument("--image", action="append", required=True,
                        help="image stem, e.g. cam00_00000004 (repeatable: one row each)")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    a = parser.parse_args()
    try:
        from PIL import Image
    except ImportError:
        print("face_strip.py needs Pillow: pip install pillow", file=sys.stderr)
        return 2
    rows = []
    for stem in a.image:
        paths = [a.evals[0] / "images" / f"{stem}_head_gt.png"]
        paths += [e / "images" / f"{stem}_head.png" for e in a.evals]
        missing = [str(p) for p in paths if not p.is_file()]
        if missing:
            print(f"missing: {', '.join(missing)}", file=sys.stderr)
            return 1
        rows.append([Image.open(p).convert("RGB") for p in paths])
    w, h = rows[0][0].size
    strip = Image.new("RGB", (w * len(rows[0]), h * len(rows)), "white")
    for r, row in enumerate(rows):
        for c, im in enumerate(row):
            strip.paste(im.resize((w, h)), (c * w, r * h))
    strip.save(a.out)
    print(f"wrote {a.out} ({strip.size[0]}×{strip.size[1]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
