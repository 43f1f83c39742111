#!/usr/bin/env python3
"""How a stylization's parts grow with the image size: a plot and a table.

Usage:
  python3 scripts/growth_plot.py --out growth.png LABEL=OUT[:PHOTO] ...

OUT is a stylized run's folder (its stylize.json; a `refnpr stylize` or a
`refnpr bench-stylize`), PHOTO the photoreal run it stylized (its
metrics.json: the fit's time and peak). Each run contributes its
smooth-update steps (always at the views' own size, also under
--coarse-scale) split into their timed parts, the phases' wall times and
the peak memory. Writes the plot (needs matplotlib) and prints a markdown
table. A benchmark script for docs/performance.md, not a test.
"""
import argparse
import json
import sys
from pathlib import Path

# The smooth-update step's timed parts (stylize.json step_profiles), and
# what each is in the words of docs/performance.md.
PARTS = [
    ("view_samples", "march (the view's sample lists)"),
    ("image_render", "render (forward)"),
    ("image_losses_vgg", "VGG16 forward + backward, losses"),
    ("image_rerender_grad", "render (backward)"),
    ("reference_loss", "R³'s registered rays"),
]
PHASES = ["registration", "refit", "content", "image_epochs", "smooth_update"]


def gb(mib):
    """The reports' MB (MiB) as docs/performance.md quotes `/usr/bin/time -v`'s
    peak: its kilobytes (KiB) over a million."""
    return mib * 1024 / 1e6


def load_run(label, spec):
    out, _, photo = spec.partition(":")
    styl = json.loads((Path(out) / "stylize.json").read_text())
    w, h = styl["image_size"]
    profile = styl["step_profiles"].get("smooth_update") or []
    steps = next((p["calls"] for p in profile if p["part"] == "view_samples"), 0)
    parts = {p["part"]: p["seconds"] / steps for p in profile if steps}
    # The smooth update's own R³ and guides (at the views' size): its wall
    # time less its steps' timed parts.
    smooth_guides_s = styl["seconds"].get("smooth_update", 0.0) - sum(p["seconds"] for p in profile)
    run = {
        "label": label,
        "pixels": w * h,
        "size": f"{w}x{h}",
        "views": styl["views"],
        "coarse": styl["config"]["schedule"].get("coarse_scale", 1),
        "parts": parts,
        "phases": styl["seconds"],
        "guides_s": styl["seconds"].get("content", float("nan")),
        "smooth_guides_s": smooth_guides_s,
        "total_s": styl["total_seconds"],
        "peak_mb": styl["peak_rss_mb"],
    }
    if photo:
        metrics = json.loads((Path(photo) / "metrics.json").read_text())
        run["fit_s"] = metrics["train_seconds"]
        run["fit_peak_mb"] = metrics["peak_rss_mb"]
        run["fit_psnr"] = metrics["test_psnr"]
    return run


def table(runs):
    head = ["run", "view size", "views", "coarse"]
    head += [f"{name} (s a step)" for name, _ in PARTS]
    head += ["guides, epochs' size (s)", "smooth update's R³ + guides (s)"]
    head += ["stylize wall", "stylize peak", "fit wall", "fit peak"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for r in runs:
        cells = [r["label"], r["size"], str(r["views"]), str(r["coarse"])]
        cells += [f"{r['parts'].get(name, float('nan')):.3f}" for name, _ in PARTS]
        cells += [f"{r['guides_s']:.0f}", f"{r['smooth_guides_s']:.0f}"]
        cells += [f"{r['total_s'] / 60:.1f} min", f"{gb(r['peak_mb']):.2f} GB"]
        if "fit_s" in r:
            cells += [f"{r['fit_s'] / 60:.1f} min", f"{gb(r['fit_peak_mb']):.2f} GB"]
        else:
            cells += ["", ""]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(runs, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = sorted(runs, key=lambda r: r["pixels"])
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.8))
    px = [r["pixels"] / 1e3 for r in runs]
    for name, words in PARTS:
        # A part under a millisecond (a march the cache spared) is left off the log scale.
        secs = [r["parts"].get(name, float("nan")) for r in runs]
        left.plot(px, [t if t >= 1e-3 else float("nan") for t in secs], "o-", label=words)
    left.plot(px, [r["smooth_guides_s"] / r["views"] for r in runs], "s--",
              label="the smooth update's R³ + guides, a view")
    first = runs[0]["parts"].get("image_losses_vgg")
    if first:
        left.plot(px, [first * p / px[0] for p in px], "k:", label="proportional to the pixels")
    left.set(xscale="log", yscale="log", xlabel="pixels per view (thousands)",
             ylabel="seconds per smooth-update step (per view)", title="A step's parts at the views' own size")
    left.legend(fontsize=7)
    for x, r in zip(px, runs):
        left.annotate(r["label"], (x, r["parts"].get("image_losses_vgg", 1)), fontsize=6,
                      textcoords="offset points", xytext=(3, 6))
    total = [r["pixels"] * r["views"] / 1e6 for r in runs]
    right.plot(total, [gb(r["peak_mb"]) for r in runs], "o", label="stylization peak")
    fits = [(t, gb(r["fit_peak_mb"])) for t, r in zip(total, runs) if "fit_peak_mb" in r]
    if fits:
        right.plot(*zip(*fits), "s", label="photoreal fit peak")
    for t, r in zip(total, runs):
        right.annotate(r["label"], (t, gb(r["peak_mb"])), fontsize=6,
                       textcoords="offset points", xytext=(3, 4))
    right.set(xscale="log", xlabel="training pixels, all views (millions)", ylabel="GB",
              title="Peak memory")
    right.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="the plot to write (PNG)")
    ap.add_argument("runs", nargs="+", help="LABEL=OUT[:PHOTO]")
    args = ap.parse_args()
    runs = []
    for item in args.runs:
        label, eq, spec = item.partition("=")
        if not eq:
            sys.exit(f"growth_plot: '{item}' is not LABEL=OUT[:PHOTO]")
        try:
            runs.append(load_run(label, spec))
        except (OSError, KeyError, json.JSONDecodeError) as e:
            sys.exit(f"growth_plot: {item}: {e}")
    print(table(runs))
    if args.out:
        plot(runs, args.out)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
