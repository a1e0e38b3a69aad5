"""The leaderboard's pages, each a function of ``Site`` (everything computed once) returning its HTML.

- ``index.html``: the entries, the two filters and one sortable board per measurement;
- ``entries/<slug>.html``: an entry's card and provenance, its scores overall, by task and by partition, its
  physics readouts, its envelope columns (when results.json has them) and its per-example scores;
- ``compare/index.html`` and ``compare/<a>--<b>.html``: paired differences and probability of improvement;
- ``examples/index.html`` and ``examples/<id>.html``: every entry's scores and readouts on one example, and
  the filmstrips of the clips the submissions include.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from rigidbench.leaderboard.entries import Entry
from rigidbench.leaderboard.html import (NONE, Cell, Column, Row, e, filters, interval, kv_table, metric_heading,
                                         number, page, sort_key, table, text_cell)
from rigidbench.leaderboard.scores import ALL, BoardRow, Comparison, View
from rigidbench.metrics import METRICS
from rigidbench.readouts.flags import FLAGS
from rigidbench.readouts.records import aggregate_readouts, summary
from rigidbench.report.paper import PaperNumbers
from rigidbench.report.tables import decimals_for

#: the readout distributions shown: summary key -> heading
READOUTS = {"speed": "playback speed s^", "gravity": "gravity g^ (m/s\u00b2)", "gravity_per_speed2": "g^ s^-2",
            "restitution": "restitution e^"}


@dataclass(frozen=True)
class Site:
    """Everything the pages show. ``groups``: example id -> (task, partition); ``boards``: metric -> view ->
    rows; ``comparisons``: (a, b) slug pairs, both orders; ``means``: slug -> (M, E) per-example means over
    ``groups``' ids; ``strips``: slug -> id -> filmstrip path under ``out`` or why there is none;
    ``problems``: slug -> why it does not stand on the paper's footing (None: it does); ``decimals``: metric
    -> places shown."""

    out: Path
    entries: tuple[Entry, ...]
    groups: dict[str, tuple[str, str]]
    metrics: tuple[str, ...]
    views: tuple[View, ...]
    boards: dict[str, dict[View, list[BoardRow]]]
    comparisons: dict[tuple[str, str], Comparison]
    means: dict[str, np.ndarray]
    strips: dict[str, dict[str, Path | str]]
    paper: PaperNumbers | None
    problems: dict[str, str | None]
    decimals: dict[str, int]
    resamples: int

    @property
    def tasks(self) -> list[str]:
        return sorted({t for t, _ in self.groups.values()})

    @property
    def partitions(self) -> list[str]:
        return sorted({p for _, p in self.groups.values()})

    @property
    def ids(self) -> list[str]:
        return list(self.groups)

    def entry(self, slug: str) -> Entry:
        return next(x for x in self.entries if x.slug == slug)


def site_decimals(boards: dict[str, dict[View, list[BoardRow]]], paper: PaperNumbers | None) -> dict[str, int]:
    """Places per measurement: enough for ~3 significant digits of the scored means, and at least the paper's."""
    printed = {c.metric: c.decimals for t in (paper.tables_by("model") if paper else ()) for c in t.columns}
    out = {}
    for metric, by_view in boards.items():
        scale = METRICS[metric].display_scale
        values = [r.mean * scale for rows in by_view.values() for r in rows if not r.paper]
        out[metric] = max(decimals_for(values), printed.get(metric, 0))
    return out


def bundle_name(path: Path) -> str:
    """A bundle as its file name, or an extracted folder as "<parent>/submission"."""
    return f"{path.parent.name}/{path.name}" if path.name == "submission" and path.parent.name else path.name


def entry_href(slug: str, root: str) -> str:
    return f"{root}entries/{slug}.html"


def example_href(sample_id: str, root: str) -> str:
    return f"{root}examples/{sample_id}.html"


def pair_href(a: str, b: str, root: str) -> str:
    return f"{root}compare/{a}--{b}.html"


def _rel(path: Path, site: Site, root: str) -> str:
    return root + path.relative_to(site.out).as_posix()


