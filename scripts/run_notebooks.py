#!/usr/bin/env python3
"""Executes notebooks with the evcxr (Rust) Jupyter kernel, headless.

    run_notebooks.py [--write] NOTEBOOK...

Each notebook runs top to bottom in its own folder. It fails on:
- a cell that does not compile or panics (nbclient stops there);
- a cell that prints to stderr: evcxr reports an error returned by `?` that
  way, not as a cell error, and carries on (its text may land in the next
  cell: evcxr forwards output on its own thread);
- a cell whose committed outputs hold a picture (PNG or SVG) or a table
  (HTML) that yields none on re-execution.
With --write the executed notebook (outputs included) replaces the file:
that is how the committed outputs are made. Prints each notebook's time.
"""

import argparse
import copy
import sys
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError

RICH = {"image/png": "a PNG picture", "image/svg+xml": "an SVG plot", "text/html": "an HTML table"}


def kinds(cell):
    """The rich output kinds a code cell shows."""
    found = set()
    for out in cell.get("outputs", []):
        for mime in out.get("data", {}):
            if mime in RICH:
                found.add(mime)
    return found


def failed(cell):
    return any(o.get("output_type") == "error" for o in cell.get("outputs", [])) or any(
        o.get("output_type") == "stream" and o.get("name") == "stderr" for o in cell.get("outputs", [])
    )


def shown(cell):
    """What a failed cell printed: its streams and its error (evcxr puts compile errors there)."""
    parts = []
    for o in cell.get("outputs", []):
        if o.get("output_type") == "stream":
            parts.append(o.get("text", ""))
        elif o.get("output_type") == "error":
            parts.append(f"{o.get('ename', '')}: {o.get('evalue', '')}\n" + "\n".join(o.get("traceback", [])))
    return "".join(parts)


def source(cell):
    text = "".join(cell["source"]) if isinstance(cell["source"], list) else cell["source"]
    return text.strip().splitlines()[0] if text.strip() else ""


def run(path, write, timeout):
    nb = nbformat.read(path, as_version=4)
    committed = copy.deepcopy(nb)
    client = NotebookClient(
        nb,
        timeout=timeout,
        kernel_name="rust",
        resources={"metadata": {"path": str(path.parent)}},
        allow_errors=False,
    )
    started = time.time()
    try:
        client.execute()
    except CellExecutionError as e:
        print(f"FAIL {path}: a cell failed:\n{e}", file=sys.stderr)
        for i, cell in enumerate(nb.cells):
            if cell.cell_type == "code" and failed(cell):
                print(f"cell {i} printed:\n{shown(cell)}", file=sys.stderr)
        return False, time.time() - started
    seconds = time.time() - started
    problems = []
    for i, (before, after) in enumerate(zip(committed.cells, nb.cells)):
        if after.cell_type != "code":
            continue
        if failed(after):
            problems.append(f"cell {i} ({source(after)!r}) failed:\n{shown(after)}")
        missing = kinds(before) - kinds(after)
        for mime in sorted(missing):
            problems.append(f"cell {i} ({source(after)!r}) showed {RICH[mime]} and now shows none")
    for p in problems:
        print(f"FAIL {path}: {p}", file=sys.stderr)
    if write and not problems:
        nbformat.write(nb, path)
    return not problems, seconds


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("notebooks", nargs="+", type=Path)
    ap.add_argument("--write", action="store_true", help="save the executed outputs into the notebooks")
    ap.add_argument("--timeout", type=int, default=3600, help="seconds a cell may run (the first compiles the crate)")
    args = ap.parse_args()
    ok = True
    times = []
    for path in args.notebooks:
        print(f"== {path}", flush=True)
        good, seconds = run(path, args.write, args.timeout)
        times.append((path.name, seconds, good))
        print(f"   {'ok' if good else 'FAILED'} in {seconds:.0f} s", flush=True)
        ok &= good
    print("\nnotebook times:")
    for name, seconds, good in times:
        print(f"  {name:<28} {seconds:7.0f} s  {'ok' if good else 'FAILED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
