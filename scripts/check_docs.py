"""Check the repository's markdown: no oversized file, no broken relative link.

    python scripts/check_docs.py [ROOT] [--max-kb 200]

Every ``*.md`` under ROOT (default: the repository; hidden folders, ``out/``, ``build/`` and
``*.egg-info`` are skipped) must be at most ``--max-kb`` kB (1 kB = 1000 bytes), and every relative
link or image in it (``[text](target)``, ``![alt](target)``, ``[id]: target``, ``src="target"``
and ``href="target"``) must name an existing file or folder, and an existing heading when it has
a ``#anchor`` into a markdown file (GitHub's anchors: lower case, punctuation dropped, spaces to
hyphens, ``-1``, ``-2`` for repeats). Links with a scheme (``https:``, ``mailto:``) are not
followed; code blocks and code spans are ignored. Prints one line per problem, ``FILE:LINE:
problem``, and exits with 1 if there is any (0 otherwise). CI runs it before the tests, and
``tests/scripts/test_check_docs.py`` runs it on the repository.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from urllib.parse import unquote

DEFAULT_MAX_KB = 200
SKIPPED_DIRS = ("out", "build", "node_modules")

_FENCE = re.compile(r"^\s*(```|~~~)")
_CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1")
_INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_REFERENCE_DEF = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$")
_HTML_ATTR = re.compile(r"""\b(?:src|href)\s*=\s*["']([^"']+)["']""")
_HTML_ID = re.compile(r"""\b(?:id|name)\s*=\s*["']([^"']+)["']""")
_HEADING = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


def markdown_files(root: Path) -> list[Path]:
    """The ``*.md`` files under ``root``, skipping hidden, output and build folders."""
    found = []
    for path in sorted(root.rglob("*.md")):
        parts = path.relative_to(root).parts[:-1]
        if any(p.startswith(".") or p in SKIPPED_DIRS or p.endswith(".egg-info") for p in parts):
            continue
        found.append(path)
    return found


def _prose_lines(text: str) -> list[tuple[int, str]]:
    """``(line number, line)`` outside fenced code blocks, with code spans blanked."""
    lines, fenced = [], False
    for number, line in enumerate(text.splitlines(), start=1):
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append((number, _CODE_SPAN.sub("", line)))
    return lines


def github_slug(heading: str) -> str:
    """GitHub's anchor for a heading's text: link syntax reduced to its text, lower case,
    punctuation except ``-`` and ``_`` dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = re.sub(r"<[^>]+>", "", text).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors a markdown file defines: its headings' slugs (repeats numbered) and HTML ids."""
    seen: dict[str, int] = {}
    found: set[str] = set()
    text = path.read_text(encoding="utf-8", errors="replace")
    raw = text.splitlines()
    for number, line in _prose_lines(text):
        found.update(_HTML_ID.findall(line))
        match = _HEADING.match(raw[number - 1])  # a heading's code spans count in its anchor
        if match:
            slug = github_slug(match.group(2))
            count = seen.get(slug, 0)
            seen[slug] = count + 1
            found.add(slug if count == 0 else f"{slug}-{count}")
    return found


def link_targets(text: str) -> list[tuple[int, str]]:
    """``(line number, target)`` of every link and image in markdown ``text`` outside code."""
    targets = []
    for number, line in _prose_lines(text):
        targets += [(number, t) for t in _INLINE_LINK.findall(line)]
        targets += [(number, t) for t in _HTML_ATTR.findall(line)]
        match = _REFERENCE_DEF.match(line)
        if match:
            targets.append((number, match.group(1)))
    return targets


def check_link(source: Path, target: str, anchor_cache: dict[Path, set[str]]) -> str | None:
    """Why a relative link from ``source`` is broken, or None if it resolves (or is not relative)."""
    if _SCHEME.match(target) or target.startswith("//"):
        return None
    path_part, _, anchor = target.partition("#")
    path_part = unquote(path_part.split("?", 1)[0])
    dest = source if not path_part else (source.parent / path_part)
    if not dest.exists():
        return f"broken link {target!r}: no such file"
    if anchor and dest.is_file() and dest.suffix.lower() == ".md":
        if dest not in anchor_cache:
            anchor_cache[dest] = anchors(dest)
        if unquote(anchor).lower() not in anchor_cache[dest]:
            return f"broken link {target!r}: no heading #{anchor} in {dest.name}"
    return None


def check_docs(root: Path, max_kb: float = DEFAULT_MAX_KB) -> list[str]:
    """Problems with the markdown under ``root``, one line each (``FILE:LINE: problem``)."""
    problems = []
    anchor_cache: dict[Path, set[str]] = {}
    for path in markdown_files(root):
        rel = path.relative_to(root)
        size = path.stat().st_size
        if size > max_kb * 1000:
            problems.append(f"{rel}:1: {size / 1000:.0f} kB, over the {max_kb:g} kB limit for a doc")
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        for number, target in link_targets(text):
            reason = check_link(path, target, anchor_cache)
            if reason:
                problems.append(f"{rel}:{number}: {reason}")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", nargs="?", default=str(Path(__file__).resolve().parents[1]),
                        help="folder to check (default: the repository)")
    parser.add_argument("--max-kb", type=float, default=DEFAULT_MAX_KB,
                        help="largest allowed markdown file, kB (%(default)s)")
    args = parser.parse_args(argv)
    root = Path(args.root)
    if not root.is_dir():
        print(f"{root}: not a folder", file=sys.stderr)
        return 2
    problems = check_docs(root, args.max_kb)
    for line in problems:
        print(line)
    count = len(markdown_files(root))
    sys.stdout.flush()
    print(f"check_docs: {count} markdown files, {len(problems)} problems", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
