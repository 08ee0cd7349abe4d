#!/usr/bin/env python3
"""The contact sheet of the retargeting corpus, for the README (assets/readme/corpus.png).

    F3G_CORPUS_DIR=/tmp/corpus cargo test --release -p f3g-motion --test conventions
    python3 tools/corpus_sheet.py --corpus /tmp/corpus --f3g target/release/f3g --out corpus.png

The conventions test writes each skeleton layout it checks as a BVH file into
`F3G_CORPUS_DIR`; this runs `f3g motion show --view front` on each (the file's skeleton in
blue, the built-in human it drives in orange) and stacks the sheets, two to a row, labelled.
Needs Pillow (`pip install pillow`).
"""

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

LAYOUTS = [
    ("mixamo", "Mixamo"),
    ("unreal", "Unreal mannequin"),
    ("cmu", "CMU ASF"),
    ("biped", "3ds Max Biped"),
    ("humanik", "MotionBuilder HumanIK"),
    ("lafan1", "LAFAN1 (rest along +X)"),
    ("metarig", "Rigify metarig"),
    ("DEF", "Rigify DEF- bones"),
    ("mixamo-anonymous", "names that say nothing"),
    ("kneel", "a kneel"),
]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--corpus", type=Path, required=True, help="F3G_CORPUS_DIR of the test")
    parser.add_argument("--f3g", type=Path, default=Path("target/release/f3g"))
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    parser.add_argument("--panel", type=int, default=110, help="side of one panel, pixels")
    a = parser.parse_args()
    try:
        from PIL import Image, ImageDraw
    except ImportError:
        print("corpus_sheet.py needs Pillow: pip install pillow", file=sys.stderr)
        return 2
    sheets = []
    with tempfile.TemporaryDirectory() as tmp:
        for stem, label in LAYOUTS:
            bvh = a.corpus / f"{stem}.bvh"
            if not bvh.is_file():
                print(f"missing {bvh}: run the conventions test with F3G_CORPUS_DIR", file=sys.stderr)
                return 1
            png = Path(tmp) / f"{stem}.png"
            subprocess.run([str(a.f3g), "motion", "show", str(bvh), "--out", str(png),
                            "--columns", "5", "--panel", str(a.panel), "--view", "front"],
                           check=True, stderr=subprocess.DEVNULL)
            sheets.append((Image.open(png).convert("RGB"), label))
    w = max(s.size[0] for s, _ in sheets)
    h = max(s.size[1] for s, _ in sheets)
    label_width = 160
    rows = (len(sheets) + 1) // 2
    out = Image.new("RGB", (2 * (w + label_width), rows * h), "white")
    draw = ImageDraw.Draw(out)
    for i, (sheet, label) in enumerate(sheets):
        x, y = (i % 2) * (w + label_width), (i // 2) * h
        out.paste(sheet, (x + label_width, y))
        draw.text((x + 6, y + h // 2 - 6), label, fill=(0, 0, 0))
    out.save(a.out)
    print(f"wrote {a.out} ({out.size[0]}×{out.size[1]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
