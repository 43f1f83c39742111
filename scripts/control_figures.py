#!/usr/bin/env python3
"""Figures for the artist's controls (scripts/controls.sh): each run's test
renders against the photoreal field's, over the pixels that are not the
white background of both.

usage: control_figures.py PHOTO_RGB OUT RUN [RUN ...]
  PHOTO_RGB  the photoreal field's test renders (`refnpr render --path test`'s rgb/)
  OUT/RUN/test/rgb  each stylization's renders of the same views

Columns:
- colour: mean |RGB difference| to the photo (all of the stylization's change);
- chroma: mean distance of (Cb, Cr) (Cb ~ B - Y, Cr ~ R - Y, Rec. 601 Y): what
  `--preserve-colour` removes;
- luminance: mean |Y difference|: what `--preserve-colour` keeps;
- stroke period: the painting's pattern, as the luminance the stylization added
  (its Y minus the photo's, windowed) seen through its power spectrum: the
  wavelength in pixels of the spectrum's centroid (median over the views):
  the yardstick for `--stroke-scale`;
- at the reference: the same period of the run's render at the reference
  camera (OUT/RUN/reference_0.png) against the image the painting was made
  over (OUT/case/content.png), where the painting is told exactly.
"""
import os
import sys

import numpy as np
from PIL import Image


def load(path):
    return np.asarray(Image.open(path).convert("RGB")).astype(np.float64) / 255


def ycc(a):
    y = a @ [0.299, 0.587, 0.114]
    return y, np.stack([a[..., 2] - y, a[..., 0] - y], -1)


def stroke_period(residual):
    """The wavelength (pixels) of the power spectrum's centroid of `residual`."""
    h, w = residual.shape
    window = np.outer(np.hanning(h), np.hanning(w))
    r = (residual - residual.mean()) * window
    power = np.abs(np.fft.fftshift(np.fft.fft2(r))) ** 2
    fy, fx = np.meshgrid(np.fft.fftshift(np.fft.fftfreq(h)), np.fft.fftshift(np.fft.fftfreq(w)), indexing="ij")
    f = np.hypot(fy, fx)
    keep = (f > 0) & (f <= 0.5)
    centroid = (f[keep] * power[keep]).sum() / max(power[keep].sum(), 1e-12)
    return 1.0 / centroid


def main():
    photo_dir, out, runs = sys.argv[1], sys.argv[2], sys.argv[3:]
    names = sorted(n for n in os.listdir(photo_dir) if n.endswith(".png"))
    print("| run | colour | chroma | luminance | stroke period (px) | at the reference (px) | views |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    content_y, _ = ycc(load(os.path.join(out, "case", "content.png")))
    for run in runs:
        colour, chroma, luma, periods = [], [], [], []
        for n in names:
            p = load(os.path.join(photo_dir, n))
            s = load(os.path.join(out, run, "test", "rgb", n))
            both_white = (p > 0.99).all(-1) & (s > 0.99).all(-1)
            (yp, cp), (ys, cs) = ycc(p), ycc(s)
            colour.append(np.abs(s - p).mean(-1)[~both_white])
            chroma.append(np.linalg.norm(cs - cp, axis=-1)[~both_white])
            luma.append(np.abs(ys - yp)[~both_white])
            periods.append(stroke_period(ys - yp))
        mean = lambda parts: np.concatenate(parts).mean()
        at_reference = stroke_period(ycc(load(os.path.join(out, run, "reference_0.png")))[0] - content_y)
        print(
            f"| {run} | {mean(colour):.4f} | {mean(chroma):.4f} | {mean(luma):.4f} | {np.median(periods):.2f} "
            f"| {at_reference:.2f} | {len(names)} |"
        )


if __name__ == "__main__":
    main()
