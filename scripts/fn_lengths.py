#!/usr/bin/env python3
"""The longest functions under src/: lines of code from `fn` to its closing
brace, blank and comment lines not counted (what clippy's `too_many_lines`
counts; the test command enforces 80 through clippy, clippy.toml). Strings
and comments are stripped over the whole file first, so braces inside them
(a multi-line string, `{{` in a format string) do not count.

    python3 scripts/fn_lengths.py [N]     # the N longest (default 8)
"""
import pathlib
import re
import sys

FN = re.compile(r"\s*(pub(\([a-z]+\))?\s+)?(const\s+)?(unsafe\s+)?fn\s+(\w+)")
LITERALS = re.compile(r'//[^\n]*|/\*.*?\*/|r#*"(?:.|\n)*?"#*|b?"(?:[^"\\]|\\.|\n)*"|\'(?:[^\'\\\n]|\\.)\'', re.S)


def stripped(text):
    """The text with comments and string / char literals blanked, line breaks kept."""
    def blank(m):
        s = m.group(0)
        if s.startswith("//") or s.startswith("/*"):
            return "\n" * s.count("\n")
        return '""' + "\n" * s.count("\n")
    return LITERALS.sub(blank, text)


def lengths(root):
    out = []
    for path in sorted(pathlib.Path(root).rglob("*.rs")):
        raw = path.read_text().split("\n")
        code = stripped(path.read_text()).split("\n")
        for start, line in enumerate(raw):
            m = FN.match(line)
            if not m or line.rstrip().endswith(";"):
                continue
            depth, seen, end, count = 0, False, start, 0
            while end < len(code):
                c = code[end]
                count += bool(c.strip())
                depth += c.count("{") - c.count("}")
                seen = seen or "{" in c
                if seen and depth <= 0:
                    break
                end += 1
            out.append((count, f"{path}:{start + 1}", m.group(5)))
    return sorted(out, reverse=True)


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 8
    for length, place, name in lengths("src")[:n]:
        print(f"{length:4} {place} {name}")
