#!/usr/bin/env python3
"""List the broken relative links of the repository's Markdown: a linked file or folder that does
not exist, or a `#section` that names no heading of the linked page (GitHub's heading anchors).

Checks every .md file under docs/ and scripts/, and README.md, ARCHITECTURE.md, CHANGELOG.md and
jetson/README.md at the root. Links to web addresses are not followed.

usage: python3 scripts/lab/check-links.py [ROOT]     (ROOT: the repository, default: this one)
Prints `page:line: link (why)` per broken link; exit status 1 if any, 0 if none.
"""
import os
import re
import sys

LINK = re.compile(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")


def pages(root):
    """The Markdown files to check, as paths relative to root."""
    out = [p for p in ("README.md", "ARCHITECTURE.md", "CHANGELOG.md", "jetson/README.md")
           if os.path.isfile(os.path.join(root, p))]
    for top in ("docs", "scripts"):
        for folder, dirs, files in os.walk(os.path.join(root, top)):
            dirs[:] = [d for d in dirs if d != "raw" or top != "docs"]
            out += [os.path.relpath(os.path.join(folder, f), root) for f in files if f.endswith(".md")]
    return sorted(out)


def slug(heading):
    """GitHub's anchor for a heading's text: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`|\*", "", heading)
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path, cache={}):
    """Every heading anchor of a Markdown file (with GitHub's -1, -2 suffixes for repeats)."""
    if path not in cache:
        seen, found, fenced = {}, set(), False
        with open(path, encoding="utf-8") as f:
            for line in f:
                if FENCE.match(line):
                    fenced = not fenced
                m = None if fenced else HEADING.match(line)
                if m:
                    s = slug(m.group(2))
                    n = seen.get(s, 0)
                    found.add(s if n == 0 else f"{s}-{n}")
                    seen[s] = n + 1
        cache[path] = found
    return cache[path]


def broken(root, page):
    """(line number, link, why) for each broken link of one page."""
    out, fenced = [], False
    with open(os.path.join(root, page), encoding="utf-8") as f:
        for no, line in enumerate(f, 1):
            if FENCE.match(line):
                fenced = not fenced
            if fenced:
                continue
            for link in LINK.findall(line):
                if re.match(r"^[a-z][a-z0-9+.-]*:", link):
                    continue
                target, _, anchor = link.partition("#")
                path = os.path.normpath(os.path.join(root, os.path.dirname(page), target)) if target \
                    else os.path.join(root, page)
                if not os.path.exists(path):
                    out.append((no, link, "no such file"))
                elif anchor and path.endswith(".md") and anchor.lower() not in anchors(path):
                    out.append((no, link, "no such section"))
    return out


def main():
    root = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "..", "..")
    root = os.path.abspath(root)
    count = 0
    for page in pages(root):
        for no, link, why in broken(root, page):
            print(f"{page}:{no}: {link} ({why})")
            count += 1
    print(f"check-links: {count} broken link(s) in {len(pages(root))} pages", file=sys.stderr)
    return 1 if count else 0


if __name__ == "__main__":
    sys.exit(main())