def _paper_note(site: Site) -> str:
    if site.paper is None:
        return ""
    bad = [(x, site.problems.get(x.slug)) for x in site.entries if site.problems.get(x.slug)]
    lines = [f"Rows marked <em>{e(site.paper.marker)}</em> are the paper's means over the "
             f"{site.paper.examples} examples of {e(site.paper.dataset)} {e(site.paper.version)} "
             f"({e(site.paper.protocol)} protocol, {e(site.paper.perception)} perception), as printed in its "
             "tables; they have no interval and no rank. Under a task or partition filter a paper row shows only "
             "where the paper prints a number for that subset. " + e(site.paper.non_finite)]
    if bad:
        lines.append("Marked †: not on the paper's footing, so not directly comparable with its rows: "
                     + "; ".join(f"{e(x.name)} {e(why)}" for x, why in bad) + ".")
    return "".join(f'<p class="note">{line}</p>' for line in lines)


# ------------------------------------------------------------------------------------------ index


def board_rows(site: Site, metric: str, root: str) -> list[Row]:
    """Every view's rows of one measurement's board; only the all-examples view is shown before filtering."""
    scale, dec = METRICS[metric].display_scale, site.decimals[metric]
    out = []
    for view in site.views:
        for r in site.boards[metric][view]:
            if r.paper:
                name = (f'{e(r.name)} <span class="marker">{e(site.paper.marker if site.paper else "")}</span>')
                mean = Cell(e(r.text), sort_key(r.mean))
                samples = Cell(NONE, "")
            else:
                why = site.problems.get(r.key)
                name = (f'<a href="{entry_href(r.key, root)}">{e(r.name)}</a>'
                        + (f' <span class="warn" title="{e(why)}">† not on the paper\'s footing</span>'
                           if why else ""))
                mean = Cell(number(r.mean, dec, scale), sort_key(r.mean))
                samples = Cell(str(r.samples), sort_key(r.samples))
            cells = (Cell(str(r.rank) if r.rank else NONE, sort_key(r.rank)),
                     Cell(name, r.name.lower(), "label", True),
                     mean,
                     Cell(f'<span class="ci">{interval(r.lo, r.hi, dec, scale)}</span>', sort_key(r.lo)),
                     Cell(f"{r.n_finite}/{r.n_examples}", sort_key(r.n_finite)),
                     Cell(number(r.seed_std, dec, scale), sort_key(r.seed_std)),
                     samples)
            out.append(Row(cells, {"data-task": view.task, "data-partition": view.partition,
                                   "data-key": r.key}, hidden=view != ALL, cls="reported" if r.paper else ""))
    return out


BOARD_COLUMNS = (Column("Rank"), Column("Entry", number=False, label=True), Column("Mean"),
                 Column("95% interval"), Column("Examples (finite/all)"), Column("Seed std"), Column("Samples"))


def index_page(site: Site) -> str:
    entries_rows = []
    for x in site.entries:
        d = x.dataset
        dataset = " ".join(str(d[k]) for k in ("dataset", "version") if d.get(k)) or NONE
        if d.get("verified") is True:
            dataset += " (MD5 verified)"
        entries_rows.append(Row((
            Cell(f'<a href="{entry_href(x.slug, "")}">{e(x.name)}</a>', x.name.lower(), "label", True),
            text_cell(_card_text(x.card, "model") or NONE),
            Cell(str(len(x.records)), str(len(x.records))),
            Cell(str(x.samples_per_example), str(x.samples_per_example)),
            text_cell("yes" if x.official else "no"),
            text_cell(dataset), text_cell(x.protocol or NONE), text_cell(x.perception or NONE),
            text_cell("yes" if x.has_videos else "no"))))
    entries_table = table((Column("Entry", number=False, label=True), Column("Model", number=False, label=True),
                           Column("Examples"), Column("Samples per example"),
                           Column("Official", number=False, label=True), Column("Reference set", number=False,
                                                                                label=True),
                           Column("Protocol", number=False, label=True), Column("Perception", number=False,
                                                                                label=True),
                           Column("Clips included", number=False, label=True)), entries_rows, table_id="entries")
    toc = " ".join(f'<a href="#m-{m}">{e(metric_heading(m))}</a>' for m in site.metrics)
    sections = []
    for m in site.metrics:
        info = METRICS[m]
        scale = "" if info.display_scale == 1 else f" Shown \u00d7{info.display_scale:g}."
        caption = (f"{e(info.summary)}; {info.direction} is better.{e(scale)} Mean over examples of each "
                   f"example's mean over its samples, with a 95% percentile bootstrap interval over examples "
                   f"({site.resamples} resamples). Seed std: the standard deviation across sample indices of the "
                   f"whole-set mean ({NONE} with one sample per example).")
        sections.append(f'<section id="m-{m}" aria-labelledby="h-{m}"><h2 id="h-{m}">{e(metric_heading(m))}</h2>'
                        f'<p class="caption">{caption}</p>'
                        + table(BOARD_COLUMNS, board_rows(site, m, ""), cls="board", filter_mode="view",
                                table_id=f"board-{m}") + "</section>")
    body = (f"<h1>RigidBench leaderboard</h1><p class=\"meta\">{len(site.entries)} entries on "
            f"{len(site.groups)} examples ({len(site.tasks)} tasks, {len(site.partitions)} evaluation "
            "partitions). Every number here is computed from the per-example records in the submission bundles; "
            "click a column heading to sort, and choose a task or partition to see that subset.</p>"
            + _paper_note(site) + "<h2 id=\"entries-heading\">Entries</h2>" + entries_table
            + filters(site.tasks, site.partitions) + f'<p class="toc">Measurements: {toc}</p>' + "".join(sections))
    return page("RigidBench leaderboard", body)


