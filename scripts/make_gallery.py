#!/usr/bin/env python3
"""Builds the README gallery (assets/gallery/).

From a demo run:
    cargo run -- demo --out demo-out
    python3 -m pip install pillow && python3 scripts/make_gallery.py demo-out
writes demo_reference.png (photo at the reference view | the reference),
demo_novel_views.png (photoreal orbit frames above the stylized ones at the
same cameras), and the two orbit GIFs.

From two stylizations of one real scene (Ref-NPR and ARF, same case),
each rendered with `refnpr render --run RUN --path test|spiral --out RUN/test`:
    python3 scripts/make_gallery.py --scene lego CASE REFNPR_RUN ARF_RUN
writes lego_reference.png (content | reference), lego_test_views.png
(four of the Ref-NPR renders above ARF's at the same cameras) and both
GIFs (images and frames wider than GIF_WIDTH are halved, so a 504x378
spiral stays a few MB).

One row of images at half size (a reference beside a run's test views):
    python3 scripts/make_gallery.py --row NAME.png IMAGE...
writes assets/gallery/NAME.png. Several rows, one below the other (each
argument a comma-separated list of images; images wider than 256 px at half size):
    python3 scripts/make_gallery.py --rows NAME.png IMAGE,IMAGE... IMAGE,...
Rows of images all brought to WIDTH pixels wide (runs at two sizes side by side):
    python3 scripts/make_gallery.py --rows-at WIDTH NAME.png IMAGE,IMAGE... IMAGE,...
The same crop (X,Y,W,H in pixels) of each image, side by side, enlarged
FACTOR times pixel for pixel (strokes a pixel or two wide, as they are):
    python3 scripts/make_gallery.py --crop X,Y,W,H FACTOR NAME.png IMAGE...
"""
import shutil
import sys
from pathlib import Path

from PIL import Image

FRAMES = [5, 20, 35, 50]  # orbit frames shown as novel views
SCALE = 2                 # the demo renders 96x96: enlarge for the README
GIF_WIDTH = 320           # real-scene GIFs wider than this are halved


def on_white(path):
    im = Image.open(path).convert("RGBA")
    white = Image.new("RGBA", im.size, (255, 255, 255, 255))
    return Image.alpha_composite(white, im).convert("RGB")


def row(images):
    w, h = images[0].size
    out = Image.new("RGB", (w * len(images), h), (255, 255, 255))
    for i, im in enumerate(images):
        out.paste(im, (i * w, 0))
    return out


def column(images):
    w, h = images[0].size
    out = Image.new("RGB", (w, h * len(images)), (255, 255, 255))
    for i, im in enumerate(images):
        out.paste(im, (0, i * h))
    return out


def enlarge(im):
    return im.resize((im.width * SCALE, im.height * SCALE), Image.NEAREST)


def small(im):
    """Halves an image wider than GIF_WIDTH (a 504x378 fern frame)."""
    return im if im.width <= GIF_WIDTH else im.resize((im.width // 2, im.height // 2), Image.LANCZOS)


def scene_gallery(name, case, refnpr, arf, out):
    reference = row([small(on_white(case / "content.png")), small(on_white(case / "style.png"))])
    reference.save(out / f"{name}_reference.png")
    frames = sorted((refnpr / "test/rgb").glob("*.png"))
    picks = sorted({frames[i * len(frames) // 4].name for i in range(4)})
    top = row([small(on_white(refnpr / "test/rgb" / f)) for f in picks])
    bottom = row([small(on_white(arf / "test/rgb" / f)) for f in picks])
    column([top, bottom]).save(out / f"{name}_test_views.png")
    small_gif(refnpr / "test/path.gif", out / f"{name}_refnpr.gif")
    small_gif(arf / "test/path.gif", out / f"{name}_arf.gif")


def small_gif(src, dst):
    """Copies a GIF, halving its frames when it is wider than GIF_WIDTH."""
    gif = Image.open(src)
    if gif.width <= GIF_WIDTH:
        shutil.copy(src, dst)
        return
    frames, durations = [], []
    for i in range(gif.n_frames):
        gif.seek(i)
        frames.append(small(gif.convert("RGB")))
        durations.append(gif.info.get("duration", 40))
    frames[0].save(dst, save_all=True, append_images=frames[1:], duration=durations, loop=0)


def main():
    out = Path(__file__).resolve().parent.parent / "assets" / "gallery"
    out.mkdir(parents=True, exist_ok=True)
    if len(sys.argv) >= 4 and sys.argv[1] == "--row":
        images = [on_white(p) for p in sys.argv[3:]]
        row([im.resize((im.width // 2, im.height // 2), Image.LANCZOS) for im in images]).save(out / sys.argv[2])
        print(f"wrote {out / sys.argv[2]}")
        return
    if len(sys.argv) >= 4 and sys.argv[1] == "--rows":
        def fit(im):
            return im if im.width <= 256 else im.resize((im.width // 2, im.height // 2), Image.LANCZOS)

        rows = [row([fit(on_white(p)) for p in arg.split(",")]) for arg in sys.argv[3:]]
        column(rows).save(out / sys.argv[2])
        print(f"wrote {out / sys.argv[2]}")
        return
    if len(sys.argv) >= 5 and sys.argv[1] == "--rows-at":
        width = int(sys.argv[2])

        def at_width(im):
            return im.resize((width, im.height * width // im.width), Image.LANCZOS)

        rows = [row([at_width(on_white(p)) for p in arg.split(",")]) for arg in sys.argv[4:]]
        column(rows).save(out / sys.argv[3])
        print(f"wrote {out / sys.argv[3]}")
        return
    if len(sys.argv) >= 6 and sys.argv[1] == "--crop":
        x, y, w, h = (int(v) for v in sys.argv[2].split(","))
        factor = int(sys.argv[3])
        crops = [on_white(p).crop((x, y, x + w, y + h)) for p in sys.argv[5:]]
        row([c.resize((w * factor, h * factor), Image.NEAREST) for c in crops]).save(out / sys.argv[4])
        print(f"wrote {out / sys.argv[4]}")
        return
    if len(sys.argv) == 6 and sys.argv[1] == "--scene":
        scene_gallery(sys.argv[2], *(Path(a) for a in sys.argv[3:]), out)
        print(f"gallery written to {out}")
        return
    demo = Path(sys.argv[1] if len(sys.argv) > 1 else "demo-out")
    reference = row([on_white(demo / "scene/train/r_0.png"), on_white(demo / "case/style.png")])
    enlarge(reference).save(out / "demo_reference.png")
    photo = row([on_white(demo / f"orbit/rgb/{i:04}.png") for i in FRAMES])
    stylized = row([on_white(demo / f"stylized/orbit/rgb/{i:04}.png") for i in FRAMES])
    enlarge(column([photo, stylized])).save(out / "demo_novel_views.png")
    shutil.copy(demo / "orbit/path.gif", out / "demo_photo_orbit.gif")
    shutil.copy(demo / "stylized/orbit/path.gif", out / "demo_stylized_orbit.gif")
    print(f"gallery written to {out}")


if __name__ == "__main__":
    main()
