"""The README and docs/: generated parts current, links that resolve, no history.

- docs/benchmarks.md and the README's headline table are what ``python -m
  benchmarks.report`` makes of the committed results (each number written once);
- docs/usage.md's option references are what ``python -m hdrmerge_cli.manpages --usage``
  makes of the click definitions (as the man pages are);
- README.md stays short; every relative link and anchor in README and docs resolves;
- the text describes the present: no development stops, commit hashes or before/after.
"""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

#: wording that tells the project's history instead of its present
HISTORY = [
    (re.compile(r"\bstop \d+", re.I), "a development stop"),
    (re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b"), "a commit hash"),
    (re.compile(r"before/after", re.I), "before/after"),
    (re.compile(r"\bpreviously\b", re.I), "previously"),
    (re.compile(r"\bused to\b", re.I), "used to"),
    (re.compile(r"\bnow\b", re.I), "now"),
]


def test_benchmarks_page_and_headline_are_generated():
    from benchmarks import report

    assert (ROOT / "docs" / "benchmarks.md").read_text() == report.benchmarks_page(), \
        "docs/benchmarks.md is out of date: run python -m benchmarks.report"
    readme = (ROOT / "README.md").read_text()
    assert readme == report.readme_with_headline(readme), \
        "README.md's headline table is out of date: run python -m benchmarks.report"


def test_usage_option_reference_is_generated():
    from hdrmerge_cli.cli import COMMANDS
    from hdrmerge_cli.manpages import update_usage

    usage = (ROOT / "docs" / "usage.md").read_text()
    for name in COMMANDS:
        assert f"<!-- options:{name}:start -->" in usage, f"docs/usage.md has no option reference of {name}"
    assert usage == update_usage(usage), \
        "docs/usage.md's option reference is out of date: run python -m hdrmerge_cli.manpages --usage"


def test_readme_is_short():
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= 300, f"README.md has {n} lines (at most 300)"


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading (formatting dropped, then punctuation)."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip())
    text = re.sub(r"[^\w\- ]", "", text.lower())
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    seen, out = {}, set()
    in_code = False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            in_code = not in_code
        if in_code or not re.match(r"#{1,6} ", line):
            continue
        slug = _slug(line.lstrip("#"))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def _links(path: Path):
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if not re.match(r"[a-z]+:", target):
            yield target


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page):
    for target in _links(page):
        file, _, anchor = target.partition("#")
        dest = (page.parent / file).resolve() if file else page
        assert dest.exists(), f"{page.name}: link to {target}: no such file"
        if anchor and dest.suffix == ".md":
            assert anchor in _anchors(dest), f"{page.name}: link to {target}: no such heading"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_no_history(page):
    for n, line in enumerate(page.read_text().splitlines(), 1):
        for pattern, what in HISTORY:
            assert not pattern.search(line), f"{page.name}:{n} speaks of history ({what}): {line.strip()}"


def test_docs_exist_and_the_readme_links_each():
    readme = (ROOT / "README.md").read_text()
    for name in ("usage.md", "method.md", "benchmarks.md", "limitations.md"):
        assert (ROOT / "docs" / name).exists()
        assert f"docs/{name}" in readme, f"README.md does not link docs/{name}"
    assert "](man/)" in readme or "](man/" in readme
