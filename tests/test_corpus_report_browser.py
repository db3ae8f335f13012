"""The report of ``lidarloc corpus compare`` opened from disk in headless Chromium, with no server:
its plots decode, nothing is fetched from anywhere but the page itself, the regressions come
first (the corpus outputs as tests/test_corpus_compare.py writes them)."""

from __future__ import annotations

import pytest
from test_corpus_compare import base_tables, compare, drive_table, planted, write_output

pytestmark = pytest.mark.browser


@pytest.fixture
def base(tmp_path):
    tables = base_tables()
    tables["retired"] = (drive_table("solo", 5), 0)
    return write_output(tmp_path / "base", tables)


def test_the_html_report_opens_from_disk_in_a_browser(base, tmp_path, browser):
    """The report opened from file:// in headless Chromium, no server: its plots decode, nothing
    is fetched from anywhere but the page itself, and the regressions come first."""
    from lidarloc.app.corpus.compare_report import write_reports
    from lidarloc.app.corpus.figures import read_output

    new = planted(tmp_path)
    b, n = read_output(base, "BASE"), read_output(new, "NEW")
    result = compare(base, new)
    _, page_file = write_reports(result, b, n, tmp_path / "report")
    page = browser.new_page()
    requests: list[str] = []
    page.on("request", lambda r: requests.append(r.url))
    page.goto(page_file.resolve().as_uri())
    page.wait_for_load_state("load")
    images = page.evaluate("Array.from(document.images).map(i => [i.complete, i.naturalWidth, i.naturalHeight])")
    assert len(images) >= 1 and all(done and w > 100 and h > 50 for done, w, h in images), images
    assert all(u.startswith(("file:", "data:")) for u in requests), requests
    text = page.inner_text("body")
    assert text.index("Regressions") < text.index("Improvements") < text.index("Unchanged drives")
    assert result["regressions"][0]["drive"] in text and result["regressions"][0]["view"] in text
