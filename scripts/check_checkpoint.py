"""A refnpr checkpoint read without refnpr: Python's `safetensors` and numpy.

    python3 scripts/check_checkpoint.py RUN/checkpoint.bin [...]

Checks the metadata (format, version, the run's metadata as JSON), that the
arrays agree with it (rows, SH width from the SH degree, coordinates inside
the lattice) and are finite, and the far background's map, when there is one
(`far`, [height, width, 3], colours in [0, 1]); prints what a script would use. Exits 1 on a failure.
"""
import json
import sys

import numpy as np
from safetensors import safe_open
from safetensors.numpy import load_file


def check(path):
    with safe_open(path, "np") as f:
        metadata = f.metadata()
    if metadata.get("format") != "refnpr-checkpoint":
        sys.exit(f"error: {path}: metadata format {metadata.get('format')!r}")
    meta = json.loads(metadata["meta"])
    t = load_file(path)
    coords, density, sh = t["coords"], t["density"], t["sh"]
    rows = len(coords)
    res = meta["geometry"]["res"]
    basis = (meta["sh_degree"] + 1) ** 2
    problems = []
    if coords.dtype != np.uint32 or density.dtype != np.float32 or sh.dtype != np.float32:
        problems.append("dtypes")
    if density.shape != (rows, 1) or sh.shape != (rows, 3 * basis):
        problems.append(f"shapes {density.shape} {sh.shape} for {rows} rows of SH degree {meta['sh_degree']}")
    if rows and int(coords.max()) >= int(np.prod(res)):
        problems.append("a coordinate outside the lattice")
    if not (np.isfinite(density).all() and np.isfinite(sh).all()):
        problems.append("non-finite values")
    for name in ("opt_density", "opt_sh"):
        if t[name].shape[0] not in (0, rows):
            problems.append(f"{name} has {t[name].shape[0]} rows")
    far = ""
    if "far" in t:
        f = t["far"]
        if f.dtype != np.float32 or f.ndim != 3 or f.shape[2] != 3 or not np.isfinite(f).all():
            problems.append(f"far background {f.dtype} {f.shape}")
        elif f.min() < 0 or f.max() > 1:
            problems.append(f"far background colours {f.min():.3g}..{f.max():.3g} outside [0, 1]")
        far = f", far background {f.shape[1]}x{f.shape[0]} texels, colours {f.min():.3g}..{f.max():.3g}"
    occupied = np.unravel_index(coords.astype(np.int64), res)
    print(f"{path}: step {meta['step']}, {rows} rows of {np.prod(res)} lattice points {res}, SH degree "
          f"{meta['sh_degree']}, densities {density.min():.3g}..{density.max():.3g}, "
          f"occupied x {occupied[0].min()}..{occupied[0].max()}{far}")
    if problems:
        sys.exit(f"error: {path}: " + "; ".join(problems))


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    for p in sys.argv[1:]:
        check(p)
