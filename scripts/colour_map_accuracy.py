#!/usr/bin/env python3
"""How well a reference's colour map predicts a graded scene, without a stylization.

    colour_map_accuracy.py CASE PHOTOS TRUTH ANGLES [SIGMA:PRIOR_PIXELS:PRIOR ...]

Fits the colour map as `ColourMap::fit` does (src/stylize/colour_map.rs: 16
bins a channel, Gaussian mixing of width SIGMA, PRIOR_PIXELS of the prior,
PRIOR "unchanged" or "affine") on CASE/content.png and CASE/style.png, applies
it to every test photo of the dataset folder PHOTOS (its transforms_test.json
order) and prints the PSNR against the same view of TRUTH (`refnpr recolour`'s
folder), for the views within 45 degrees of the reference and the others.
ANGLES is an `eval.json` of a run on that case (`gt_views[].angle`). A fast
scan of the map's settings on true photos: a stylization applies the map to
the refit field's renders instead. Needs numpy and Pillow.
"""

import json
import sys

import numpy as np
from PIL import Image

BINS = 16


def load(path):
    """RGB in [0, 1], transparent pixels composited on white, one row a pixel."""
    a = np.asarray(Image.open(path).convert("RGBA"), dtype=np.float64) / 255.0
    return (a[..., :3] * a[..., 3:] + (1.0 - a[..., 3:])).reshape(-1, 3)


def background(c):
    return np.abs(c - 1.0).max(axis=1) < 1.5 / 255.0


def fit(content, style, sigma, prior_pixels, prior):
    """The offsets at the bin centres, `[BINS, BINS, BINS, 3]`."""
    scene = ~background(content)
    c, s = content[scene], style[scene]
    idx = np.minimum((np.clip(c, 0, 1) * BINS).astype(int), BINS - 1)
    flat = (idx[:, 0] * BINS + idx[:, 1]) * BINS + idx[:, 2]
    sums, counts = np.zeros((BINS**3, 3)), np.zeros(BINS**3)
    np.add.at(sums, flat, s - c)
    np.add.at(counts, flat, 1.0)
    i = np.arange(BINS**3)
    centres = (np.stack([i // (BINS * BINS), (i // BINS) % BINS, i % BINS], -1) + 0.5) / BINS
    filled = np.nonzero(counts)[0]
    w = np.exp(-((centres[:, None, :] - centres[None, filled, :]) ** 2).sum(-1) / (2 * sigma * sigma))
    prior_offset = np.zeros_like(centres)
    if prior == "affine":
        x = np.concatenate([c, np.ones((len(c), 1))], 1)
        a = np.linalg.solve(x.T @ x, x.T @ s)
        prior_offset = np.clip(np.concatenate([centres, np.ones((len(centres), 1))], 1) @ a, 0, 1) - centres
    offsets = (w @ sums[filled] + prior_pixels * prior_offset) / (prior_pixels + w @ counts[filled])[:, None]
    return offsets.reshape(BINS, BINS, BINS, 3)


def apply(offsets, c):
    """`ColourMap::apply`: trilinear between bin centres, background kept."""
    pos = np.clip(np.clip(c, 0, 1) * BINS - 0.5, 0, BINS - 1)
    lo = np.minimum(np.floor(pos).astype(int), BINS - 2)
    t = pos - lo
    off = np.zeros_like(c)
    for corner in range(8):
        bits = [(corner >> (2 - k)) & 1 for k in range(3)]
        weight = np.prod([t[:, k] if bits[k] else 1 - t[:, k] for k in range(3)], axis=0)
        off += weight[:, None] * offsets[lo[:, 0] + bits[0], lo[:, 1] + bits[1], lo[:, 2] + bits[2]]
    out = np.clip(c + off, 0, 1)
    out[background(c)] = c[background(c)]
    return out


def main():
    if len(sys.argv) < 5:
        sys.exit(__doc__)
    case, photos, truth, angles_json = sys.argv[1:5]
    settings = sys.argv[5:] or ["0.08:4:unchanged"]
    angles = [v["angle"] for v in json.load(open(angles_json))["gt_views"]]
    frames = json.load(open(f"{photos}/transforms_test.json"))["frames"]
    views = [(a, load(f"{photos}/{f['file_path']}.png"), load(f"{truth}/{f['file_path']}.png"))
             for a, f in zip(angles, frames)]
    content, style = load(f"{case}/content.png"), load(f"{case}/style.png")
    for setting in settings:
        sigma, prior_pixels, prior = setting.split(":")
        offsets = fit(content, style, float(sigma), float(prior_pixels), prior)
        near, far = [], []
        for angle, photo, graded in views:
            (near if angle <= 45 else far).append(((apply(offsets, photo) - graded) ** 2).mean())
        psnr = lambda mses: -10 * np.log10(np.mean(mses))
        print(f"sigma {sigma}, {prior_pixels} prior pixels, {prior}: near {psnr(near):.2f} dB, far {psnr(far):.2f} dB")


if __name__ == "__main__":
    main()
