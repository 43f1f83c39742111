"""PSNR of a browser's screenshots against refnpr's renders of the same cameras.

    python3 compare.py SHOTS_DIR RENDER_DIR/rgb [--json OUT.json]

Each screenshot NNNN.png is compared with the render of the same name
(camera NNNN); prints the PSNR per view and the mean, and exits 1 when a
render is missing or differs in size.
"""
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image


def load(path):
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0


def main():
    args = sys.argv[1:]
    out = None
    if "--json" in args:
        i = args.index("--json")
        out = args[i + 1]
        del args[i : i + 2]
    shots, renders = map(Path, args)
    names = sorted(p.name for p in shots.glob("*.png"))
    if not names:
        sys.exit(f"error: no PNG screenshots in {shots}")
    psnrs = []
    for name in names:
        if not (renders / name).exists():
            sys.exit(f"error: {renders / name} is missing (refnpr rendered fewer views than the browser shot)")
        a, b = load(shots / name), load(renders / name)
        if a.shape != b.shape:
            sys.exit(f"error: {name}: the shot is {a.shape}, the render {b.shape}")
        mse = max(np.mean((a - b) ** 2), 1e-10)
        psnrs.append(10 * np.log10(1.0 / mse))
        print(f"{name}  {psnrs[-1]:.2f} dB")
    print(f"mean {np.mean(psnrs):.2f} dB over {len(psnrs)} views (min {min(psnrs):.2f}, max {max(psnrs):.2f})")
    if out:
        Path(out).write_text(json.dumps({"psnr": psnrs, "mean": float(np.mean(psnrs))}, indent=1))


if __name__ == "__main__":
    main()
