#!/usr/bin/env python3
"""A local edit on the procedural scene, measured per object.

usage: scripts/local_edit_figures.py SCENE GRADED PHOTO STYLE OBJECTS [REFERENCE]
  SCENE     the `refnpr scene` folder (test/r_N.png, r_N_id.png, r_N_depth.npy)
  GRADED    `refnpr recolour --data SCENE --objects OBJECTS`: the intended result
  PHOTO     the photoreal run's test renders (`refnpr render --path test`: DIR/rgb/NNNN.png)
  STYLE     the stylized run's test renders (STYLE/test/rgb/NNNN.png)
  OBJECTS   the edited object ids, comma-separated (1 ground, 2 sphere, 3 box, 4 cylinder)
  REFERENCE the references' training view indices, comma-separated (default 0)

Prints, for each edited object, the PSNR of the stylized renders against
GRADED over the surfaces a reference sees and those none does (and the
photoreal renders' PSNR against GRADED beside them: what the edit has to
move); for every other object, the PSNR of the stylized renders against
the photoreal renders and the share of its pixels that are the same, to
the 8 bits of the PNG. A surface point counts as seen when the reference
camera's own depth there agrees with it within 2 % of its depth.
"""
import json
import sys

import numpy as np
from PIL import Image


def rgb(path):
    img = np.asarray(Image.open(path).convert("RGBA"), dtype=np.float64) / 255
    return img[..., :3] * img[..., 3:] + (1 - img[..., 3:])


def cameras(scene, split):
    meta = json.load(open(f"{scene}/transforms_{split}.json"))
    return meta["camera_angle_x"], [np.array(f["transform_matrix"], dtype=np.float64) for f in meta["frames"]]


def world_points(c2w, depth, focal):
    """The surface point of every pixel (depth: distance along the unit ray, 0 = miss)."""
    h, w = depth.shape
    x, y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = np.stack([(x - w / 2) / focal, -(y - h / 2) / focal, -np.ones_like(x)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return c2w[:3, 3] + depth[..., None] * (d @ c2w[:3, :3].T)


def seen_from(points, hit, ref_c2w, ref_depth, focal):
    """Whether the reference camera sees each point (in its frame, not occluded)."""
    h, w = ref_depth.shape
    q = (points - ref_c2w[:3, 3]) @ ref_c2w[:3, :3]
    z = -q[..., 2]
    front = hit & (z > 1e-6)
    zs = np.where(front, z, 1.0)
    u = np.round(focal * q[..., 0] / zs + w / 2 - 0.5).astype(int)
    v = np.round(-focal * q[..., 1] / zs + h / 2 - 0.5).astype(int)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    uc, vc = np.clip(u, 0, w - 1), np.clip(v, 0, h - 1)
    ref_points = world_points(ref_c2w, ref_depth, focal)[vc, uc]
    ref_z = -((ref_points - ref_c2w[:3, 3]) @ ref_c2w[:3, :3])[..., 2]
    return inside & (ref_depth[vc, uc] > 0) & (np.abs(ref_z - z) <= 0.02 * z)


def psnr(errors):
    e = np.concatenate(errors) if errors else np.array([])
    return (10 * np.log10(1 / max(e.mean(), 1e-10)), e.size) if e.size else (float("nan"), 0)


def main(scene, graded, photo, style, objects, reference="0"):
    edited = [int(o) for o in objects.split(",")]
    angle, test = cameras(scene, "test")
    _, train = cameras(scene, "train")
    refs = [(train[r], np.load(f"{scene}/train/r_{r}_depth.npy")) for r in map(int, reference.split(","))]
    focal = 0.5 * refs[0][1].shape[1] / np.tan(0.5 * angle)
    parts = {(o, k): [] for o in edited for k in ("seen", "unseen", "photo_seen", "photo_unseen")}
    others = {}
    for i, c2w in enumerate(test):
        ids = np.asarray(Image.open(f"{scene}/test/r_{i}_id.png"))
        depth = np.load(f"{scene}/test/r_{i}_depth.npy")
        stylized, photoreal = rgb(f"{style}/{i:04d}.png"), rgb(f"{photo}/{i:04d}.png")
        truth = rgb(f"{graded}/test/r_{i}.png")
        points = world_points(c2w, depth, focal)
        seen = np.any([seen_from(points, depth > 0, c, d, focal) for c, d in refs], axis=0)
        for o in edited:
            for name, mask in (("seen", (ids == o) & seen), ("unseen", (ids == o) & ~seen)):
                parts[o, name].append(((stylized - truth) ** 2).mean(-1)[mask])
                parts[o, "photo_" + name].append(((photoreal - truth) ** 2).mean(-1)[mask])
        for o in np.unique(ids):
            if o == 0 or o in edited:
                continue
            mask = ids == o
            err, same = others.setdefault(int(o), ([], []))
            err.append(((stylized - photoreal) ** 2).mean(-1)[mask])
            same.append(np.all(stylized == photoreal, -1)[mask])
    print("| edited object vs the intended result | surfaces | stylized | photoreal | pixels |")
    print("| --- | --- | --- | --- | --- |")
    for o in edited:
        for name in ("seen", "unseen"):
            (p, n), (q, _) = psnr(parts[o, name]), psnr(parts[o, "photo_" + name])
            print(f"| {o} | {name} by a reference | {p:.2f} dB | {q:.2f} dB | {n} |")
    print()
    print("| other object vs the photoreal renders | PSNR | same pixels (8 bits) |")
    print("| --- | --- | --- |")
    for o, (err, same) in sorted(others.items()):
        p, n = psnr(err)
        print(f"| {o} | {p:.2f} dB | {np.concatenate(same).mean() * 100:.1f} % of {n} |")


if __name__ == "__main__":
    if len(sys.argv) not in (6, 7):
        sys.exit(__doc__)
    main(*sys.argv[1:])
