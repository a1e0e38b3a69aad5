"""HTML building blocks of the leaderboard site: the page frame, escaping, sortable tables, key-value tables and
number cells. Every link is relative (``root`` is "" for a page at the site's top, "../" one folder down).
"""

from __future__ import annotations

import html
import math
from dataclasses import dataclass, field
from typing import Sequence

from rigidbench import __version__
from rigidbench.metrics import METRICS
from rigidbench.report.tables import fmt, interval_text, metric_label

NONE = "\u2014"  # what an empty cell shows


def e(text) -> str:
    """Text escaped for HTML (quotes included)."""
    return html.escape(str(text), quote=True)


def number(x: float, decimals: int, scale: float = 1.0, signed: bool = False) -> str:
    """x x scale at ``decimals`` places, or the dash when it is not finite."""
    return fmt(x * scale, decimals, signed) if x is not None and math.isfinite(x) else NONE


def interval(lo: float, hi: float, decimals: int, scale: float = 1.0, signed: bool = False) -> str:
    """'[lo, hi]' x scale, or the dash when undefined (fewer than two examples)."""
    text = interval_text(lo * scale, hi * scale, decimals, signed)
    return text or NONE


def sort_key(x) -> str:
    """A number for ``data-sort`` (repr, exact), or "" for a missing one (sorted last)."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return ""
    return repr(float(x)) if isinstance(x, float) else str(x)


def metric_heading(metric: str) -> str:
    """'IoU ↑' / 'BGDrift×10³ ↓': the display name, its display scale and its direction."""
    return f"{metric_label(metric)} {METRICS[metric].arrow}"


@dataclass(frozen=True)
class Cell:
    """One table cell: ``html`` (already escaped), ``sort`` (the data-sort value; None: its text), ``cls``."""

    html: str
    sort: str | None = None
    cls: str = ""
    header: bool = False  # a row header (<th scope="row">)


@dataclass(frozen=True)
class Row:
    cells: tuple[Cell, ...]
    attrs: dict[str, str] = field(default_factory=dict)  # data-task, data-partition, ...
    hidden: bool = False
    cls: str = ""


@dataclass(frozen=True)
class Column:
    """A column heading (plain text); ``number``: sorted as numbers; ``sortable``: a header button; ``label``:
    a left-aligned text column."""

    heading: str
    number: bool = True
    sortable: bool = True
    label: bool = False


def text_cell(text, sort=None, header: bool = False) -> Cell:
    return Cell(e(text), None if sort is None else str(sort), "label", header)


def table(columns: Sequence[Column], rows: Sequence[Row], *, cls: str = "", filter_mode: str | None = None,
          caption: str = "", table_id: str = "") -> str:
    """A table whose sortable headers are buttons (Enter and Space sort, as a click does; assets.JS);
    ``filter_mode`` "view" or "subset" lets the page's filters show and hide its rows."""
    attrs = (f' id="{e(table_id)}"' if table_id else "") + (f' class="{e(cls)}"' if cls else "") + (
        f' data-filter="{e(filter_mode)}"' if filter_mode else "")
    head = []
    for k, col in enumerate(columns):
        th_attrs = ' scope="col"' + (' class="label"' if col.label else "")
        if col.sortable:
            th_attrs += f' aria-sort="none" data-type="{"number" if col.number else "text"}"'
            inner = f'<button type="button" class="sort" data-col="{k}">{e(col.heading)}</button>'
        else:
            inner = e(col.heading)
        head.append(f"<th{th_attrs}>{inner}</th>")
    body = []
    for row in rows:
        r_attrs = "".join(f' {k}="{e(v)}"' for k, v in row.attrs.items())
        r_attrs += (f' class="{e(row.cls)}"' if row.cls else "") + (" hidden" if row.hidden else "")
        cells = []
        for cell in row.cells:
            tag = "th" if cell.header else "td"
            c_attrs = (' scope="row"' if cell.header else "") + (f' class="{e(cell.cls)}"' if cell.cls else "")
            c_attrs += f' data-sort="{e(cell.sort)}"' if cell.sort is not None else ""
            cells.append(f"<{tag}{c_attrs}>{cell.html}</{tag}>")
        body.append(f"<tr{r_attrs}>{''.join(cells)}</tr>")
    cap = f"<caption class=\"caption\">{caption}</caption>" if caption else ""
    return (f'<div class="scroll"><table{attrs}>{cap}<thead><tr>{"".join(head)}</tr></thead>'
            f'<tbody>{"".join(body)}</tbody></table></div>')


