"""report.html: one self-contained page (inline CSS, no scripts) showing every table, figure and example.

The header is short: what was compared, whether it is official (the shared reason said once), and
the measurements that were not computed folded into one collapsible note. Then the model table,
the example filmstrips, the task and partition breakdowns (every measurement in a collapsible
table), the paired comparisons and probability-of-improvement matrices, where a run was scored against a
physical envelope the share inside it and its figure, with several samples per example the best-of-K and power
tables, the fine-tuned checkpoints
(metric-versus-step curves, paired changes against base Wan and the selected checkpoints' tables, only
when some runs are checkpoints), and the runs. A probe report given to `build_report` is linked in the header.

Images, clips and downloads are referenced by paths relative to the report directory, so the
directory can be moved or zipped as a whole; every referenced file is written before the page.
"""

from __future__ import annotations

import html
from pathlib import Path

from rigidbench.report.analysis import ReportData, partition_label, task_label
from rigidbench.report.examples import ExampleStrips, Filmstrips
from rigidbench.report.figures import FigureFile
from rigidbench.report.tables import Table, samples_text, to_html

CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 24px auto; max-width: 1240px;
       color: #1d1d1f; line-height: 1.45; padding: 0 16px; }
h1 { font-size: 26px; margin: 0 0 4px 0; }
h2 { font-size: 20px; margin-top: 40px; border-bottom: 1px solid #ddd; padding-bottom: 2px; }
h3 { font-size: 15px; margin: 22px 0 6px 0; }
.meta { color: #555; font-size: 14px; margin: 0 0 10px 0; }
.status { font-size: 14px; padding: 7px 12px; border-radius: 4px; margin: 8px 0; max-width: 1100px; }
.status.unofficial { background: #fff4e0; border-left: 4px solid #e69a00; }
.status.official { background: #e8f6ec; border-left: 4px solid #2e9d4f; }
.notes { font-size: 14px; margin: 6px 0; padding-left: 20px; max-width: 1100px; } .notes li { margin: 3px 0; }
details.note { font-size: 14px; margin: 6px 0; max-width: 1100px; }
details.note summary { cursor: pointer; color: #333; }
details.note ul { font-size: 13px; color: #444; margin: 6px 0; padding-left: 20px; overflow-wrap: anywhere; }
nav.toc { font-size: 14px; margin: 12px 0 0 0; color: #555; } nav.toc a { margin-right: 12px; }
table { border-collapse: collapse; font-size: 12.5px; margin: 8px 0; font-variant-numeric: tabular-nums; }
th, td { padding: 4px 7px; text-align: right; white-space: nowrap; }
th[scope=row], th:first-child, th.label { text-align: left; }
thead tr:last-child th { border-bottom: 1.5px solid #333; } thead tr:first-child th { border-top: 1.5px solid #333; }
tbody tr:last-child td, tbody tr:last-child th { border-bottom: 1.5px solid #333; }
tr.break td, tr.break th { border-top: 1px solid #999; }
tr.block th { text-align: left; font-weight: 600; font-style: italic; background: #fff8e6; color: #6b4e00; }
.paper-note { color: #6b4e00; font-size: 13px; max-width: 1100px; }
th.group { text-align: center; border-bottom: 1px solid #999; font-weight: 600; }
tbody tr:nth-child(even) { background: #f6f7f9; }
.ci { color: #666; font-size: 11px; } table.results td .ci { display: block; }
.n { color: #a05a00; font-size: 11px; } td.skipped { color: #999; }
table.vertical thead th { vertical-align: bottom; }
table.vertical .vh { writing-mode: vertical-rl; transform: rotate(180deg); white-space: nowrap; display: inline-block;
                     text-align: left; }
table.vertical td { text-align: center; min-width: 34px; }
table.runs td, table.runs th { text-align: left; white-space: normal; vertical-align: top; }
table.runs td.path { overflow-wrap: anywhere; max-width: 360px; }
.caption, figcaption { color: #444; font-size: 13px; max-width: 1100px; }
.downloads { font-size: 13px; } .downloads a { margin-right: 10px; }
figure { margin: 16px 0 28px 0; } figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
.scroll { overflow-x: auto; }
.pair { display: flex; flex-wrap: wrap; gap: 8px 40px; align-items: flex-start; }
.pair > div { flex: 0 1 auto; max-width: 100%; overflow-x: auto; } .pair .caption { max-width: 560px; }
details.more { margin: 10px 0 4px 0; } details.more > summary { cursor: pointer; font-size: 14px; color: #0b57d0; }
.example { margin: 8px 0 26px 0; }
.strips { display: grid; grid-template-columns: 150px minmax(0, var(--strip)); gap: 4px 10px; align-items: center; }
.strips .times { display: flex; justify-content: space-between; font-size: 11.5px; color: #555; }
.strips .times span { flex: 0 0 var(--tile); text-align: center; }
.strips img { width: 100%; height: auto; display: block; }
.strips .label { font-size: 13px; line-height: 1.25; overflow-wrap: anywhere; }
.strips .label small { display: block; color: #666; font-size: 11px; }
.strips .missing { font-size: 12px; color: #999; padding: 6px 0; }
details.clips summary { cursor: pointer; font-size: 13px; color: #0b57d0; margin-top: 6px; }
.clipgrid { display: flex; flex-wrap: wrap; gap: 10px; margin-top: 8px; }
.clipgrid figure { margin: 0; width: 224px; } .clipgrid video { width: 100%; display: block; background: #000; }
.clipgrid figcaption { font-size: 12px; }
"""

# (anchor, heading) of each section, in page order; a section without content is left out.
SECTIONS = (("models", "Model comparison"), ("examples", "Examples"), ("by-task", "By task"),
            ("by-partition", "By evaluation partition"), ("paired", "Paired comparisons"),
            ("envelope", "Against the physical envelope"), ("samples", "Several samples per example"),
            ("checkpoints", "Fine-tuned checkpoints"), ("readouts", "Physics readouts"),
            ("uncertainty", "Uncertainty across all measurements"), ("runs", "Runs"))


def _e(text) -> str:
    return html.escape(str(text))


def _rel(path: Path, root: Path) -> str:
    return _e(path.relative_to(root).as_posix())


def _link(path: Path, root: Path, label: str) -> str:
    return f'<a href="{_rel(path, root)}">{_e(label)}</a>'


def runs_table(data: ReportData, extra_reasons: dict[str, tuple[str, ...]]) -> str:
    """The runs with their provenance; 'Not official because' lists only what a run adds to the shared reason."""
    with_reasons = any(extra_reasons.get(run.name) for run in data.table.runs)
    head = ["Model", "Run directory", "Perception", "Protocol", "Official", "Examples", "Coverage of the span",
            "Failed", "Skipped measurements"]
    head += ["Samples per example"] if data.samples is not None else []
    head += ["Not official because (beyond the reason above)"] if with_reasons else []
    rows = ['<table class="runs"><thead><tr>' + "".join(f"<th>{_e(h)}</th>" for h in head) + "</tr></thead><tbody>"]
    for run in data.table.runs:
        skipped = ", ".join(_e(m) for m in run.skipped_metrics) or "none"  # the reasons are in the header note
        failed = str(len(run.failed)) if not run.failed else (
            f'<span title="{_e("; ".join(f"{k}: {v}" for k, v in run.failed.items()))}">{len(run.failed)}</span>')
        backend = run.perception + (f" (v{run.perception_version})" if run.perception_version else "")
        total = f"{run.n_examples}" + (f" of {run.n_reference}" if run.n_reference is not None else "")
        cells = [f'<th scope="row">{_e(run.name)}</th>', f'<td class="path">{_e(run.path)}</td>',
                 f"<td>{_e(backend)}</td>", f"<td>{_e(run.protocol or 'unrecorded')}</td>",
                 f"<td>{'yes' if run.official else 'no'}</td>", f"<td>{total}</td>",
                 f"<td>{_e(run.coverage_text)}</td>", f"<td>{failed}</td>", f"<td>{skipped}</td>"]
        if data.samples is not None:
            cells.append(f"<td>{_e(samples_text(*data.samples.samples[data.table.runs.index(run)]))}</td>")
        if with_reasons:
            cells.append(f"<td>{_e('; '.join(extra_reasons.get(run.name, ()))) or '—'}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    rows.append("</tbody></table>")
    return "\n".join(rows)


def header(data: ReportData, notes, probe: tuple[str, str] | None = None) -> list[str]:
    """Title, one line of what was compared, the official status once, and the notes (skip reasons folded);
    probe: (href, note) of a probe report to link."""
    t = data.table
    backends = sorted({run.perception for run in t.runs})
    meta = [f"{len(t.models)} run{'s' if len(t.models) != 1 else ''}",
            f"{len(t.example_ids)} shared example{'s' if len(t.example_ids) != 1 else ''}",
            f"{' / '.join(backends)} perception",
            f"protocol {' / '.join(sorted({run.protocol or 'unrecorded' for run in t.runs}))}",
            f"reference set {' / '.join(sorted({run.dataset_text for run in t.runs}))}",
            f"95% percentile bootstrap intervals ({data.resamples:,} resamples over examples, seed {data.seed})"]
    if data.samples is not None:
        most = int(data.samples.samples[:, 1].max())
        meta.append(f"up to {most} samples per example: mean ± seed std")
    if len(t.models) > 1:
        meta.append(f"paired comparisons with <b>{_e(t.models[data.baseline])}</b>")
    parts = ["<h1>RigidBench report</h1>",
             '<p class="meta">' + " · ".join(m if m.startswith("paired") else _e(m) for m in meta) + "</p>",
             f'<p class="status {"official" if notes.official else "unofficial"}">{_e(notes.status)}</p>']
    if probe is not None:
        parts.append(f'<p class="meta">Probe report: <a href="{_e(probe[0])}">{_e(probe[0])}</a>{_e(probe[1])}</p>')
    if notes.general:
        parts.append('<ul class="notes">' + "".join(f"<li>{_e(n)}</li>" for n in notes.general) + "</ul>")
    if notes.skipped:
        parts.append(f'<details class="note"><summary>{_e(notes.skipped_summary)}: why, and how to compute '
                     "them</summary><ul>" + "".join(f"<li>{_e(n)}</li>" for n in notes.skipped) + "</ul></details>")
    return parts


def _table_block(tb: Table, files: dict, root: Path, heading: str = "h3") -> list[str]:
    links = [_link(files["md"], root, "Markdown"), _link(files["tex"], root, "LaTeX")]
    links += [_link(p, root, p.name) for p in files.get("csv", [])]
    title = [f"<{heading}>{_e(tb.title)}</{heading}>"] if heading else []
    return title + [f'<div class="scroll">{to_html(tb)}</div>', f'<p class="downloads">Download: {" ".join(links)}</p>']


def _figure_block(fig: FigureFile, root: Path, heading: str = "h3") -> list[str]:
    return ([f"<{heading}>{_e(fig.title)}</{heading}>"] if heading else []) + [
        "<figure>",
        f'<img src="{_rel(fig.png, root)}" alt="{_e(fig.title)}" width="{round(fig.width_in * 96)}">',
        f"<figcaption>{_e(fig.caption)} {_link(fig.pdf, root, 'PDF')}</figcaption>", "</figure>"]


def example_block(ex: ExampleStrips, root: Path) -> list[str]:
    """One example: a time ruler, then one filmstrip row per run (reference first), then the clips folded."""
    title = f"Example {ex.sample_id} · {task_label(ex.task)} · {partition_label(ex.partition)}"
    style = f"--strip: {ex.strip_css}px; --tile: {100 * ex.tile_css / ex.strip_css:.2f}%"
    if ex.cropped:
        title += " · cropped around the moving objects"
    parts = [f'<div class="example"><h3>{_e(title)}</h3>', f'<div class="strips" style="{style}">',
             '<div></div><div class="times">' + "".join(f"<span>t = {s:.2f} s</span>" for s in ex.times_s) + "</div>"]
    for row in ex.rows:
        sub = " · ".join(x for x in (row.scores, row.note if row.image is not None else "") if x)
        parts.append(f'<div class="label"><b>{_e(row.label)}</b>' + (f"<small>{_e(sub)}</small>" if sub else "")
                     + "</div>")
        if row.image is not None:
            parts.append(f'<img src="{_rel(row.image, root)}" alt="{_e(row.label)}, example {_e(ex.sample_id)}" '
                         f'width="{ex.strip_css}">')
        else:
            parts.append(f'<div class="missing">{_e(row.note)}</div>')
    parts.append("</div>")
    clips = [row for row in ex.rows if row.video is not None]
    if clips:
        parts.append('<details class="clips"><summary>Play the whole frames as looping clips</summary>'
                     '<div class="clipgrid">')
        parts += [f'<figure><video src="{_rel(row.video, root)}" autoplay loop muted playsinline preload="auto">'
                  f"</video><figcaption>{_e(row.label)}</figcaption></figure>" for row in clips]
        parts.append("</div></details>")
    parts.append("</div>")
    return parts


def examples_caption(strips: Filmstrips) -> str:
    perceived = any(ex.outlines == "perceived" for ex in strips.examples)
    outlines = ("the reference's ground-truth masks on the reference and, on a prediction, the masks perception "
                "found in it" if perceived else
                "where the reference's objects are at that moment, on every row: on a prediction, an object off its "
                "outline moved differently from the reference")
    return ("Each row shows one clip at the same moments (columns): the reference first, then every run's "
            f"prediction, with that example's scores. Coloured outlines mark the moving objects: {outlines}. The "
            "examples are one per task where the runs' ATE-3D differs most.")


def render_page(data: ReportData, notes, tables: list[Table], table_files: dict[str, dict[str, Path]],
                figures: list[FigureFile], root: Path, strips: Filmstrips | None = None, checkpoints=None,
                probe: tuple[str, str] | None = None, paper_note: str = "") -> str:
    """The whole report page; every path it references lies under `root` (but a linked probe report).

    checkpoints: a CheckpointSweep (report/checkpoints.py) or None; probe: (href, note) of a probe report;
    paper_note: the line saying why the paper's numbers are not beside the runs ("" when they are, or none)."""
    tb = {table.key: table for table in tables}
    fig = {f.key: f for f in figures}
    strips = strips or Filmstrips(())
    body: dict[str, list[str]] = {}

    def table(key: str, heading: str = "h3") -> list[str]:
        return _table_block(tb[key], table_files[key], root, heading) if key in tb else []

    def figure(key: str, heading: str = "h3") -> list[str]:
        return _figure_block(fig[key], root, heading) if key in fig else []

    def folded(key: str) -> list[str]:
        if key not in tb:
            return []
        return [f'<details class="more"><summary>{_e(tb[key].title)}</summary>'] + table(key, "") + ["</details>"]

    body["models"] = ([f'<p class="paper-note">{_e(paper_note)}</p>'] if paper_note else []) \
        + table("model_metrics", "") + figure("ssim_vs_ate3d")
    if strips.examples or strips.note:
        captions = ([examples_caption(strips)] if strips.examples else []) + ([strips.note] if strips.note else [])
        body["examples"] = [f'<p class="caption">{_e(c)}</p>' for c in captions]
        for ex in strips.examples:
            body["examples"] += example_block(ex, root)
    body["by-task"] = table("by_task", "") + folded("all_by_task")
    if "ate3d_by_task" in fig:
        body["by-task"] += [f'<details class="more"><summary>{_e(fig["ate3d_by_task"].title)} as a bar chart'
                            "</summary>"] + figure("ate3d_by_task", "") + ["</details>"]
    body["by-partition"] = table("by_partition", "") + folded("all_by_partition")
    poi = [key for key in tb if key.startswith("poi_")]
    paired = table("paired_changes", "")
    if poi:
        paired += ["<h3>Probability of improvement between models</h3>", '<div class="pair">']
        paired += [f"<div>{''.join(table(key, ''))}</div>" for key in poi]
        paired.append("</div>")
    if "poi_heatmaps" in fig:
        paired += ['<details class="more"><summary>Every measurement as a heatmap</summary>']
        paired += figure("poi_heatmaps", "") + ["</details>"]
    body["paired"] = paired
    body["envelope"] = table("envelope", "") + table("envelope_widths") + next(
        (figure(key) for key in fig if key.startswith("envelope_")), [])
    body["samples"] = table("best_of_k") + table("power")
    if checkpoints is not None:
        n_runs, n_ckpt = len(checkpoints.runs), len(checkpoints.checkpoints)
        intro = (f"{n_ckpt} evaluated checkpoint{'s' if n_ckpt != 1 else ''}"
                 f" from {n_runs} training run{'s' if n_runs != 1 else ''} ({', '.join(checkpoints.runs)})"
                 + (f", compared with base Wan ({data.table.models[checkpoints.base]})."
                    if checkpoints.base is not None else "."))
        body["checkpoints"] = [f'<p class="caption">{_e(intro)}</p>']
        if checkpoints.notes:
            body["checkpoints"].append('<ul class="notes">' + "".join(f"<li>{_e(n)}</li>" for n in checkpoints.notes)
                                       + "</ul>")
        body["checkpoints"] += figure("metric_vs_step")
        for key in ("checkpoint_sweep", "checkpoint_paired", "checkpoint_selected_paired",
                    "checkpoint_selected_tasks", "checkpoint_selected_partitions"):
            body["checkpoints"] += table(key)
    body["readouts"] = table("readouts", "") + figure("readouts", "")  # beside the ten measurements, not inside
    body["uncertainty"] = figure("metric_intervals", "")
    body["runs"] = ['<div class="scroll">', runs_table(data, notes.extra_reasons), "</div>"]

    sections = [(anchor, title) for anchor, title in SECTIONS if body.get(anchor)]
    if "paired_changes" in tb:
        sections = [(a, tb["paired_changes"].title if a == "paired" else t) for a, t in sections]
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             '<meta name="viewport" content="width=device-width, initial-scale=1">',
             "<title>RigidBench report</title>", f"<style>{CSS}</style></head><body>"]
    parts += header(data, notes, probe)
    parts.append('<nav class="toc">' + "".join(f'<a href="#{a}">{_e(t)}</a>' for a, t in sections) + "</nav>")
    for anchor, title in sections:
        parts += [f'<section id="{anchor}">', f"<h2>{_e(title)}</h2>", *body[anchor], "</section>"]
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"
