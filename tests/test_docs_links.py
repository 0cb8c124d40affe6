"""The README and the docs point at things that exist: every relative link resolves to a file (and its #anchor to
a heading of that file), and every repository path named in backticks (`tests/...`, `src/...`, `examples/...`,
`benchmarks/...`, `docs/...`) is a file or directory of the repository."""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md")])

LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)")
CODE_SPAN = re.compile(r"`([^`\n]+)`")
REPO_PATH = re.compile(r"(?<![\w./-])((?:tests|src|examples|benchmarks|docs)/[\w./*-]*[\w*/])")
FENCE = re.compile(r"^(```|~~~)")
#: made by a script and ignored by git, so named but absent from a checkout (see .gitignore)
GENERATED = ("benchmarks/models/",)


def _ids(page: Path) -> str:
    return str(page.relative_to(ROOT))


def _prose(text: str) -> str:
    """The text outside fenced code blocks (links and anchors in code are not links)."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        if not fenced:
            out.append(line)
    return "\n".join(out)


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, markup and punctuation dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link in a heading keeps its text
    text = unicodedata.normalize("NFC", text).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in _prose(page.read_text(encoding="utf-8")).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        slug = _slug(m.group(1))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def relative_links(page: Path) -> list[str]:
    text = _prose(page.read_text(encoding="utf-8"))
    targets = LINK.findall(text) + IMAGE.findall(text)
    return [t for t in targets if not re.match(r"^[a-z][a-z0-9+.-]*:", t)]  # http:, https:, mailto:, ...


@pytest.mark.parametrize("page", PAGES, ids=_ids)
def test_every_relative_link_resolves(page: Path) -> None:
    broken = []
    for target in relative_links(page):
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    assert not broken, f"{_ids(page)}: " + "; ".join(broken)


@pytest.mark.parametrize("page", PAGES, ids=_ids)
def test_every_repository_path_named_exists(page: Path) -> None:
    missing = []
    for span in CODE_SPAN.findall(page.read_text(encoding="utf-8")):
        for path in REPO_PATH.findall(span):
            path = path.split("::")[0]  # a test id names its file
            if path.startswith(GENERATED):
                continue
            if "*" in path:
                if not any(ROOT.glob(path)):
                    missing.append(path)
            elif not (ROOT / path).exists():
                missing.append(path)
    assert not missing, f"{_ids(page)} names paths that do not exist: {sorted(set(missing))}"


def test_the_docs_index_lists_every_page() -> None:
    index = ROOT / "docs" / "README.md"
    listed = {Path(t.partition("#")[0]).name for t in relative_links(index)}
    unlisted = [p.name for p in (ROOT / "docs").glob("*.md") if p.name != "README.md" and p.name not in listed]
    assert not unlisted, f"docs/README.md does not list {sorted(unlisted)}"


def test_make_bench_has_a_table_to_replace() -> None:
    """`make bench` (benchmarks/run_all.py --write-docs) rewrites the table between these markers."""
    text = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    begin, end = text.find("<!-- benchmarks:begin -->"), text.find("<!-- benchmarks:end -->")
    assert 0 <= begin < end, "docs/benchmarks.md has lost its benchmarks:begin / benchmarks:end markers"
    assert "| benchmark | figure | asyncdonkey |" in text[begin:end]


TEST_REF = re.compile(r"`((?:tests/[\w./-]+\.py)?)::(\w+)`")


def test_every_test_docs_safety_names_exists():
    """docs/safety.md is the list of faults with the test that proves each: a renamed or removed test must not
    leave a row pointing at nothing. ``path::name`` names a test; a bare ``::name`` is in the row's last path."""
    text = (ROOT / "docs" / "safety.md").read_text()
    missing = []
    checked = 0
    for line in text.splitlines():
        current = None
        for path, name in TEST_REF.findall(line):
            checked += 1
            current = path or current
            if current is None:
                missing.append(f"::{name} (no file before it on its line)")
                continue
            source = (ROOT / current).read_text() if (ROOT / current).is_file() else ""
            if not re.search(rf"^\s*(async\s+)?def {name}\(", source, re.MULTILINE):
                missing.append(f"{current}::{name}")
    assert not missing, missing
    assert checked > 40  # the rows are read at all
