#!/usr/bin/env python3
"""LPIPS (v0.1, as the `lpips` package computes it) in numpy: the reference
`refnpr lpips` is checked against.

Written from the formula, not from any implementation: the images in [0, 1]
map to [-1, 1]; LPIPS's scaling layer subtracts shift [-0.030, -0.088,
-0.188] and divides by scale [0.458, 0.448, 0.450]; the network's five
feature maps (VGG16: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3; AlexNet:
its five ReLUs) are unit-normalised over channels (x / (||x|| + 1e-10)); the
squared difference of the two images' maps is weighted per channel by the
layer's linear head, summed over channels, averaged over positions, and the
five layers' values summed. Computed in float64 from the float32 weights of
models/lpips_weights.safetensors (made by models/make_lpips_weights.py; the
build makes it too).

RGBA images are composited over white, as `refnpr lpips` does by default.

Usage:
  python3 scripts/lpips_reference.py A.png B.png [--net vgg|alex]
  python3 scripts/lpips_reference.py --pairs PAIRS.txt [--net vgg|alex]
      (one "A.png B.png" pair a line; prints "A B distance" a line)
"""

import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
WEIGHTS = os.path.join(HERE, "..", "models", "lpips_weights.safetensors")
SHIFT = np.array([-0.030, -0.088, -0.188]).reshape(3, 1, 1)
SCALE = np.array([0.458, 0.448, 0.450]).reshape(3, 1, 1)
EPS = 1e-10


def read_safetensors(path):
    with open(path, "rb") as f:
        data = f.read()
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8:8 + n])
    header.pop("__metadata__", None)
    start = 8 + n
    out = {}
    for name, e in header.items():
        if e["dtype"] != "F32":
            sys.exit(f"lpips_reference: {path}: {name} is {e['dtype']}, expected F32")
        b, end = e["data_offsets"]
        out[name] = np.frombuffer(data[start + b:start + end], dtype="<f4").reshape(e["shape"]).astype(np.float64)
    return out


def read_image(path):
    from PIL import Image
    img = Image.open(path)
    if img.mode in ("I;16", "I;16B", "I"):
        sys.exit(f"lpips_reference: {path}: 16-bit images are not supported here")
    rgba = np.asarray(img.convert("RGBA"), dtype=np.float64) / 255.0
    a = rgba[..., 3:4]
    rgb = rgba[..., :3] * a + 1.0 * (1.0 - a)
    return rgb.transpose(2, 0, 1)  # [3, H, W]


def conv(x, w, b, stride=1, pad=1):
    """2-D convolution of x [C, H, W] with w [O, C, k, k] and bias b [O] (zero padding)."""
    c, _, _ = x.shape
    k = w.shape[2]
    xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    win = np.lib.stride_tricks.sliding_window_view(xp, (k, k), axis=(1, 2))[:, ::stride, ::stride]
    _, oh, ow, _, _ = win.shape
    cols = win.transpose(1, 2, 0, 3, 4).reshape(oh * ow, c * k * k)
    out = cols @ w.reshape(w.shape[0], -1).T + b
    return out.T.reshape(w.shape[0], oh, ow)


def max_pool(x, k, stride):
    win = np.lib.stride_tricks.sliding_window_view(x, (k, k), axis=(1, 2))[:, ::stride, ::stride]
    return win.max(axis=(3, 4))


def relu(x):
    return np.maximum(x, 0.0)


def vgg_features(x, wts):
    out = []
    taps = {2, 4, 7, 10, 13}
    for i in range(1, 14):
        if i in (3, 5, 8, 11):
            x = max_pool(x, 2, 2)
        x = relu(conv(x, wts[f"vgg.conv{i}.weight"], wts[f"vgg.conv{i}.bias"]))
        if i in taps:
            out.append(x)
    return out


def alex_features(x, wts):
    out = []
    geometry = [(4, 2), (1, 2), (1, 1), (1, 1), (1, 1)]  # (stride, padding) of conv 1..5
    for i, (stride, pad) in enumerate(geometry, start=1):
        if i in (2, 3):
            x = max_pool(x, 3, 2)
        w, b = wts[f"alex.conv{i}.weight"], wts[f"alex.conv{i}.bias"]
        x = relu(conv(x, w, b, stride, pad))
        out.append(x)
    return out


def lpips(a, b, net, wts):
    if a.shape != b.shape:
        sys.exit(f"lpips_reference: images of different sizes {a.shape[1:]} and {b.shape[1:]}")
    features = vgg_features if net == "vgg" else alex_features
    fa = features(((2 * a - 1) - SHIFT) / SCALE, wts)
    fb = features(((2 * b - 1) - SHIFT) / SCALE, wts)
    total = 0.0
    for k, (x, y) in enumerate(zip(fa, fb)):
        nx = x / (np.sqrt((x * x).sum(axis=0, keepdims=True)) + EPS)
        ny = y / (np.sqrt((y * y).sum(axis=0, keepdims=True)) + EPS)
        d = (nx - ny) ** 2
        total += float(np.tensordot(wts[f"{net}.lin{k}"], d, axes=(0, 0)).mean())
    return total


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("images", nargs="*")
    ap.add_argument("--pairs")
    ap.add_argument("--net", choices=["vgg", "alex"], default="vgg")
    ap.add_argument("--weights", default=WEIGHTS)
    args = ap.parse_args()
    if not os.path.exists(args.weights):
        sys.exit(f"lpips_reference: {args.weights} is missing: run python3 models/make_lpips_weights.py")
    wts = read_safetensors(args.weights)
    if args.pairs:
        with open(args.pairs) as f:
            pairs = [line.split() for line in f if line.strip()]
        for a, b in pairs:
            print(f"{a} {b} {lpips(read_image(a), read_image(b), args.net, wts):.8f}", flush=True)
    elif len(args.images) == 2:
        print(f"{lpips(read_image(args.images[0]), read_image(args.images[1]), args.net, wts):.8f}")
    else:
        ap.error("give two images, or --pairs FILE")


if __name__ == "__main__":
    main()
