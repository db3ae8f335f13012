"""BENCHMARKS.md stays a reference a user can read: one row per target of five cells (target,
figure, command, machine, date), no row over 300 characters, and the explanations beside it in
docs/benchmarks/, one page per area, every relative link and anchor resolving."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "BENCHMARKS.md"
PAGES = ROOT / "docs" / "benchmarks"
MAX_ROW = 300

_FENCE = re.compile(r"^```.*?^```", re.M | re.S)
_CODE = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _prose(text: str) -> str:
    """The text without code blocks and code spans, where a bracket is not a link."""
    return _CODE.sub("", _FENCE.sub("", text))


def _rows(text: str) -> list[str]:
    return [line for line in _FENCE.sub("", text).splitlines() if line.startswith("|")]


def _cells(row: str) -> list[str]:
    return re.split(r"(?<!\\)\|", row.strip()[1:-1])


def _slug(heading: str) -> str:
    """The anchor GitHub gives a heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = _FENCE.sub("", page.read_text())
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", text, re.M)}


def _links(page: Path) -> list[tuple[Path, str]]:
    """Every relative link of a page: the file it names and its anchor ('' without one)."""
    found = []
    for target in _LINK.findall(_prose(page.read_text())):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        found.append(((page.parent / path).resolve() if path else page, anchor))
    return found


def _documents() -> list[Path]:
    return [BENCHMARKS, *sorted(PAGES.glob("*.md"))]


def test_every_row_has_five_cells_and_at_most_300_characters():
    rows = _rows(BENCHMARKS.read_text())
    assert rows
    wrong = [row[:80] for row in rows if len(_cells(row)) != 5]
    assert not wrong, f"rows without exactly 5 cells: {wrong}"
    long = [f"{len(row)}: {row[:80]}" for row in rows if len(row) > MAX_ROW]
    assert not long, f"rows over {MAX_ROW} characters (move the detail to the area's page): {long}"


def test_every_table_is_target_figure_command_machine_date():
    headers = [row for row in _rows(BENCHMARKS.read_text()) if _cells(row)[0].strip() == "target"]
    assert headers
    for header in headers:
        assert [c.strip() for c in _cells(header)] == ["target", "figure", "command", "machine", "date"]


def test_every_area_links_its_page_and_every_page_is_linked():
    linked = {path for path, _ in _links(BENCHMARKS) if path.parent == PAGES.resolve()}
    missing = sorted(p.name for p in linked if not p.is_file())
    assert not missing, f"BENCHMARKS.md links pages that do not exist: {missing}"
    pages = {p.resolve() for p in PAGES.glob("*.md") if p.name != "README.md"}
    assert pages, "docs/benchmarks/ has no pages"
    assert not sorted(p.name for p in pages - linked), "pages BENCHMARKS.md does not link"
    areas = re.findall(r"^## .+$", _FENCE.sub("", BENCHMARKS.read_text()), re.M)
    assert len(areas) == len(pages), "one page per area"


def test_every_relative_link_and_anchor_resolves():
    broken = []
    for doc in _documents():
        for path, anchor in _links(doc):
            name = f"{doc.relative_to(ROOT)} -> {path}#{anchor}"
            if not path.exists():
                broken.append(name)
            elif anchor and path.suffix == ".md" and anchor not in _anchors(path):
                broken.append(name)
    assert not broken, f"links that resolve to nothing: {broken}"