def _card_text(card: dict, key: str) -> str:
    v = card.get(key)
    if isinstance(v, dict):
        return " ".join(str(v[k]) for k in ("name", "version") if v.get(k))
    return "" if v is None else str(v)


# ------------------------------------------------------------------------------------------ entries


def _value_cell(mean: float, lo: float, hi: float, dec: int, scale: float) -> Cell:
    return Cell(f'{number(mean, dec, scale)}<span class="ci block">{interval(lo, hi, dec, scale)}</span>',
                sort_key(mean))


def breakdown_table(site: Site, entry: Entry, by: str) -> str:
    """Rows: the tasks (or partitions); columns: the measurements, each mean with its interval."""
    groups = site.tasks if by == "task" else site.partitions
    rows = []
    for g in groups:
        view = View(g, "") if by == "task" else View("", g)
        cells = [text_cell(g, g, header=True)]
        for m in site.metrics:
            r = next(r for r in site.boards[m][view] if r.key == entry.slug)
            cells.append(_value_cell(r.mean, r.lo, r.hi, site.decimals[m], METRICS[m].display_scale))
        n = next(r for r in site.boards[site.metrics[0]][view] if r.key == entry.slug).n_examples
        cells.append(Cell(str(n), str(n)))
        rows.append(Row(tuple(cells)))
    columns = [Column(by.capitalize(), number=False, label=True)] + [Column(metric_heading(m)) for m in site.metrics]
    return table(columns + [Column("Examples")], rows, cls="breakdown", table_id=f"by-{by}")


def readouts_block(entry: Entry) -> dict | None:
    """The entry's readouts block: results.json's, else aggregated from its records' compact summaries."""
    block = entry.results.get("readouts")
    if isinstance(block, dict) and isinstance(block.get("overall"), dict):
        return block
    records = [r for r in entry.records.values() if isinstance(r.get("readouts"), dict)]
    return aggregate_readouts(records) if records else None


def _distribution_text(d) -> str:
    if not isinstance(d, dict) or d.get("median") is None:
        return NONE
    return f"{d['median']:.3g} [{d['q25']:.3g}, {d['q75']:.3g}] ({d.get('finite', 0)}/{d.get('n', 0)})"


def readouts_table(block: dict) -> str:
    groups = [("overall", block.get("overall") or {})]
    groups += [(f"task {k}", v) for k, v in (block.get("by_task") or {}).items()]
    groups += [(f"partition {k}", v) for k, v in (block.get("by_partition") or {}).items()]
    rows = []
    for label, b in groups:
        flags = b.get("flags") or {}
        cells = [text_cell(label, header=True)]
        cells += [Cell(e(_distribution_text(b.get(k))), sort_key((b.get(k) or {}).get("median")))
                  for k in READOUTS]
        for f in FLAGS:
            v = flags.get(f) or {}
            cells.append(Cell(f"{v.get('raised', 0)}/{v.get('defined', 0)}", sort_key(v.get("rate"))))
        rows.append(Row(tuple(cells)))
    columns = ([Column("Examples", number=False, label=True)] + [Column(h) for h in READOUTS.values()]
               + [Column(f"{f} (raised/defined)") for f in FLAGS])
    return table(columns, rows, table_id="readouts")


