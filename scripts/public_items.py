#!/usr/bin/env python3
"""Counts the public items a user of the library can reach: `pub` items
(fn, struct, enum, const, static, type, trait, mod, use; methods
included) in the files reachable from src/lib.rs through `pub mod`
declarations, `#[cfg(test)]` parts left out. `pub(crate)` modules and
everything in them do not count.

    python3 scripts/public_items.py [ROOT]      # ROOT: a checkout (default: this one)
"""
import pathlib
import re
import sys

ITEM = re.compile(r"^\s*pub (?:async |unsafe |const )*(fn|struct|enum|const|static|type|trait|mod|use|union) ")


def reachable(src):
    out, todo = [], [src / "lib.rs"]
    while todo:
        f = todo.pop()
        out.append(f)
        for m in re.finditer(r"^\s*pub mod (\w+);", f.read_text(), re.M):
            base = f.parent if f.name in ("lib.rs", "mod.rs") else f.parent / f.stem
            for candidate in (base / f"{m.group(1)}.rs", base / m.group(1) / "mod.rs"):
                if candidate.exists():
                    todo.append(candidate)
                    break
    return out


def main():
    root = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else pathlib.Path(__file__).resolve().parent.parent)
    total = 0
    for f in reachable(root / "src"):
        text = f.read_text().split("#[cfg(test)]")[0]
        total += sum(1 for line in text.split("\n") if ITEM.match(line))
    print(total)


if __name__ == "__main__":
    main()
