#!/usr/bin/env python3
"""Writes tests/fixtures/lpips/: two synthetic images (a smooth colour field
with edges, and the same with a hue shift, a blur and a stroke) and their
LPIPS distances from scripts/lpips_reference.py (numpy, float64), for
tests/evaluation.rs to check the Burn metric against on every backend.

Usage: python3 models/make_lpips_fixtures.py   (needs numpy and Pillow, and
models/lpips_weights.safetensors, which the build makes)
"""
import json
import os
import subprocess
import sys

import numpy as np
from PIL import Image

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "..", "tests", "fixtures", "lpips")
W, H = 64, 48


def base():
    y, x = np.mgrid[0:H, 0:W] / np.array([H, W]).reshape(2, 1, 1)
    r = 0.5 + 0.4 * np.sin(6 * x + 2 * y)
    g = 0.5 + 0.4 * np.cos(5 * y - 3 * x)
    b = np.where((x - 0.5) ** 2 + (y - 0.5) ** 2 < 0.08, 0.9, 0.2)
    return np.stack([r, g, b], axis=-1)


def edited(img):
    out = img[..., [1, 2, 0]] * 0.8 + 0.1
    out = (out + np.roll(out, 1, axis=0) + np.roll(out, 1, axis=1)) / 3
    out[20:24, 8:56] = [0.95, 0.9, 0.1]
    return out


def save(img, name):
    Image.fromarray(np.round(np.clip(img, 0, 1) * 255).astype(np.uint8), "RGB").save(os.path.join(OUT, name))


def main():
    os.makedirs(OUT, exist_ok=True)
    a = base()
    save(a, "a.png")
    save(edited(a), "b.png")
    values = {}
    for net in ["vgg", "alex"]:
        script = os.path.join(HERE, "..", "scripts", "lpips_reference.py")
        r = subprocess.run([sys.executable, script, os.path.join(OUT, "a.png"), os.path.join(OUT, "b.png"),
                            "--net", net], capture_output=True, text=True, check=True)
        values[net] = float(r.stdout.strip())
    with open(os.path.join(OUT, "distances.json"), "w") as f:
        json.dump({"made_by": "models/make_lpips_fixtures.py (scripts/lpips_reference.py, numpy float64)",
                   "a": "a.png", "b": "b.png", **values}, f, indent=2)
        f.write("\n")
    print(values)


if __name__ == "__main__":
    main()