def _scalar_fields(block: dict) -> list[str]:
    return sorted({k for v in block.values() if isinstance(v, dict) for k, x in v.items()
                   if isinstance(x, (int, float)) and not isinstance(x, bool)})


def envelope_tables(envelope: dict) -> str:
    """results.json's ``envelope`` as tables: for each block (overall, each task, each partition) that maps
    measurements to numbers, one row per measurement and one column per number; anything else as keys and
    values."""
    blocks: list[tuple[str, dict]] = []
    if isinstance(envelope.get("overall"), dict):
        blocks.append(("all examples", envelope["overall"]))
    for key, word in (("by_task", "task"), ("by_partition", "partition")):
        for g, b in sorted((envelope.get(key) or {}).items()):
            if isinstance(b, dict):
                blocks.append((f"{word} {g}", b))
    if not blocks and any(k in METRICS for k in envelope):
        blocks.append(("all examples", envelope))
    if not blocks:
        return kv_table(envelope)
    out = []
    for label, b in blocks:
        fields = _scalar_fields(b)
        metrics = [m for m in METRICS if isinstance(b.get(m), dict)]
        rows = [Row((text_cell(metric_heading(m), header=True),)
                    + tuple(Cell(e(_plain(b[m].get(f))), sort_key(_float(b[m].get(f)))) for f in fields))
                for m in metrics]
        out.append(f"<h3>{e(label)}</h3>" + table([Column("Measurement", number=False, label=True)]
                                                   + [Column(f) for f in fields], rows))
    return "".join(out)


def _float(x):
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else None


def _plain(x) -> str:
    if isinstance(x, float):
        return f"{x:.4g}" if math.isfinite(x) else NONE
    return NONE if x is None else str(x)


def entry_page(site: Site, entry: Entry) -> str:
    root = "../"
    why = site.problems.get(entry.slug)
    reasons = "; ".join(str(r) for r in entry.results.get("why_not_official") or [])
    official = "an official result" if entry.official else "not an official result" + (f": {reasons}" if reasons
                                                                                        else "")
    rows = []
    for m in site.metrics:
        r = next(r for r in site.boards[m][ALL] if r.key == entry.slug)
        dec, scale = site.decimals[m], METRICS[m].display_scale
        rows.append(Row((text_cell(metric_heading(m), m, header=True), Cell(number(r.mean, dec, scale),
                                                                               sort_key(r.mean)),
                         Cell(f'<span class="ci">{interval(r.lo, r.hi, dec, scale)}</span>', sort_key(r.lo)),
                         Cell(f"{r.n_finite}/{r.n_examples}", sort_key(r.n_finite)),
                         Cell(number(r.seed_std, dec, scale), sort_key(r.seed_std)),
                         Cell(str(r.samples), sort_key(r.samples)),
                         Cell(str(r.rank) if r.rank else NONE, sort_key(r.rank)))))
    overall = table((Column("Measurement", number=False, label=True), Column("Mean"), Column("95% interval"),
                     Column("Examples (finite/all)"), Column("Seed std"), Column("Samples"), Column("Rank")),
                    rows, table_id="overall")
    parts = [f"<h1>{e(entry.name)}</h1>",
             f'<p class="meta">Bundle {e(bundle_name(entry.source))}; {e(official)}.</p>',
             f'<p class="note">Not on the paper\'s footing: it {e(why)}.</p>' if why else "",
             '<p class="toc"><a href="#card">Card</a> <a href="#scores">Scores</a> <a href="#by-task-h">By task</a> '
             '<a href="#by-partition-h">By partition</a> <a href="#readouts-h">Physics readouts</a> '
             + ('<a href="#envelope">Physical envelope</a> ' if isinstance(entry.results.get("envelope"), dict)
                else "") + '<a href="#examples-h">Examples</a></p>',
             '<h2 id="card">Submission card</h2>', kv_table(entry.card),
             "<details><summary>Provenance (filled in from the run, never typed)</summary>",
             kv_table(entry.provenance), "</details>",
             '<h2 id="scores">Scores on all examples</h2>', overall,
             '<h2 id="by-task-h">By task</h2>', breakdown_table(site, entry, "task"),
             '<h2 id="by-partition-h">By evaluation partition</h2>', breakdown_table(site, entry, "partition"),
             '<h2 id="readouts-h">Physics readouts</h2>']
    block = readouts_block(entry)
    parts.append('<p class="caption">Median [first quartile, third quartile] (finite/all) of each readout over the '
                 "examples, and how often each failure flag was raised where it is defined (docs/physics.md).</p>"
                 + readouts_table(block) if block else '<p class="meta">This submission has no readouts.</p>')
    if isinstance(entry.results.get("envelope"), dict):
        parts += ['<h2 id="envelope">Physical envelope</h2>', envelope_tables(entry.results["envelope"])]
    parts += ['<h2 id="examples-h">Examples</h2>', filters(site.tasks, site.partitions),
              example_scores_table(site, [entry], root, per_entry=False)]
    return page(f"{entry.name}: RigidBench leaderboard", "".join(parts), root)


