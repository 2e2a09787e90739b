"""The evaluation report as one HTML file: the tables, the FID-vs-time plot and the sample animations.

Images are embedded as base64 data URIs, so ``report.html`` opens offline, can be moved or mailed on
its own, and loads nothing from the network (no script, no CDN, no external stylesheet). The same
inputs give the same bytes: nothing in the page depends on the time or the machine.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Sequence

from PIL import Image

from pipelines.report import Section, report_notes, report_sections, report_title, table_cells

MIME_TYPES = {".gif": "image/gif", ".png": "image/png"}

CSS = """
body { font-family: sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.5em; text-align: right; white-space: nowrap; }
th { background: #eee; }
td:first-child, th:first-child { text-align: left; }
tbody tr:nth-child(even) { background: #f7f7f7; }
figure { display: inline-block; margin: 0.5em; }
figcaption { font-size: 0.8em; text-align: center; }
p.note { font-size: 0.9em; max-width: 60em; }
""".strip()


def data_uri(data: bytes, mime: str) -> str:
    """``data:<mime>;base64,...``: the bytes inline, for an ``img`` that needs no other file."""
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def _img(name: str, data: bytes, alt: str) -> str:
    """An ``img`` element of the image file ``name`` (its type from the suffix), with its pixel size."""
    suffix = name[name.rfind("."):].lower() if "." in name else ""
    if suffix not in MIME_TYPES:
        raise ValueError(f"{name}: cannot embed in report.html (known image types: {', '.join(MIME_TYPES)})")
    width, height = Image.open(io.BytesIO(data)).size
    return (f'<img src="{data_uri(data, MIME_TYPES[suffix])}" width="{width}" height="{height}" '
            f'alt="{html.escape(alt)}">')


def _table(section: Section) -> list[str]:
    header, rows = table_cells(section)
    lines = ["<table>", "<thead><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr></thead>",
             "<tbody>"]
    lines += ["<tr>" + "".join(f"<td>{html.escape(cell)}</td>" for cell in cells) + "</tr>" for cells in rows]
    return [*lines, "</tbody>", "</table>"]


def _row_of(sample_name: str) -> str:
    """The row a sample file belongs to: ``<row>_<k>.gif`` -> ``<row>``."""
    stem = sample_name.rsplit(".", 1)[0]
    return stem.rsplit("_", 1)[0]


def report_html(table: dict[str, dict[str, float]], meta: dict[str, object], plot_png: bytes,
                samples: Sequence[tuple[str, bytes]], speed: dict[str, dict[str, float]] | None = None) -> str:
    """The page: title, the tables of :func:`pipelines.report.report_sections`, the notes, the plot, and
    the samples (``(file name, bytes)``) grouped under the row they belong to, rows and files in the given
    order. ``speed``: the side-by-side timing table, if any."""
    title = html.escape(report_title(meta))
    lines = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">', f"<title>{title}</title>",
             f"<style>\n{CSS}\n</style>", "</head>", "<body>", f"<h1>{title}</h1>"]
    for section in report_sections(table, speed):
        if section.heading is not None:
            lines.append(f"<h2>{html.escape(section.heading)}</h2>")
        lines += _table(section)
    lines += [f'<p class="note">{html.escape(note)}</p>' for note in report_notes(table)]
    lines += ["<h2>FID vs inference time</h2>", _img("fid_vs_time.png", plot_png, "FID against AITS per row")]
    if samples:
        lines.append("<h2>Samples</h2>")
        by_row: dict[str, list[tuple[str, bytes]]] = {}
        for name, data in samples:
            by_row.setdefault(_row_of(name), []).append((name, data))
        for row, group in by_row.items():
            lines.append(f"<h3>{html.escape(row)}</h3>")
            lines += [f"<figure>{_img(name, data, name)}<figcaption>{html.escape(name)}</figcaption></figure>"
                      for name, data in group]
    lines += ["</body>", "</html>"]
    return "\n".join(lines) + "\n"
