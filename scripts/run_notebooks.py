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

With --cargo-lock FILE, once the kernel has started and before the first
cell, FILE is copied into the kernel's build folder ($EVCXR_TMPDIR). evcxr
builds an empty crate when it starts, which leaves that folder a Cargo.lock
with no dependencies; the first cell's `:dep` would then resolve every
dependency afresh, to the newest versions on crates.io, and none of the
project's compiled dependencies would match. With the project's Cargo.lock
the notebooks' crate gets the project's versions, and reuses its build.
"""

import argparse
import copy
import os
import shutil
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


def execute(client, nb, cargo_lock):
    """What NotebookClient.execute does, with the lock put in place between
    the kernel's start and the first cell."""
    client.reset_execution_trackers()
    with client.setup_kernel():
        info = client.wait_for_reply(client.kc.kernel_info())
        if info is not None and "language_info" in info["content"]:
            nb.metadata["language_info"] = info["content"]["language_info"]
        if cargo_lock is not None:
            shutil.copyfile(cargo_lock, Path(os.environ["EVCXR_TMPDIR"]) / "Cargo.lock")
        for index, cell in enumerate(nb.cells):
            client.execute_cell(cell, index, execution_count=client.code_cells_executed + 1)


def run(path, write, timeout, cargo_lock):
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
        execute(client, nb, cargo_lock)
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
    ap.add_argument("--cargo-lock", type=Path, help="copied into $EVCXR_TMPDIR once the kernel has started")
    args = ap.parse_args()
    if args.cargo_lock is not None and "EVCXR_TMPDIR" not in os.environ:
        ap.error("--cargo-lock needs EVCXR_TMPDIR (the kernel's build folder)")
    ok = True
    times = []
    for path in args.notebooks:
        print(f"== {path}", flush=True)
        good, seconds = run(path, args.write, args.timeout, args.cargo_lock)
        times.append((path.name, seconds, good))
        print(f"   {'ok' if good else 'FAILED'} in {seconds:.0f} s", flush=True)
        ok &= good
    print("\nnotebook times:")
    for name, seconds, good in times:
        print(f"  {name:<28} {seconds:7.0f} s  {'ok' if good else 'FAILED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