def example_scores_table(site: Site, entries: Sequence[Entry], root: str, per_entry: bool,
                         sample_id: str | None = None) -> str:
    """Per-example means: one row per example of one entry (``per_entry`` False; filterable), or one row per
    entry on ``sample_id`` (``per_entry`` True)."""
    ids = site.ids
    rows = []
    if per_entry:
        j = ids.index(sample_id)
        for x in entries:
            if sample_id not in x.records:
                continue
            cells = [Cell(f'<a href="{entry_href(x.slug, root)}">{e(x.name)}</a>', x.name.lower(), "label", True)]
            cells += [Cell(number(site.means[x.slug][m, j], site.decimals[name], METRICS[name].display_scale),
                           sort_key(float(site.means[x.slug][m, j]))) for m, name in enumerate(site.metrics)]
            rows.append(Row(tuple(cells)))
        columns = [Column("Entry", number=False, label=True)]
        return table(columns + [Column(metric_heading(m)) for m in site.metrics], rows, table_id="example-scores")
    x = entries[0]
    strips = site.strips.get(x.slug, {})
    for j, i in enumerate(ids):
        if i not in x.records:
            continue
        task, part = site.groups[i]
        cells = [Cell(f'<a href="{example_href(i, root)}">{e(i)}</a>', i, "label", True), text_cell(task),
                 text_cell(part)]
        cells += [Cell(number(site.means[x.slug][m, j], site.decimals[name], METRICS[name].display_scale),
                       sort_key(float(site.means[x.slug][m, j]))) for m, name in enumerate(site.metrics)]
        cells.append(text_cell("yes" if isinstance(strips.get(i), Path) else "no"))
        rows.append(Row(tuple(cells), {"data-task": task, "data-partition": part}))
    columns = ([Column("Example", number=False, label=True), Column("Task", number=False, label=True),
                Column("Partition", number=False, label=True)] + [Column(metric_heading(m)) for m in site.metrics]
               + [Column("Filmstrip", number=False, label=True)])
    return table(columns, rows, filter_mode="subset", table_id="examples")


# ------------------------------------------------------------------------------------------ comparisons


def compare_index_page(site: Site) -> str:
    root = "../"
    options = "".join(f'<option value="{e(x.slug)}">{e(x.name)}</option>' for x in site.entries)
    second = "".join(f'<option value="{e(x.slug)}"{" selected" if k == 1 else ""}>{e(x.name)}</option>'
                     for k, x in enumerate(site.entries))
    form = ('<form id="compare-form" class="compare">'
            f'<span><label for="compare-a">Entry A</label> <select id="compare-a" name="a">{options}</select></span>'
            f'<span><label for="compare-b">Entry B</label> <select id="compare-b" name="b">{second}</select></span>'
            '<button type="submit">Compare</button><span class="meta" data-compare-message role="status"></span>'
            "</form>")
    rows = []
    for k, xa in enumerate(site.entries):
        for xb in site.entries[k + 1:]:
            n = len(site.comparisons[(xa.slug, xb.slug)].shared)
            rows.append(Row((Cell(f'<a href="{pair_href(xa.slug, xb.slug, root)}">{e(xa.name)} vs {e(xb.name)}</a>',
                                  f"{xa.name} {xb.name}".lower(), "label", True), Cell(str(n), str(n)))))
    listing = table((Column("Comparison", number=False, label=True), Column("Shared examples")), rows,
                    table_id="pairs")
    body = ("<h1>Compare two entries</h1><p class=\"meta\">Paired over the examples both entries hold: the mean "
            "difference A \u2212 B of per-example means and the probability that A is better than B on an example "
            "(ties count one half), each with a 95% percentile bootstrap interval over the matched examples.</p>"
            + (form if len(site.entries) > 1 else '<p class="meta">One entry only: nothing to compare.</p>')
            + "<h2>Every pair</h2>" + listing)
    return page("Compare two entries: RigidBench leaderboard", body, root)


