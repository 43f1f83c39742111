#!/usr/bin/env python3
"""The documentation gate of the test command.

- README.md stays at most 300 lines (the rest belongs in docs/);
- every relative link and image in README.md and docs/*.md resolves: the
  file exists, and a `#anchor` names a heading of the file it points into
  (GitHub's slugs);
- with --run-quickstart: the commands of the README's quick start (the
  fenced block after the `<!-- quickstart -->` marker) run as written, in
  the repository root, each to exit 0. They are read from the README
  itself, so the check and the README cannot drift apart.

Exit status 1 with one line per problem.
"""

import functools
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README_MAX_LINES = 300
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^(```|~~~)")


def without_code(text):
    """The text with fenced code blocks and inline code removed (links there are not links)."""
    out, fenced = [], False
    for line in text.split("\n"):
        if FENCE.match(line.strip()):
            fenced = not fenced
            out.append("")
            continue
        out.append("" if fenced else re.sub(r"`[^`]*`", "", line))
    return "\n".join(out)


def slug(heading):
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


@functools.lru_cache(maxsize=None)
def anchors(path):
    found, seen = set(), {}
    for line in without_code(path.read_text()).split("\n"):
        m = re.match(r"^#{1,6}\s+(.*)$", line)
        if not m:
            continue
        base = slug(m.group(1))
        n = seen.get(base, 0)
        seen[base] = n + 1
        found.add(base if n == 0 else f"{base}-{n}")
    return found


def check_links(path):
    problems = []
    text = without_code(path.read_text())
    for lineno, line in enumerate(text.split("\n"), 1):
        for target in LINK.findall(line):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
                continue
            file_part, _, anchor = target.partition("#")
            dest = path if file_part == "" else (path.parent / file_part).resolve()
            where = f"{path.relative_to(ROOT)}:{lineno}"
            if not dest.exists():
                problems.append(f"{where}: link to {target}: {file_part} does not exist")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                problems.append(f"{where}: link to {target}: no heading with the anchor #{anchor} in {dest.name}")
    return problems


def quickstart_commands(readme):
    lines = readme.read_text().split("\n")
    try:
        start = lines.index("<!-- quickstart -->")
    except ValueError:
        return None
    commands, inside = [], False
    for line in lines[start + 1 :]:
        if FENCE.match(line.strip()):
            if inside:
                break
            inside = True
            continue
        if inside:
            command = line.split(" #", 1)[0].strip()
            if command:
                commands.append(command)
    return commands


def main():
    readme = ROOT / "README.md"
    problems = []
    n = len(readme.read_text().split("\n")) - 1
    if n > README_MAX_LINES:
        problems.append(f"README.md: {n} lines, more than {README_MAX_LINES}: move detail into docs/")
    files = [readme] + sorted((ROOT / "docs").glob("*.md"))
    for f in files:
        problems.extend(check_links(f))
    commands = quickstart_commands(readme)
    if commands is None or not commands:
        problems.append("README.md: no `<!-- quickstart -->` marker followed by a fenced block of commands")
    if problems:
        print("\n".join(problems))
        return 1
    print(f"README.md: {n} lines (at most {README_MAX_LINES}); links resolve in {len(files)} files")
    if "--run-quickstart" in sys.argv:
        for command in commands:
            print(f"quick start: {command}", flush=True)
            if subprocess.run(["bash", "-c", command], cwd=ROOT).returncode != 0:
                print(f"README.md quick start: `{command}` failed")
                return 1
        print(f"quick start: {len(commands)} commands ran")
    return 0


if __name__ == "__main__":
    sys.exit(main())
