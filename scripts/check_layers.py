#!/usr/bin/env python3
"""The layering check of the test command: imports only point down.

The stage order is the table of `src/lib.rs`'s map (its first column, top to
bottom: the lowest stage first). A module may use its own stage and the
stages above it in that table, never a later one; and the files of one stage
may not import each other in a cycle. Every `crate::` path counts: `use`
lines, grouped imports and paths written inline.

    python3 scripts/check_layers.py          # prints the order and the imports per stage; exits 1 on a violation
"""
import pathlib
import re
import sys

SRC = pathlib.Path(__file__).resolve().parent.parent / "src"


def stage_order():
    rows = re.findall(r"^//! \| `(\w+)` \|", (SRC / "lib.rs").read_text(), re.M)
    if not rows:
        sys.exit("error: no stage table in src/lib.rs (rows like '//! | `util` | ... |')")
    return rows


def crate_paths(text):
    """Every `crate::a::b` path of a file, grouped imports expanded (`crate::{a, b::c}`)."""
    text = re.sub(r"//.*", "", text)
    text = re.sub(r'"([^"\\]|\\.)*"', '""', text)
    paths = []
    for m in re.finditer(r"\bcrate::(\{[^;]*?\}|\w+(?:::\w+)*)", text, re.S):
        body = m.group(1)
        if body.startswith("{"):
            paths += [p.strip() for p in re.split(r",(?![^{]*\})", body[1:-1]) if p.strip()]
        else:
            paths.append(body)
    return paths


def module_of(path):
    """(stage, file module) of a source file: `src/field/view.rs` -> ("field", "view")."""
    parts = path.relative_to(SRC).with_suffix("").parts
    if len(parts) == 1:
        return parts[0], parts[0]
    return parts[0], parts[1]


def is_file_module(stage, name):
    """Whether `crate::stage::name` is a file of that stage (not an item of its mod.rs)."""
    return (SRC / stage / f"{name}.rs").exists() or (SRC / stage / name / "mod.rs").exists()


def main():
    order = stage_order()
    rank = {m: i for i, m in enumerate(order)}
    errors, uses, edges = [], {m: set() for m in order}, {}
    for path in sorted(SRC.rglob("*.rs")):
        stage, file_mod = module_of(path)
        if stage not in rank:
            continue  # lib.rs, bin/: above every stage
        for p in crate_paths(path.read_text()):
            target = re.split(r"::|\{", p)[0].strip()
            if target not in rank:
                continue
            if rank[target] > rank[stage]:
                errors.append(f"{path.relative_to(SRC.parent)}: stage `{stage}` imports the later stage `{target}` (crate::{p})")
            elif target != stage:
                uses[stage].add(target)
            else:
                inner = p.split("::")[1] if "::" in p else None
                if inner and inner != file_mod and is_file_module(stage, inner):
                    edges.setdefault((stage, file_mod), set()).add((stage, inner))
    # Cycles between the files of one stage (depth-first search).
    state = {}

    def visit(node, trail):
        state[node] = "open"
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == "open":
                cycle = trail[trail.index(nxt):] + [nxt] if nxt in trail else [node, nxt]
                errors.append("files import each other: " + " -> ".join(f"{s}/{f}" for s, f in cycle))
            elif nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = "done"

    for node in sorted(edges):
        if node not in state:
            visit(node, [node])
    print("stage order (src/lib.rs):", " < ".join(order))
    for m in order:
        print(f"  {m:10} uses {', '.join(sorted(uses[m], key=rank.get)) or '-'}")
    if errors:
        print("\n".join(["layering errors:"] + errors), file=sys.stderr)
        sys.exit(1)
    print("layering: every import points down; no file cycles inside a stage")


if __name__ == "__main__":
    main()
