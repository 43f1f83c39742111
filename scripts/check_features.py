#!/usr/bin/env python3
"""The dependencies must be compiled with the same features by `cargo test`
(which adds the dev-dependencies' features) and by a plain build (the binary,
the notebooks' evcxr build); otherwise a cold CI run compiles Burn, and
everything above the crate whose features differ, twice.

Reads `cargo tree` with and without the dev-dependencies, tells crates built
for the target from those built for the build host (proc-macros, build
scripts and their dependencies), and compares each crate's features in both
trees. A crate only the dev-dependencies bring is fine. Fix a difference by
naming the feature in Cargo.toml's feature pins: [dependencies] for the
target, [build-dependencies] for the host.

Usage: python3 scripts/check_features.py
"""

import collections
import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LINE = re.compile(r"^(?P<indent>(?:[│ ] {3}|[├└]── )*)(?P<text>.*)$")
PACKAGE = re.compile(r"^(?P<id>\S+ v\S+)(?P<notes>(?: \([^)]*\))*) \[(?P<features>[^\]]*)\]")


def target_triple():
    triple = os.environ.get("CARGO_BUILD_TARGET")
    if triple:
        return triple
    out = subprocess.run(["rustc", "-vV"], capture_output=True, text=True, check=True).stdout
    return next(line.split(": ")[1] for line in out.splitlines() if line.startswith("host: "))


def features(edges):
    """(where it is built, crate and version) -> its feature sets in the tree."""
    out = subprocess.run(
        ["cargo", "tree", "--locked", "--target", target_triple(), "-e", edges, "-f", "{p} [{f}]"],
        cwd=ROOT, capture_output=True, text=True, check=True).stdout
    found = collections.defaultdict(set)
    # host[d]: whether the package at depth d (or a section above it) builds for the host.
    host = {}
    section_host = {}
    for raw in out.splitlines():
        m = LINE.match(raw)
        depth = len(m.group("indent")) // 4
        text = m.group("text").strip()
        if text.startswith("["):
            # A section of the package at `depth` - 1 ("[build-dependencies]"); its children are at `depth` + 1.
            section_host[depth + 1] = text == "[build-dependencies]" or host.get(depth - 1, False)
            continue
        p = PACKAGE.match(text)
        if not p:
            continue
        parent_host = section_host.get(depth, host.get(depth - 1, False)) if depth else False
        is_host = parent_host or "(proc-macro)" in p.group("notes")
        host[depth] = is_host
        # Sections opened under a shallower package no longer apply below a new sibling.
        for d in [d for d in section_host if d > depth]:
            del section_host[d]
        found[("host" if is_host else "target", p.group("id"))].add(p.group("features"))
    return found


def main():
    plain = features("normal,build")
    with_dev = features("normal,build,dev")
    bad = [(key, plain[key], with_dev[key]) for key in sorted(set(plain) & set(with_dev))
           if plain[key] != with_dev[key]]
    if bad:
        print("check_features: these crates get other features under `cargo test` than in a plain build:",
              file=sys.stderr)
        for (where, crate), a, b in bad:
            print(f"  {crate} (built for the {where}): plain {sorted(a)}, with the dev-dependencies {sorted(b)}",
                  file=sys.stderr)
        print("Name the missing features in Cargo.toml's feature pins ([dependencies] for the target,"
              " [build-dependencies] for the host).", file=sys.stderr)
        sys.exit(1)
    print(f"check_features: the test build and the plain build share the features of all "
          f"{len(set(plain) & set(with_dev))} crates they both compile")


if __name__ == "__main__":
    main()
