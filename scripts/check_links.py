#!/usr/bin/env python3
"""Check every relative Markdown link and `#anchor` in the repository's Markdown files.

    python3 scripts/check_links.py            # every *.md git tracks or would track (git ls-files), exit 1 on a broken link
    python3 scripts/check_links.py FILE...    # only these files
    python3 scripts/check_links.py --anchors FILE   # print FILE's anchors (to write a link)

A link is `[text](target)`, `![alt](target)` or a reference definition `[label]: target`, outside
fenced code blocks and inline code. External targets (`http:`, `https:`, `mailto:`) are not
fetched. A relative target must name a file or directory that exists; a `#fragment` must be an
anchor of the target Markdown file (or of the same file for `#fragment` alone): a heading's
GitHub slug (lower case, punctuation dropped, spaces as `-`, `-1`, `-2` for repeats) or an
explicit `<a id="...">` / `<a name="...">`. Standard library only.
"""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
INLINE_LINK = re.compile(r"!?\[((?:[^\[\]]|\[[^\]]*\])*)\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
REF_DEF = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(\s+.*)?$")
HTML_ANCHOR = re.compile(r"<a\s+(?:id|name)\s*=\s*\"([^\"]+)\"", re.I)
CODE_SPAN = re.compile(r"(`+)(.+?)\1")


def slug(text: str) -> str:
    """GitHub's heading anchor: the rendered text, lower case, only letters, digits, `-`, `_` and
    spaces kept, spaces turned into `-`."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)  # links keep their text
    text = text.replace("`", "")
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML
    text = text.strip().lower()
    out = []
    for ch in text:
        if ch.isalnum() or ch in "-_":
            out.append(ch)
        elif ch == " ":
            out.append("-")
    return "".join(out)


def lines_outside_code(text: str):
    """(line number, line) for every line outside fenced code blocks."""
    fenced = None
    for no, line in enumerate(text.split("\n"), 1):
        m = FENCE.match(line)
        if m:
            if fenced is None:
                fenced = m.group(1)
            elif line.strip().startswith(fenced):
                fenced = None
            continue
        if fenced is None:
            yield no, line


_anchor_cache: dict = {}


def anchors(path: Path) -> set:
    if path in _anchor_cache:
        return _anchor_cache[path]
    seen: dict = {}
    found = set()
    text = path.read_text(encoding="utf-8")
    for _, line in lines_outside_code(text):
        for a in HTML_ANCHOR.findall(line):
            found.add(a)
        m = HEADING.match(line)
        if m:
            s = slug(m.group(2))
            n = seen.get(s, 0)
            seen[s] = n + 1
            found.add(s if n == 0 else f"{s}-{n}")
    _anchor_cache[path] = found
    return found


def links(path: Path):
    text = path.read_text(encoding="utf-8")
    for no, line in lines_outside_code(text):
        m = REF_DEF.match(line)
        if m:
            yield no, m.group(1)
            continue
        bare = CODE_SPAN.sub(lambda c: " " * len(c.group(0)), line)
        for m in INLINE_LINK.finditer(bare):
            yield no, m.group(2)


def check(path: Path) -> list:
    problems = []
    for no, target in links(path):
        if not target or re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):
            continue  # external (http:, https:, mailto:) or empty
        file_part, _, fragment = target.partition("#")
        dest = path if not file_part else (path.parent / file_part).resolve()
        where = f"{path.relative_to(ROOT)}:{no}: {target}"
        if not dest.exists():
            problems.append(f"{where}: no such file")
            continue
        if fragment:
            if dest.is_dir() or dest.suffix.lower() != ".md":
                problems.append(f"{where}: an anchor into something that is not a Markdown file")
            elif fragment not in anchors(dest):
                problems.append(f"{where}: no anchor #{fragment} in {dest.relative_to(ROOT)}")
    return problems


def main(argv: list) -> int:
    if argv[:1] == ["--anchors"]:
        for name in argv[1:]:
            for a in sorted(anchors(Path(name).resolve())):
                print(a)
        return 0
    if argv:
        files = [Path(a).resolve() for a in argv]
    else:
        listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "*.md"], cwd=ROOT, capture_output=True,
                                text=True, check=True).stdout.split()
        files = [ROOT / f for f in listed]
    problems = []
    for f in files:
        problems.extend(check(f))
    for p in problems:
        print(p)
    print(f"{len(files)} files, {len(problems)} broken links", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
