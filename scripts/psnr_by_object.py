#!/usr/bin/env python3
"""PSNR of a run's test renders against a procedural scene's test views,
split by the scene's object ids: the background (id 0, which the
`--environment` scene fills with its far environment) and the objects.

usage: scripts/psnr_by_object.py RUN SCENE [TRUTH]
  RUN    a `refnpr train` run folder (its test/NNNN.png renders) or a
         `refnpr stylize` one (test/rgb/NNNN.png)
  SCENE  the `refnpr scene` folder it was trained on (test/r_N.png, r_N_id.png)
  TRUTH  the views to compare with, when not SCENE's (SCENE/stylized for a
         stylization: its twin)
"""
import os
import sys

import numpy as np
from PIL import Image


def main(run, scene, truth_dir=None):
    truth_dir = truth_dir or scene
    renders = f"{run}/test/rgb" if os.path.isdir(f"{run}/test/rgb") else f"{run}/test"
    errors = {"background": [], "objects": [], "all": []}
    i = 0
    while True:
        try:
            render = np.asarray(Image.open(f"{renders}/{i:04d}.png").convert("RGB"), dtype=np.float64) / 255
        except FileNotFoundError:
            break
        truth = np.asarray(Image.open(f"{truth_dir}/test/r_{i}.png").convert("RGBA"), dtype=np.float64) / 255
        # Over white, as the Blender loader composites a transparent background.
        truth = truth[..., :3] * truth[..., 3:] + (1 - truth[..., 3:])
        ids = np.asarray(Image.open(f"{scene}/test/r_{i}_id.png"))
        squared = ((render - truth) ** 2).mean(-1)
        errors["background"].append(squared[ids == 0])
        errors["objects"].append(squared[ids != 0])
        errors["all"].append(squared.ravel())
        i += 1
    if i == 0:
        sys.exit(f"{renders}/0000.png: no test renders")
    total = np.concatenate(errors["all"]).sum()
    for part, e in errors.items():
        e = np.concatenate(e)
        share = e.sum() / total
        print(f"{part}: {10 * np.log10(1 / e.mean()):.2f} dB over {e.size} px, {share:.2f} of the squared error")


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    main(*sys.argv[1:])
