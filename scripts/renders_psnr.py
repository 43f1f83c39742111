#!/usr/bin/env python3
"""PSNR between the test renders of two stylizations of the same views:
how far a shortcut (coarse epochs, coarse matches) moves the result from
the run it shortens. Prints the mean, lowest and highest over the views.

usage: scripts/renders_psnr.py RUN_A RUN_B
  RUN_A, RUN_B  `refnpr stylize` output folders (their test/rgb/NNNN.png)
"""
import glob
import os
import sys

import numpy as np
from PIL import Image


def load(path):
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255


def main(a, b):
    names = sorted(os.path.basename(p) for p in glob.glob(f"{a}/test/rgb/[0-9]*.png"))
    if not names:
        sys.exit(f"{a}/test/rgb holds no NNNN.png renders")
    psnrs = []
    for name in names:
        other = f"{b}/test/rgb/{name}"
        if not os.path.exists(other):
            sys.exit(f"{other} is missing: both runs must render the same test views")
        x, y = load(f"{a}/test/rgb/{name}"), load(other)
        if x.shape != y.shape:
            sys.exit(f"{name}: {x.shape[1]}x{x.shape[0]} in {a}, {y.shape[1]}x{y.shape[0]} in {b}")
        mse = max(float(np.mean((x - y) ** 2)), 1e-12)
        psnrs.append(10 * np.log10(1 / mse))
    print(f"{len(psnrs)} views: mean {np.mean(psnrs):.2f} dB (lowest {min(psnrs):.2f}, highest {max(psnrs):.2f})")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
