"""The guide (docs/, an mdBook) and the README: every relative link and image points at a file
that exists (and, for `page.md#anchor`, at a heading of that page), every page is in the book's
SUMMARY.md, the README stays short, and `mdbook build` succeeds.

mdbook is installed by scripts/test.sh (`cargo install mdbook`); without it the build test fails
and says how to install it."""

import os
import pathlib
import re
import shutil
import subprocess

ROOT = pathlib.Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
INCLUDE = re.compile(r"\{\{#include ([^}\s]+)\}\}")


def pages():
    return sorted(p for p in DOCS.rglob("*.md") if "figures" not in p.relative_to(DOCS).parts[:1])


def text_outside_code(path, inline=False):
    """The page's text without fenced code blocks and (unless `inline`) inline code: links
    there are examples. Headings keep their inline code (`inline=True`), which names them."""
    out, fenced = [], False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            out.append(line if inline else re.sub(r"`[^`]*`", "", line))
    return "\n".join(out)


def slug(heading):
    """The anchor mdbook (and GitHub) give a heading."""
    text = re.sub(r"`|\*\*|\*", "", heading.strip().lower())
    return "".join(c for c in text.replace(" ", "-") if c.isalnum() or c in "-_")


def anchors(path):
    """The page's heading anchors, with those of the files it includes (as mdbook renders it)."""
    own = {slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", text_outside_code(path, inline=True), re.M)}
    for m in INCLUDE.finditer(path.read_text()):
        included = (path.parent / m.group(1)).resolve()
        if included.is_file():
            own |= anchors(included)
    return own


def links(path):
    for m in LINK.finditer(text_outside_code(path)):
        target = m.group(1)
        if re.match(r"^[a-z]+:", target) or target.startswith("mailto:"):
            continue
        yield target


def test_every_relative_link_resolves():
    bad = []
    for page in [ROOT / "README.md", *pages()]:
        for target in links(page):
            file, _, anchor = target.partition("#")
            dest = (page.parent / file).resolve() if file else page
            if not dest.exists():
                bad.append(f"{page.relative_to(ROOT)}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                bad.append(f"{page.relative_to(ROOT)}: {target} (no heading with that anchor)")
        for m in INCLUDE.finditer(page.read_text(encoding="utf-8")):
            if not (page.parent / m.group(1)).exists():
                bad.append(f"{page.relative_to(ROOT)}: include {m.group(1)} (no such file)")
    assert not bad, "broken links:\n" + "\n".join(bad)


def test_every_page_is_in_the_summary():
    summary = (DOCS / "SUMMARY.md").read_text(encoding="utf-8")
    listed = {(DOCS / t).resolve() for t in LINK.findall(summary)}
    missing = [str(p.relative_to(ROOT)) for p in pages() if p.name != "SUMMARY.md" and p.resolve() not in listed]
    assert not missing, f"pages not in docs/SUMMARY.md: {missing}"
    assert all(p.exists() for p in listed), "SUMMARY.md lists a page that does not exist"


def test_the_link_checker_catches_a_broken_link(tmp_path):
    page = tmp_path / "page.md"
    (tmp_path / "there.md").write_text("# A heading\n\n## `lmac`\n")
    page.write_text("[ok](there.md#a-heading) [gone](missing.md) `[code](not-a-link.md)`\n")
    found = list(links(page))
    assert found == ["there.md#a-heading", "missing.md"]
    assert {"a-heading", "lmac"} <= anchors(tmp_path / "there.md")


def test_readme_is_short():
    size = (ROOT / "README.md").stat().st_size
    assert size <= 10 * 1024, f"README.md is {size} bytes: the guide in docs/ is the place for detail"


def mdbook():
    found = shutil.which("mdbook") or str(pathlib.Path.home() / ".cargo" / "bin" / "mdbook")
    assert os.access(found, os.X_OK), "mdbook is not installed: cargo install mdbook --locked --no-default-features"
    return found


def test_mdbook_builds(tmp_path):
    out = tmp_path / "book"
    r = subprocess.run([mdbook(), "build", str(DOCS), "--dest-dir", str(out)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "ERROR" not in r.stderr, r.stderr
    assert (out / "index.html").exists()
    # The configuration reference and the figures' data land in the book.
    assert (out / "reference" / "configuration.html").exists()
    assert (out / "figures").is_dir()