def compare_page(site: Site, c: Comparison) -> str:
    root = "../"
    xa, xb = site.entry(c.a), site.entry(c.b)
    ids = site.ids
    idx = [ids.index(i) for i in c.shared]
    rows = []
    for m, name in enumerate(site.metrics):
        cell = c.cells[name][ALL]
        dec, scale = site.decimals[name], METRICS[name].display_scale
        ma, mb = (finite_mean(site.means[x.slug][m, idx]) for x in (xa, xb))
        rows.append(Row((text_cell(metric_heading(name), name, header=True),
                         Cell(number(ma, dec, scale), sort_key(ma)), Cell(number(mb, dec, scale), sort_key(mb)),
                         _value_cell_signed(cell.diff, cell.diff_lo, cell.diff_hi, dec, scale),
                         Cell(f'{number(cell.poi, 3)}<span class="ci block">{interval(cell.poi_lo, cell.poi_hi, 3)}'
                              "</span>", sort_key(cell.poi)),
                         Cell(str(cell.n), str(cell.n)))))
    overall = table((Column("Measurement", number=False, label=True), Column(f"A: {xa.name}"),
                     Column(f"B: {xb.name}"), Column("A \u2212 B [95% interval]"),
                     Column("P(A better) [95% interval]"), Column("Matched examples")), rows, table_id="paired")
    breakdowns = []
    for by, groups in (("task", site.tasks), ("partition", site.partitions)):
        rows = []
        for g in groups:
            view = View(g, "") if by == "task" else View("", g)
            cells = [text_cell(g, g, header=True)]
            for name in site.metrics:
                cell = c.cells[name][view]
                cells.append(Cell(f'{number(cell.poi, 3)}<span class="ci block">'
                                  f"{interval(cell.poi_lo, cell.poi_hi, 3)}</span>", sort_key(cell.poi)))
            rows.append(Row(tuple(cells)))
        columns = [Column(by.capitalize(), number=False, label=True)] + [Column(metric_heading(m))
                                                                         for m in site.metrics]
        breakdowns.append(f"<h2>Probability that A is better, by {by}</h2>"
                          + table(columns, rows, table_id=f"poi-by-{by}"))
    body = (f'<h1>{e(xa.name)} vs {e(xb.name)}</h1><p class="meta">A: <a href="{entry_href(xa.slug, root)}">'
            f'{e(xa.name)}</a>; B: <a href="{entry_href(xb.slug, root)}">{e(xb.name)}</a>; {len(c.shared)} shared '
            f'examples; {site.resamples} bootstrap resamples. <a href="{pair_href(c.b, c.a, root)}">Swap A and B</a>'
            '.</p><p class="caption">A \u2212 B is in each measurement\'s display units; whether a positive '
            "difference is good depends on its direction (the arrow). P(A better) accounts for the direction: "
            "above 0.5, A is better on most examples.</p>" + overall + "".join(breakdowns))
    return page(f"{xa.name} vs {xb.name}: RigidBench leaderboard", body, root)


def finite_mean(values: np.ndarray) -> float:
    """The mean of the finite values, NaN when there is none."""
    values = values[np.isfinite(values)]
    return float(values.mean()) if values.size else math.nan


def _value_cell_signed(mean: float, lo: float, hi: float, dec: int, scale: float) -> Cell:
    return Cell(f'{number(mean, dec, scale, signed=True)}<span class="ci block">'
                f"{interval(lo, hi, dec, scale, signed=True)}</span>", sort_key(mean))


# ------------------------------------------------------------------------------------------ examples


