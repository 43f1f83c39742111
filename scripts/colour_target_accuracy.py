#!/usr/bin/env python3
"""How close L_color's targets are to a ground truth, next to how close
stylized fields' renders get on the same patches.

usage: scripts/colour_target_accuracy.py RUN/colour_targets.json GT_TRAIN_DIR [NAME=RENDER_DIR ...]

RUN/colour_targets.json is written by `refnpr stylize` (Ref-NPR with the
colour loss); GT_TRAIN_DIR holds the ground truth of the training views
(a procedural scene's stylized/train, r_<view>.png, composited over the
background given by BACKGROUND="r,g,b", default white); each RENDER_DIR
holds `refnpr render --path train` frames (rgb/0000.png ...). Prints, over
the supervised 16x16 patches, the PSNR of the patch means against the
ground truth's: of the targets, and of each run's renders (for the renders
also over all patches), split into the reference views and the others
(REFERENCE_VIEWS="0" by default). With ID_DIR (a procedural scene's
train folder, r_<view>_id.png object ids), also the share of supervised
targets taken from a reference patch of another object (majority ids;
one reference, the first of REFERENCE_VIEWS) and the targets' PSNR split
by that.
"""
import json, os, sys
import numpy as np
from PIL import Image

PATCH = 16  # records written before `patch` was recorded are relu5 patches

def load(path, background):
    a = np.asarray(Image.open(path).convert("RGBA"), dtype=np.float64) / 255.0
    return a[..., :3] * a[..., 3:] + background * (1.0 - a[..., 3:])

def patch_means(img, cols, rows, patch=PATCH):
    img = img[: rows * patch, : cols * patch]
    return img.reshape(rows, patch, cols, patch, 3).mean(axis=(1, 3)).reshape(-1, 3)

def majority_ids(path, cols, rows, patch=PATCH):
    ids = np.asarray(Image.open(path))[: rows * patch, : cols * patch]
    blocks = ids.reshape(rows, patch, cols, patch).transpose(0, 2, 1, 3).reshape(rows * cols, -1)
    return np.array([np.bincount(b).argmax() for b in blocks])

def psnr(a, b):
    mse = float(np.mean((a - b) ** 2)) if len(a) else float("nan")
    return 10 * np.log10(1.0 / mse) if mse > 0 else float("inf")

def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    records = json.load(open(sys.argv[1]))
    gt_dir = sys.argv[2]
    runs = [a.split("=", 1) for a in sys.argv[3:]]
    background = np.array([float(x) for x in os.environ.get("BACKGROUND", "1,1,1").split(",")])
    refs = {int(v) for v in os.environ.get("REFERENCE_VIEWS", "0").split(",")}
    groups = {"reference views": [], "other views": []}
    for r in records:
        groups["reference views" if r["view"] in refs else "other views"].append(r)
    for name, recs in groups.items():
        if not recs:
            continue
        tgt, gt_sup, gt_all = [], [], []
        run_sup = {n: [] for n, _ in runs}
        run_all = {n: [] for n, _ in runs}
        for r in recs:
            cols, rows = r["positions"]
            gt = patch_means(load(f"{gt_dir}/r_{r['view']}.png", background), cols, rows, r.get("patch", PATCH))
            sup = np.array([t is not None for t in r["targets"]])
            tgt += [t for t in r["targets"] if t is not None]
            gt_sup.append(gt[sup])
            gt_all.append(gt)
            for n, d in runs:
                p = patch_means(load(f"{d}/rgb/{r['view']:04d}.png", background), cols, rows, r.get("patch", PATCH))
                run_sup[n].append(p[sup])
                run_all[n].append(p)
        gt_sup, gt_all = np.concatenate(gt_sup), np.concatenate(gt_all)
        tgt = np.array(tgt)
        print(f"{name}: {len(recs)} views, {len(gt_sup)} of {len(gt_all)} patches supervised")
        print(f"  targets vs ground truth (supervised patches): {psnr(tgt, gt_sup):.2f} dB")
        id_dir = os.environ.get("ID_DIR")
        if id_dir:
            ref = min(refs)
            cols, rows = recs[0]["positions"]
            ref_ids = majority_ids(f"{id_dir}/r_{ref}_id.png", cols, rows)
            same = []
            for r in recs:
                ids = majority_ids(f"{id_dir}/r_{r['view']}_id.png", *r["positions"], r.get("patch", PATCH))
                same += [ids[i] == ref_ids[s] for i, s in enumerate(r["sources"]) if s is not None]
            same = np.array(same)
            print(f"  targets from a reference patch of the same object: {100 * same.mean():.1f} %"
                  f" ({psnr(tgt[same], gt_sup[same]):.2f} dB); of another object: {100 * (1 - same.mean()):.1f} %"
                  f" ({psnr(tgt[~same], gt_sup[~same]):.2f} dB)")
        for n, _ in runs:
            s, a = np.concatenate(run_sup[n]), np.concatenate(run_all[n])
            print(f"  {n}: supervised patches {psnr(s, gt_sup):.2f} dB, all patches {psnr(a, gt_all):.2f} dB")

if __name__ == "__main__":
    main()
