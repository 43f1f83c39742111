#!/usr/bin/env python3
"""The longest functions under src/ (lines from `fn` to its closing brace,
counted by brace depth with strings and comments stripped).

    python3 scripts/fn_lengths.py [N]     # the N longest (default 8)
"""
import pathlib
import re
import sys

FN = re.compile(r"\s*(pub(\([a-z]+\))?\s+)?(const\s+)?(unsafe\s+)?fn\s+(\w+)")


def lengths(root):
    out = []
    for path in sorted(pathlib.Path(root).rglob("*.rs")):
        lines = path.read_text().split("\n")
        for start, line in enumerate(lines):
            m = FN.match(line)
            if not m or line.rstrip().endswith(";"):
                continue
            depth, seen, end = 0, False, start
            while end < len(lines):
                code = re.sub(r'"([^"\\]|\\.)*"', '""', lines[end])
                code = re.sub(r"'.'", "", re.sub(r"//.*", "", code))
                depth += code.count("{") - code.count("}")
                seen = seen or "{" in code
                if seen and depth <= 0:
                    break
                end += 1
            out.append((end - start + 1, f"{path}:{start + 1}", m.group(5)))
    return sorted(out, reverse=True)


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 8
    for length, place, name in lengths("src")[:n]:
        print(f"{length:4} {place} {name}")