def examples_index_page(site: Site) -> str:
    root = "../"
    rows = []
    for i, (task, part) in site.groups.items():
        held = [x for x in site.entries if i in x.records]
        clips = [x for x in held if isinstance(site.strips.get(x.slug, {}).get(i), Path)]
        rows.append(Row((Cell(f'<a href="{example_href(i, root)}">{e(i)}</a>', i, "label", True), text_cell(task),
                         text_cell(part), Cell(str(len(held)), str(len(held))),
                         Cell(str(len(clips)), str(len(clips)))), {"data-task": task, "data-partition": part}))
    body = ("<h1>Examples</h1><p class=\"meta\">Every example any entry was scored on. An example's page shows each "
            "entry's scores and readouts on it, and a filmstrip of each clip the submissions include (frames at "
            "0, 0.5, 1, 1.5 and 2 s).</p>" + filters(site.tasks, site.partitions)
            + table((Column("Example", number=False, label=True), Column("Task", number=False, label=True),
                     Column("Partition", number=False, label=True), Column("Entries"), Column("Filmstrips")), rows,
                    filter_mode="subset", table_id="examples"))
    return page("Examples: RigidBench leaderboard", body, root)


def _example_readouts(entry: Entry, sample_id: str) -> dict | None:
    record = entry.records.get(sample_id) or {}
    if isinstance(record.get("readouts"), dict):
        return record["readouts"]
    doc = entry.readouts.get(sample_id)
    if isinstance(doc, dict) and isinstance(doc.get("readouts"), dict):
        try:
            return summary(doc["readouts"])
        except (KeyError, TypeError, AttributeError, ValueError):
            return None
    return None


def example_page(site: Site, sample_id: str) -> str:
    root = "../"
    task, part = site.groups[sample_id]
    ids = site.ids
    k = ids.index(sample_id)
    step = "".join(f'<a href="{example_href(ids[j], root)}">{label}</a> ' for j, label in
                   ((k - 1, "previous example"), (k + 1, "next example")) if 0 <= j < len(ids))
    held = [x for x in site.entries if sample_id in x.records]
    readout_rows = []
    for x in held:
        s = _example_readouts(x, sample_id)
        if s is None:
            continue
        raised = [f for f, v in (s.get("flags") or {}).items() if v]
        readout_rows.append(Row((Cell(f'<a href="{entry_href(x.slug, root)}">{e(x.name)}</a>', x.name.lower(),
                                      "label", True),)
                                + tuple(Cell(e(_plain(s.get(key))), sort_key(_float(s.get(key))))
                                        for key in READOUTS)
                                + (text_cell(", ".join(raised) or "none"),)))
    readouts = (table([Column("Entry", number=False, label=True)] + [Column(h) for h in READOUTS.values()]
                      + [Column("Flags raised", number=False, label=True)], readout_rows, table_id="example-readouts")
                if readout_rows else '<p class="meta">No readouts for this example.</p>')
    strips = []
    for x in held:
        strip = site.strips.get(x.slug, {}).get(sample_id)
        if isinstance(strip, Path):
            strips.append(f'<figure class="strip"><img src="{e(_rel(strip, site, root))}" alt="{e(x.name)}: frames '
                          f'of example {e(sample_id)} at 0, 0.5, 1, 1.5 and 2 s">'
                          f"<figcaption>{e(x.name)}</figcaption></figure>")
        elif isinstance(strip, str):
            strips.append(f'<p class="meta">{e(x.name)}: no filmstrip ({e(strip)}).</p>')
    body = (f"<h1>Example {e(sample_id)}</h1><p class=\"meta\">Task {e(task)}, partition {e(part)}. {step}"
            f'<a href="index.html">all examples</a></p><h2>Scores</h2>'
            + example_scores_table(site, held, root, per_entry=True, sample_id=sample_id)
            + "<h2>Physics readouts</h2>" + readouts + "<h2>Filmstrips</h2>"
            + ("".join(strips) if strips else '<p class="meta">No submission includes the clip of this '
                                              "example.</p>"))
    return page(f"Example {sample_id}: RigidBench leaderboard", body, root)


__all__ = ["READOUTS", "Site", "bundle_name", "compare_index_page", "compare_page", "entry_page", "envelope_tables",
           "example_page", "examples_index_page", "index_page", "readouts_block", "site_decimals"]
