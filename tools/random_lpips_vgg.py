#!/usr/bin/env python3
"""Write LPIPS VGG16 weights of the real shapes with random values, for timing only.

The converted VGG weights (59 MB, `f3g weights lpips --net vgg`) cannot travel to a machine
without network access; a step's work does not depend on the values, so `tools/gpu-check.sh
run` times the `paper` preset with these. Never use them for a metric.

Keys and shapes are those `f3g_nets::lpips::Lpips::from_file` reads: `features.{i}.weight`
`[O, I, 3, 3]` and `features.{i}.bias` `[O]` for VGG16's 13 convolutions, `lin.{k}.weight`
`[1, C, 1, 1]` for the five taps. Standard library only (the values need not be Gaussian).

Usage: random_lpips_vgg.py OUT.safetensors
"""
import json
import os
import random
import struct
import sys

CHANNELS = [64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512]
TAPS = [1, 3, 6, 9, 12]


def uniform_bytes(count, bound, rng):
    # He-uniform-like values: the activations stay finite through 13 layers.
    return struct.pack(f"<{count}f", *(rng.uniform(-bound, bound) for _ in range(count)))


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    out = sys.argv[1]
    rng = random.Random(0)
    tensors = []
    cin = 3
    for i, cout in enumerate(CHANNELS):
        fan_in = cin * 9
        tensors.append((f"features.{i}.weight", [cout, cin, 3, 3],
                        uniform_bytes(cout * fan_in, (6 / fan_in) ** 0.5, rng)))
        tensors.append((f"features.{i}.bias", [cout], bytes(4 * cout)))
        cin = cout
    for k, i in enumerate(TAPS):
        c = CHANNELS[i]
        tensors.append((f"lin.{k}.weight", [1, c, 1, 1], struct.pack(f"<{c}f", *([1 / c] * c))))
    header, offset = {}, 0
    for name, shape, data in tensors:
        header[name] = {"dtype": "F32", "shape": shape, "data_offsets": [offset, offset + len(data)]}
        offset += len(data)
    head = json.dumps(header).encode()
    head += b" " * (-len(head) % 8)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out + ".tmp", "wb") as f:
        f.write(struct.pack("<Q", len(head)) + head)
        for _, _, data in tensors:
            f.write(data)
    os.replace(out + ".tmp", out)
    print(f"wrote {out}: random LPIPS VGG weights ({offset // 4} values), for timing only")


if __name__ == "__main__":
    main()
