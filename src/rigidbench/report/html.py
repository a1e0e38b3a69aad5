"""report.html: one self-contained page (inline CSS, no scripts) showing every table and figure.

Images and downloads are referenced by paths relative to the report directory, so the directory
can be moved or zipped as a whole; every referenced file is written before the page.
"""

from __future__ import annotations

import html
from pathlib import Path

from rigidbench.report.analysis import ReportData
from rigidbench.report.figures import FigureFile
from rigidbench.report.tables import Table, to_html

CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 24px auto; max-width: 1240px;
       color: #1d1d1f; line-height: 1.45; padding: 0 16px; }
h1 { font-size: 26px; margin-bottom: 4px; } h2 { font-size: 20px; margin-top: 36px; border-bottom: 1px solid #ddd; }
.meta { color: #555; font-size: 14px; } .notes li { margin: 4px 0; }
table { border-collapse: collapse; font-size: 12.5px; margin: 8px 0; font-variant-numeric: tabular-nums; }
th, td { padding: 4px 8px; text-align: right; white-space: nowrap; }
th[scope=row], th:first-child, th.label { text-align: left; }
thead tr:last-child th { border-bottom: 1.5px solid #333; } thead tr:first-child th { border-top: 1.5px solid #333; }
tbody tr:last-child td, tbody tr:last-child th { border-bottom: 1.5px solid #333; }
tr.break td, tr.break th { border-top: 1px solid #999; }
th.group { text-align: center; border-bottom: 1px solid #999; font-weight: 600; }
tbody tr:nth-child(even) { background: #f6f7f9; }
.ci { color: #666; font-size: 11px; } table.results td .ci { display: block; }
.n { color: #a05a00; font-size: 11px; } td.skipped { color: #999; }
table.runs td, table.runs th { text-align: left; white-space: normal; vertical-align: top; }
.caption, figcaption { color: #444; font-size: 13px; max-width: 1100px; }
.downloads { font-size: 13px; } .downloads a { margin-right: 10px; }
figure { margin: 16px 0 28px 0; } figure img { max-width: 100%; border: 1px solid #eee; }
.scroll { overflow-x: auto; }
"""


def _link(path: Path, root: Path, label: str) -> str:
    return f'<a href="{html.escape(path.relative_to(root).as_posix())}">{html.escape(label)}</a>'


def runs_table(data: ReportData) -> str:
    """The list of runs with their provenance: perception backend, official flag, skipped measurements."""
    rows = ["<table class=\"runs\"><thead><tr><th>Model</th><th>Run directory</th><th>Perception</th>"
            "<th>Official</th><th>Examples</th><th>Failed</th><th>Skipped measurements</th>"
            "<th>Not official because</th></tr></thead><tbody>"]
    for run in data.table.runs:
        skipped = ", ".join(html.escape(m) for m in run.skipped_metrics) or "none"  # reasons: in the notes
        failed = str(len(run.failed)) if not run.failed else (
            f'<span title="{html.escape("; ".join(f"{k}: {v}" for k, v in run.failed.items()))}">'
            f"{len(run.failed)}</span>")
        backend = run.perception + (f" (v{run.perception_version})" if run.perception_version else "")
        total = f"{run.n_examples}" + (f" of {run.n_reference}" if run.n_reference is not None else "")
        rows.append(f"<tr><th scope=\"row\">{html.escape(run.name)}</th><td>{html.escape(str(run.path))}</td>"
                    f"<td>{html.escape(backend)}</td><td>{'yes' if run.official else 'no'}</td><td>{total}</td>"
                    f"<td>{failed}</td><td>{skipped}</td>"
                    f"<td>{html.escape('; '.join(run.why_not_official)) or '—'}</td></tr>")
    rows.append("</tbody></table>")
    return "\n".join(rows)


def render_page(data: ReportData, notes: list[str], tables: list[Table], table_files: dict[str, dict[str, Path]],
                figures: list[FigureFile], root: Path) -> str:
    """The whole report page; every path it references lies under `root`."""
    t = data.table
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             "<title>RigidBench report</title>", f"<style>{CSS}</style></head><body>",
             "<h1>RigidBench report</h1>",
             f'<p class="meta">{len(t.models)} run(s) on {len(t.example_ids)} shared examples · '
             f"95% percentile bootstrap intervals, {data.resamples:,} resamples over examples, seed {data.seed}"
             + (f" · paired comparisons against <b>{html.escape(t.models[data.baseline])}</b>"
                if len(t.models) > 1 else "") + "</p>"]
    if notes:
        parts.append('<ul class="notes">' + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>")
    parts += ["<h2>Runs</h2>", '<div class="scroll">', runs_table(data), "</div>"]
    figure_by_key = {f.key: f for f in figures}
    order = [("table", "model_metrics"), ("figure", "ssim_vs_ate3d"), ("figure", "metric_intervals"),
             ("table", "ate3d_by_task"), ("figure", "ate3d_by_task"), ("table", "by_partition"),
             ("table", "paired_changes"), ("figure", "poi_heatmaps")]
    table_by_key = {tb.key: tb for tb in tables}
    for kind, key in order:
        if kind == "table" and key in table_by_key:
            tb = table_by_key[key]
            files = table_files[key]
            links = [_link(files["md"], root, "Markdown"), _link(files["tex"], root, "LaTeX")]
            links += [_link(p, root, p.name) for p in files.get("csv", [])]
            parts += [f"<h2>{html.escape(tb.title)}</h2>", f'<div class="scroll">{to_html(tb)}</div>',
                      f'<p class="downloads">Download: {" ".join(links)}</p>']
        elif kind == "figure" and key in figure_by_key:
            fig = figure_by_key[key]
            src = fig.png.relative_to(root).as_posix()
            parts += [f"<h2>{html.escape(fig.title)}</h2>", "<figure>",
                      f'<img src="{html.escape(src)}" alt="{html.escape(fig.title)}" '
                      f'style="width: {round(fig.width_in * 96)}px">',  # natural size at CSS 96 dpi
                      f"<figcaption>{html.escape(fig.caption)} {_link(fig.pdf, root, 'PDF')}</figcaption>",
                      "</figure>"]
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"