def flatten(value, prefix: str = "") -> list[tuple[str, str]]:
    """(dotted key, text) for every leaf of a card or provenance mapping; lists of plain values are joined."""
    if isinstance(value, dict):
        if not value:
            return [(prefix, NONE)] if prefix else []
        out = []
        for k, v in value.items():
            out += flatten(v, f"{prefix}.{k}" if prefix else str(k))
        return out
    if isinstance(value, list):
        if all(not isinstance(v, (dict, list)) for v in value):
            return [(prefix, ", ".join(_leaf(v) for v in value) or NONE)]
        out = []
        for k, v in enumerate(value):
            out += flatten(v, f"{prefix}[{k}]")
        return out
    return [(prefix, _leaf(value))]


def _leaf(v) -> str:
    if v is None:
        return NONE
    if isinstance(v, bool):
        return "yes" if v else "no"
    return str(v)


def kv_table(mapping: dict, caption: str = "") -> str:
    """A two-column table of ``flatten(mapping)``."""
    rows = "".join(f'<tr><th scope="row">{e(k)}</th><td>{e(v)}</td></tr>' for k, v in flatten(mapping))
    cap = f'<caption class="caption">{e(caption)}</caption>' if caption else ""
    return f'<div class="scroll"><table class="kv">{cap}<tbody>{rows}</tbody></table></div>'


def filters(tasks: Sequence[str], partitions: Sequence[str]) -> str:
    """The two labelled filters of a page (assets.JS applies them to its tables with ``data-filter``)."""
    def select(ident: str, label: str, values: Sequence[str], every: str) -> str:
        options = f'<option value="">{e(every)}</option>' + "".join(
            f'<option value="{e(v)}">{e(v)}</option>' for v in values)
        return f'<span><label for="{ident}">{e(label)}</label><select id="{ident}">{options}</select></span>'

    return ('<div class="filters" role="group" aria-label="Filters">'
            + select("filter-task", "Task", tasks, "all tasks")
            + select("filter-partition", "Partition", partitions, "all partitions")
            + '<span class="meta">showing: <span data-filter-label>all examples</span></span></div>'
            + '<noscript><p class="meta">The filters and sorting need JavaScript; without it the tables show all '
              'examples.</p></noscript>')


NAV = (("index.html", "Leaderboard"), ("compare/index.html", "Compare two entries"),
       ("examples/index.html", "Examples"))


def page(title: str, body: str, root: str = "") -> str:
    """A whole page: the shared style sheet and script by relative path, the site navigation, ``body``."""
    nav = "".join(f'<a href="{root}{href}">{e(label)}</a>' for href, label in NAV)
    return ("<!doctype html>\n"
            '<html lang="en"><head><meta charset="utf-8">'
            '<meta name="viewport" content="width=device-width, initial-scale=1">'
            f'<title>{e(title)}</title><link rel="icon" href="data:,">'
            f'<link rel="stylesheet" href="{root}assets/style.css"></head>\n<body>\n'
            f'<nav class="site" aria-label="Site">{nav}</nav>\n<main>\n{body}\n</main>\n'
            f'<footer>Written by <code>rigidbench leaderboard</code> (RigidBench {e(__version__)}). A static site: '
            'it fetches nothing when viewed.</footer>\n'
            f'<script src="{root}assets/leaderboard.js"></script>\n</body></html>\n')


__all__ = ["Cell", "Column", "NONE", "Row", "e", "filters", "flatten", "interval", "kv_table", "metric_heading",
           "number", "page", "sort_key", "table", "text_cell"]
