"""Check the documentation's links, offline: README.md and every page under docs/.

* every relative link (``[text](path)``, ``[text](path#anchor)``, ``[text](#anchor)``,
  images too) resolves to a file or folder of the repository, and its ``#anchor`` to a
  heading of that page (GitHub's anchors: the heading's text in lower case, punctuation
  dropped, spaces as ``-``, ``-1``, ``-2``... for repeats);
* every page under docs/ is linked from README.md or docs/index.md (the index), so no
  page is left where no reader finds it;
* links to other sites (``http:``, ``https:``, ``mailto:``) are not followed: nothing
  here touches the network.

Links inside code (fenced blocks, inline code) are text, not links.  Run by ``make
test`` (``make lint``).  Exit status 1 with one line per problem (``page:line: ...``),
0 when every link resolves.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import unquote

TOP = Path(__file__).resolve().parents[1]
INDEX = Path("docs") / "index.md"
#: An inline link or image: [text](target) or [text](target "title"); text may hold
#: inline code, and one level of brackets.
INLINE = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
#: A reference definition: [label]: target
REFERENCE = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$")
EXTERNAL = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")  # http:, https:, mailto:, ...
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s{0,3}(```|~~~)")
CODE_SPAN = re.compile(r"(`+)(.+?)\1")


def pages(top: Path) -> list[Path]:
    """README.md and every .md under docs/, relative to ``top``."""
    found = [Path("README.md")] if (top / "README.md").is_file() else []
    return found + sorted(p.relative_to(top) for p in (top / "docs").rglob("*.md"))


def outside_fences(text: str) -> Iterator[tuple[int, str]]:
    """(line number, line) of the lines outside fenced code blocks."""
    fence: str | None = None
    for number, line in enumerate(text.splitlines(), start=1):
        opening = FENCE.match(line)
        if opening:
            if fence is None:
                fence = opening.group(1)
            elif opening.group(1) == fence:
                fence = None
            continue
        if fence is None:
            yield number, line


def prose_lines(text: str) -> Iterator[tuple[int, str]]:
    """(line number, line) outside fenced code blocks, with inline code blanked."""
    for number, line in outside_fences(text):
        yield number, CODE_SPAN.sub(lambda m: " " * len(m.group(0)), line)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading's text."""
    text = re.sub(r"`([^`]*)`", r"\1", heading)  # inline code keeps its text
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link keeps its text
    text = re.sub(r"[^\w\- ]", "", text.strip().lower())
    return text.replace(" ", "-")


def anchors(text: str) -> set[str]:
    """The anchors of a page's headings (repeats get -1, -2, ...)."""
    seen: dict[str, int] = {}
    found: set[str] = set()
    for _, line in outside_fences(text):
        match = HEADING.match(line)
        if match is None:
            continue
        base = slug(match.group(2))
        count = seen.get(base, 0)
        seen[base] = count + 1
        found.add(base if count == 0 else f"{base}-{count}")
    return found


def links(text: str) -> Iterator[tuple[int, str]]:
    """(line number, target) of every link of a page's prose."""
    for number, line in prose_lines(text):
        for match in INLINE.finditer(line):
            yield number, match.group(1)
        ref = REFERENCE.match(line)
        if ref:
            yield number, ref.group(1)


def check(top: Path) -> list[str]:
    """One line per broken link or unlinked page of the tree at ``top``."""
    problems: list[str] = []
    texts = {page: (top / page).read_text(encoding="utf-8") for page in pages(top)}
    linked: dict[Path, set[Path]] = {page: set() for page in texts}
    for page, text in texts.items():
        for number, target in links(text):
            if EXTERNAL.match(target):
                continue
            where = f"{page}:{number}"
            path_part, _, anchor = target.partition("#")
            path_part = unquote(path_part)
            resolved = (top / page).parent / path_part if path_part else top / page
            try:
                relative = resolved.resolve().relative_to(top.resolve())
            except ValueError:
                problems.append(f"{where}: link {target!r} leaves the repository")
                continue
            if not resolved.exists():
                problems.append(f"{where}: link {target!r}: no such file {relative}")
                continue
            linked[page].add(relative)
            if not anchor:
                continue
            if resolved.suffix != ".md" or not resolved.is_file():
                problems.append(f"{where}: link {target!r}: an anchor into a file that is "
                                "not a markdown page")
                continue
            target_text = texts.get(relative) or resolved.read_text(encoding="utf-8")
            if unquote(anchor).lower() not in anchors(target_text):
                problems.append(f"{where}: link {target!r}: {relative} has no heading "
                                f"#{anchor} (its anchors: "
                                f"{', '.join(sorted(anchors(target_text))) or 'none'})")
    roots = {Path("README.md"), INDEX}
    reachable = set().union(*(linked.get(root, set()) for root in roots))
    for page in texts:
        if page in roots or page.parts[0] != "docs" or page in reachable:
            continue
        problems.append(f"{page}: not linked from README.md or {INDEX}: add a line for it "
                        f"to {INDEX}")
    if INDEX not in texts:
        problems.append(f"{INDEX}: missing (the index of the pages under docs/)")
    return problems


def main() -> int:
    problems = check(TOP)
    for line in problems:
        print(line)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
