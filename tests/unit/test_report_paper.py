"""The paper's rows in `rigidbench report`: beside runs on the verified published set under rigidbench-v1 only.

Fake run folders in the format `rigidbench evaluate` writes: 100 example records (five tasks x four
partitions x five), results.json with the reference set's identity and the protocol, run.json. One report
over a comparable run must carry the paper's rows in the model, task and partition tables (HTML, Markdown,
LaTeX, CSV), labelled and never ranked; a report over an unverified copy carries one line saying why and no
paper row; every other reason is checked on the loaded table, without drawing a report.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from rigidbench.metrics import METRICS
from rigidbench.report import build_report, load_runs
from rigidbench.report.paper import comparison_problem, load_paper_numbers
from fixtures.report_files import read_csv

MARKER = "reported in the paper, not re-scored here"
TASKS = ("ball_chain", "ramp_collision", "drop_into_cluster", "bounce", "free_fall")
PARTITIONS = ("in_distribution", "ood_scene", "ood_object", "ood_both")
PUBLISHED = {"dataset": "rigidbench-eval", "version": "1.1", "id": "rigidbench-eval-v1.1",
             "md5": "b563f279451e95fe2f32d7e258588636", "verified": True, "verification": "archive MD5 matched"}


def write_run(root: Path, name: str, dataset: dict | None = PUBLISHED, protocol: str | None = "rigidbench-v1",
              perception: str = "neural", n: int = 100, seed: int = 0) -> Path:
    """runs/<name>/ with n scored examples (every task and partition equally often when n = 100)."""
    rng = np.random.default_rng(seed)
    run_dir = root / name
    (run_dir / "examples").mkdir(parents=True)
    for i in range(n):
        metrics = {m: float(rng.uniform(0.1, 0.9)) for m in METRICS}
        metrics["bgdrift"] = float(rng.uniform(0.0005, 0.002))
        record = {"id": f"{i:05d}", "model": name, "task": TASKS[i % 5], "partition": PARTITIONS[(i // 5) % 4],
                  "metrics": metrics, "skipped": {}}
        (run_dir / "examples" / f"{i:05d}.json").write_text(json.dumps(record))
    results = {"model": name, "perception": perception, "official": False, "n_examples": n, "n_reference": n,
               "failed": {}, "skipped_metrics": {}, "why_not_official": ["a test run"]}
    if dataset is not None:
        results["dataset"] = dataset
    if protocol is not None:
        results["protocol"] = {"name": protocol}
    (run_dir / "results.json").write_text(json.dumps(results))
    (run_dir / "run.json").write_text(json.dumps({"model": name, "perception": {"backend": perception}}))
    return run_dir



@pytest.fixture(scope="module")
def comparable(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("paper-yes")
    runs = [write_run(root / "runs", "my-model"), write_run(root / "runs", "other-model", seed=1)]
    return build_report(runs, root / "out", resamples=200, seed=0, examples=0)


@pytest.fixture(scope="module")
def unverified(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("paper-no")
    dataset = {k: v for k, v in PUBLISHED.items() if k not in ("verified", "verification")}  # `verified` missing
    run = write_run(root / "runs", "my-model", dataset=dataset)
    return run, build_report([run], root / "out", resamples=200, seed=0, examples=0)


def md_rows(path: Path) -> dict[str, list[str]]:
    """First cell -> the other cells of each body row of the Markdown table in `path`."""
    lines = [line for line in path.read_text().splitlines() if line.startswith("| ")][2:]
    cells = [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines]
    return {row[0]: row[1:] for row in cells}


def test_comparable_runs_get_the_papers_model_rows_labelled_and_unranked(comparable):
    out = comparable.parent
    paper = load_paper_numbers()
    rows = md_rows(out / "tables" / "model_metrics.md")
    heading = [k for k in rows if MARKER in k.lower()]
    assert len(heading) == 1 and "tab:model-results" in heading[0]  # one labelled block
    names = [k for k in rows if k.endswith("(paper)")]
    assert names == [f"{r.name} (paper)" for r in paper.tables["model-results"].rows]  # all eight, in order
    k_bg, k_ate3d = list(METRICS).index("bgdrift"), list(METRICS).index("ate3d")
    assert rows["Wan 2.2 (paper)"][k_bg] == "0.739"  # as printed, x 10^3 like the runs' column
    assert rows["Grok Imagine (paper)"][k_ate3d] == "2.30"
    assert rows["Veo 3.1 (paper)"][list(METRICS).index("iddrift")] == "0.516 (n=98)"
    assert not any("**" in c or "<u>" in c for name in names for c in rows[name])  # never ranked
    # The runs keep their marks: the paper's SSIM (0.72-0.93) beats theirs (about 0.5), yet a run is best.
    k_ssim = list(METRICS).index("ssim")
    assert sorted(rows[m][k_ssim].startswith("**") for m in ("my-model", "other-model")) == [False, True]
    # HTML: the block heading spans the table, the rows follow it
    page = comparable.read_text()
    table = page[page.index('id="table-model_metrics"'):]
    table = table[:table.index("</table>")]
    assert re.search(r'<tr class="block break"><th colspan="11" scope="colgroup">Reported in the paper, not '
                     r"re-scored here: Full model comparison \(tab:model-results", table)
    assert table.count("(paper)</th>") == 8 and "<strong>" not in table[table.index("(paper)"):]
    assert "The paper&#x27;s numbers are not shown" not in page
    tex = (out / "tables" / "model_metrics.tex").read_text()
    assert r"\multicolumn{11}{l}{\emph{Reported in the paper, not re-scored here" in tex
    # CSV: unscaled, with the marker as source; the run's rows say "scored here"
    csv_rows = read_csv(out / "tables" / "model_metrics.csv")
    assert {r["source"] for r in csv_rows if r["model"] in ("my-model", "other-model")} == {"scored here"}
    paper_rows = [r for r in csv_rows if r["source"] == MARKER]
    assert len(paper_rows) == 80
    bg = next(r for r in paper_rows if r["model"] == "Wan 2.2 (paper)" and r["metric"] == "bgdrift")
    assert (float(bg["mean"]), bg["ci_low"], bg["n_examples"], bg["mark"]) == (0.000739, "", "100", "")


def test_comparable_runs_get_the_papers_task_and_partition_rows(comparable):
    out = comparable.parent
    tasks = md_rows(out / "tables" / "by_task.md")
    # ATE-3D then SSIM columns, five tasks each: the paper reports ATE-3D by task only
    assert tasks["Wan 2.2 (paper)"] == ["1.02", "1.39", "1.78", "3.70", "5.30"] + ["—"] * 5
    assert tasks["Wan 2.2 full FT 2.5k (paper)"][:5] == ["0.78", "1.12", "1.51", "3.21", "3.94"]
    assert sum(k.endswith("(paper)") for k in tasks) == 10  # 8 models + 2 checkpoints; base Wan once
    parts = md_rows(out / "tables" / "by_partition.md")
    assert parts["Wan 2.2 LoRA 1k (paper)"] == ["2.20", "2.18", "3.36", "1.50", "0.948", "0.916", "0.946", "0.906"]
    assert sum(k.endswith("(paper)") for k in parts) == 3
    by_task = read_csv(out / "tables" / "by_task.csv")
    cell = [r for r in by_task if r["model"] == "Wan 2.2 (paper)" and r["task"] == "free_fall"]
    assert len(cell) == 1 and (float(cell[0]["mean"]), cell[0]["source"], cell[0]["n_examples"]) == (5.3, MARKER, "20")
    by_partition = read_csv(out / "tables" / "by_partition.csv")
    both = {(r["model"], r["metric"]) for r in by_partition if r["source"] == MARKER and r["partition"] == "ood_both"}
    assert both == {(f"{m} (paper)", k) for m in ("Wan 2.2", "Wan 2.2 LoRA 1k", "Wan 2.2 full FT 2.5k")
                    for k in ("ate3d", "ssim")}
    page = comparable.read_text()
    assert page.count("Reported in the paper, not re-scored here: Selected checkpoints by evaluation partition") == 1


def test_an_unverified_copy_gets_one_line_and_no_paper_rows(unverified):
    run, report = unverified
    out = report.parent
    line = (f"The paper's numbers are not shown beside these runs: {run} is on a copy of the published set whose "
            "MD5 was not verified.")
    md = (out / "report.md").read_text()
    assert md.count(line) == 1
    page = report.read_text()
    assert page.count(line.replace("'", "&#x27;")) == 1
    for name in ("model_metrics", "by_task", "by_partition"):
        assert "(paper)" not in (out / "tables" / f"{name}.md").read_text()
        assert MARKER not in (out / "tables" / f"{name}.md").read_text()
        assert {r["source"] for r in read_csv(out / "tables" / f"{name}.csv")} == {"scored here"}
    assert "(paper)" not in page and 'class="block' not in page


@pytest.mark.parametrize("kwargs, reason", [
    ({"protocol": "lossless"}, "{run} was scored under protocol lossless, not rigidbench-v1"),
    ({"protocol": None}, "{run} records no evaluation protocol"),
    ({"dataset": {"dataset": "rendered", "version": "bundle v3", "md5": None, "preset": "paper"}},
     "{run} is on a rendered set, not the published one"),
    ({"dataset": {**PUBLISHED, "verified": False}}, "{run} is on a copy of the published set whose MD5 was not "
                                                    "verified"),
    ({"dataset": {**PUBLISHED, "md5": "0" * 32}}, "{run} is on rigidbench-eval 1.1, not the paper's "
                                                   "rigidbench-eval 1.1 (MD5 b563f279451e95fe2f32d7e258588636)"),
    ({"dataset": None}, "{run} records no reference set"),
    ({"dataset": {"dataset": "mixed", "sets": [PUBLISHED, {"dataset": "rendered"}]}}, "{run} is on a mix of reference "
                                                                                      "sets"),
    ({"perception": "gt"}, "{run} used gt perception, not the paper's neural perception"),
    ({"n": 5}, "the report covers 5 of the paper's 100 examples"),
    ({}, None),
])
def test_each_reason_the_papers_numbers_are_not_comparable(tmp_path, kwargs, reason):
    run = write_run(tmp_path, "x", **kwargs)
    problem = comparison_problem(load_runs([run]), load_paper_numbers())
    if reason is None:
        assert problem is None
    else:
        assert problem.startswith("The paper's numbers are not shown beside these runs: ")
        assert reason.format(run=run) in problem and "\n" not in problem


def test_runs_sharing_a_reason_are_named_together(tmp_path):
    rendered = {"dataset": "rendered", "version": "bundle v3", "md5": None}
    runs = [write_run(tmp_path, "a", dataset=rendered), write_run(tmp_path, "b", dataset=rendered, seed=1),
            write_run(tmp_path, "c", protocol="paper-rules", seed=2), write_run(tmp_path, "ok", seed=3)]
    problem = comparison_problem(load_runs(runs), load_paper_numbers())
    assert problem == (f"The paper's numbers are not shown beside these runs: {runs[0]} and {runs[1]} are on a "
                       f"rendered set, not the published one; {runs[2]} was scored under protocol paper-rules, not "
                       "rigidbench-v1.")
