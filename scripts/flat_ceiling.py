#!/usr/bin/env python3
"""The best a flat colour per object can score against a procedural
scene's stylized twin: each object's exact mean stylized colour over the
test views' surface pixels, as PSNR over those pixels.

usage: scripts/flat_ceiling.py SCENE   (a `refnpr scene` folder)

The twin re-textures every object with another pattern, so on a surface
the reference does not see no method can know the pattern's phase: this
figure bounds what any colour mapping can reach there.
"""
import glob, sys
import numpy as np
from PIL import Image

root = sys.argv[1]
views = []
for ids_path in sorted(glob.glob(f"{root}/test/r_*_id.png")):
    i = ids_path.rsplit("/", 1)[1].split("_")[1]
    ids = np.asarray(Image.open(ids_path))
    rgb = np.asarray(Image.open(f"{root}/stylized/test/r_{i}.png").convert("RGB"), dtype=np.float64) / 255.0
    views.append((ids, rgb))
if not views:
    sys.exit(f"{root}/test has no r_*_id.png: not a procedural scene")
objects = sorted({int(o) for ids, _ in views for o in np.unique(ids) if o != 0})
means = {o: np.concatenate([rgb[ids == o] for ids, rgb in views]).mean(axis=0) for o in objects}
err = sum(((rgb[ids == o] - means[o]) ** 2).sum() for ids, rgb in views for o in objects)
count = sum((ids != 0).sum() * 3 for ids, _ in views)
print(f"{root}: each object's mean stylized colour scores {-10 * np.log10(err / count):.2f} dB over the test views' surfaces")
