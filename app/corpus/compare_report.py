"""The comparison as a report: ``compare.md`` and ``compare.html`` (one self-contained file, CSS
inline, the plots as base64 PNG: it opens from disk without a server or a network). Regressions
first, worst first, each with the command that opens both runs at its scan; then improvements,
unchanged drives, the drives of one run only, and the noise rule with its figures."""

from __future__ import annotations

import html
from pathlib import Path

from ...core.runs.results import make_out_dir
from .compare_plots import data_uri, drive_plot_png
from .figures import BY_NAME, CorpusOutput

CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 70em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.5em; text-align: left; vertical-align: top; }
th { background: #f3f3f3; }
td.num { text-align: right; }
code { background: #f5f5f5; padding: 0 0.2em; font-size: 0.85em; }
tr.first td { background: #fff1f0; }
img { max-width: 100%; border: 1px solid #eee; }
""".strip()

COLUMNS = ("#", "drive", "scans", "figure", "base", "new", "threshold", "first diverging scan", "what", "see it")


def _value(entry: dict, which: str) -> str:
    value = entry[which]
    digits = BY_NAME[entry["figure"]].digits
    return "—" if value is None else f"{value:.{digits}f}"


def _scans(entry: dict) -> str:
    s = entry["stretch"]
    if s is None:
        return "whole drive"
    return str(s["first_scan"]) if s["first_scan"] == s["last_scan"] else f"{s['first_scan']}–{s['last_scan']}"


def _cells(i: int, e: dict) -> list[str]:
    diverging = "—" if e["first_diverging_scan"] is None else str(e["first_diverging_scan"])
    return [
        str(i),
        e["drive"],
        _scans(e),
        e["figure"],
        _value(e, "base"),
        _value(e, "new"),
        _value(e, "threshold"),
        diverging,
        e["text"],
        e["view"],
    ]


def _count(n: int, what: str) -> str:
    return f"{n} {what}" if n == 1 else f"{n} {what}s"


def _summary(result: dict) -> str:
    return (
        f"{_count(result['drives_compared'], 'drive')} compared: {_count(len(result['regressions']), 'regression')}, "
        f"{_count(len(result['improvements']), 'improvement')} beyond the seed-to-seed noise, "
        f"{_count(len(result['unchanged']), 'drive')} unchanged."
    )


def _noise_rule(result: dict) -> str:
    noise = result["noise"]
    return (
        f"A figure counts when it changed by more than max(floor, {noise['k']:g} × seed spread): the spread is "
        "the range of the figure over the seeds of one log (drives of the same source and configuration, "
        f"different seed; {_count(noise['seed_groups'], 'such group')} here), the larger of BASE's and NEW's; a drive "
        "of a group is weighed against its own group's spread, any other drive against the largest of any "
        "group. Stretches (poor fit, wrong, unlocalized) count by their scans beyond the overlapping "
        "stretches of the other run, against the threshold of the count they add to. Late scans are "
        "wall-clock figures and are left out."
    )


def _noise_rows(result: dict) -> list[list[str]]:
    rows = []
    for f in result["noise"]["figures"]:
        d = f["digits"]
        spread = "—" if f["spread"] is None else f"{f['spread']:.{d}f}"
        rows.append([f["figure"], f["label"], f"{f['floor']:.{d}f}", spread, f"{f['threshold']:.{d}f}"])
    return rows


NOISE_COLUMNS = ("figure", "what", "floor", "largest seed spread", "threshold without a group of its own")


# ------------------------------------------------------------------------------------ Markdown
def _md_cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _md_table(columns, rows, code_last: bool = False) -> list[str]:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        cells = [_md_cell(c) for c in row]
        if code_last:
            cells[-1] = f"`{cells[-1]}`"
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def markdown(result: dict) -> str:
    """compare.md's text."""
    out = [
        "# Corpus comparison",
        "",
        f"BASE `{result['base']}` → NEW `{result['new']}`",
        "",
        _summary(result),
        "",
    ]
    for title, key, empty in (
        ("Regressions, worst first", "regressions", "No regression beyond the seed-to-seed noise."),
        ("Improvements, best first", "improvements", "No improvement beyond the seed-to-seed noise."),
    ):
        out += [f"## {title}", ""]
        entries = result[key]
        if entries:
            out += _md_table(COLUMNS, [_cells(i + 1, e) for i, e in enumerate(entries)], code_last=True)
        else:
            out.append(empty)
        out.append("")
    out += ["## Unchanged drives", "", ", ".join(result["unchanged"]) or "none", ""]
    out += ["## Drives of one run only", ""]
    out.append(f"- only in BASE: {', '.join(result['only_in_base']) or 'none'}")
    out.append(f"- only in NEW: {', '.join(result['only_in_new']) or 'none'}")
    out += ["", "## Noise", "", _noise_rule(result), ""]
    out += _md_table(NOISE_COLUMNS, _noise_rows(result))
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------- HTML
def _h(text) -> str:
    return html.escape(str(text), quote=True)


def _html_table(columns, rows, first_rows: int = 0, code_last: bool = False) -> str:
    head = "".join(f"<th>{_h(c)}</th>" for c in columns)
    body = []
    for i, row in enumerate(rows):
        cells = []
        for j, cell in enumerate(row):
            if code_last and j == len(row) - 1:
                cells.append(f"<td><code>{_h(cell)}</code></td>")
            else:
                cls = ' class="num"' if cell.replace(".", "", 1).replace("-", "", 1).isdigit() else ""
                cells.append(f"<td{cls}>{_h(cell)}</td>")
        cls = ' class="first"' if i < first_rows else ""
        body.append(f"<tr{cls}>{''.join(cells)}</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _plots(result: dict, base: CorpusOutput, new: CorpusOutput) -> list[str]:
    """Per regressed drive (worst first): its heading and plot."""
    order = list(dict.fromkeys(e["drive"] for e in result["regressions"]))
    parts = []
    for name in order:
        entries = [e for e in result["regressions"] if e["drive"] == name]
        png = drive_plot_png(base.drives[name], new.drives[name], entries, result["first_diverging_scan"].get(name))
        parts.append(
            f"<h3>{_h(name)}</h3><p><code>{_h(entries[0]['view'])}</code></p>"
            f'<img alt="{_h(name)}: error and inlier share over the scans, BASE and NEW" src="{data_uri(png)}">'
        )
    return parts


def html_report(result: dict, base: CorpusOutput, new: CorpusOutput) -> str:
    """compare.html's text."""
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8"><title>Corpus comparison</title>',
        f"<style>{CSS}</style></head><body>",
        "<h1>Corpus comparison</h1>",
        f"<p>BASE <code>{_h(result['base'])}</code> → NEW <code>{_h(result['new'])}</code></p>",
        f"<p>{_h(_summary(result))}</p>",
        "<h2>Regressions, worst first</h2>",
    ]
    regressions = result["regressions"]
    if regressions:
        rows = [_cells(i + 1, e) for i, e in enumerate(regressions)]
        parts.append(_html_table(COLUMNS, rows, first_rows=1, code_last=True))
        parts.append("<h2>The regressed drives, BASE and NEW</h2>")
        parts += _plots(result, base, new)
    else:
        parts.append("<p>No regression beyond the seed-to-seed noise.</p>")
    parts.append("<h2>Improvements, best first</h2>")
    if result["improvements"]:
        rows = [_cells(i + 1, e) for i, e in enumerate(result["improvements"])]
        parts.append(_html_table(COLUMNS, rows, code_last=True))
    else:
        parts.append("<p>No improvement beyond the seed-to-seed noise.</p>")
    parts.append(f"<h2>Unchanged drives</h2><p>{_h(', '.join(result['unchanged']) or 'none')}</p>")
    parts.append(
        "<h2>Drives of one run only</h2><ul>"
        f"<li>only in BASE: {_h(', '.join(result['only_in_base']) or 'none')}</li>"
        f"<li>only in NEW: {_h(', '.join(result['only_in_new']) or 'none')}</li></ul>"
    )
    parts.append(f"<h2>Noise</h2><p>{_h(_noise_rule(result))}</p>")
    parts.append(_html_table(NOISE_COLUMNS, _noise_rows(result)))
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def write_reports(result: dict, base: CorpusOutput, new: CorpusOutput, out_dir: Path) -> tuple[Path, Path]:
    """Write compare.md and compare.html into ``out_dir``; their paths."""
    out_dir = Path(out_dir)
    make_out_dir(out_dir)
    md, page = out_dir / "compare.md", out_dir / "compare.html"
    md.write_text(markdown(result))
    page.write_text(html_report(result, base, new))
    return md, page
