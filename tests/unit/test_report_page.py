"""What report.html says and how: a short header, numbers to 3-4 significant figures, no marks on ties,
the task and partition tables and the probability-of-improvement matrices.

Four runs over ten examples (five tasks x two partitions) with chosen values: 'alpha' and 'beta' both
have ATE-3D 0 everywhere (a tie), BGDrift spans four orders of magnitude, LPIPS was skipped for every
run with a long reason, and every run is unofficial for the same reason ('gamma' for one more).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from rigidbench.metrics import METRICS
from rigidbench.report import build_report
from fixtures.report_files import read_csv

TASKS = ("ball_chain", "ramp_collision", "drop_into_cluster", "bounce", "free_fall")
IDS = [f"{i:05d}" for i in range(10)]
SHARED_REASON = "the reference directory holds 10 examples, not the 100 of the eval split"
EXTRA_REASON = "2 examples failed"
LPIPS_REASON = ("AlexNet ImageNet backbone weights are not available locally: looked in $RIGIDBENCH_ALEXNET (unset) "
                "and the torch hub cache; fetch them with `rigidbench weights --download alexnet`")
BGDRIFT = {"reference": 0.0, "alpha": 0.00823457, "beta": 2.3e-5, "gamma": 0.0012}


def write_run(root: Path, model: str, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    run_dir = root / model
    (run_dir / "examples").mkdir(parents=True)
    for j, sample_id in enumerate(IDS):
        metrics = {m: float(rng.uniform(0.2, 0.8)) for m in METRICS}
        metrics.update(lpips=None, ate3d=0.0 if model in ("alpha", "beta", "reference") else float(1 + j % 3),
                       bgdrift=BGDRIFT[model] * (1 + 0.01 * j), si_mse=float(rng.uniform(0.0, 0.003)))
        record = {"id": sample_id, "model": model, "task": TASKS[j % 5],
                  "partition": "in_distribution" if j < 5 else "ood_object", "metrics": metrics,
                  "skipped": {"lpips": LPIPS_REASON}}
        (run_dir / "examples" / f"{sample_id}.json").write_text(json.dumps(record))
    reasons = [SHARED_REASON] + ([EXTRA_REASON] if model == "gamma" else [])
    results = {"model": model, "perception": "gt", "official": False, "n_examples": len(IDS), "n_reference": 10,
               "failed": {}, "skipped_metrics": {"lpips": LPIPS_REASON}, "why_not_official": reasons}
    (run_dir / "results.json").write_text(json.dumps(results))
    (run_dir / "run.json").write_text(json.dumps({"model": model, "perception": {"backend": "gt", "version": "1"}}))
    return run_dir


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("page")
    runs = [write_run(root / "runs", model, seed) for seed, model in enumerate(BGDRIFT)]
    return build_report(runs, root / "out", resamples=500, seed=0)



def md_rows(path: Path) -> list[list[str]]:
    """The body rows of the first Markdown table in `path`, as cell strings."""
    lines = [line for line in path.read_text().splitlines() if line.startswith("| ")]
    return [[c.strip() for c in line.strip("|").split(" | ")] for line in lines[2:]]


def test_header_is_short_with_the_official_reason_once_and_skip_reasons_folded(report):
    page = report.read_text()
    head = page[:page.index("<h2>")]
    assert page.count(SHARED_REASON) == 1 and SHARED_REASON in head  # said once, in the header
    assert "Not an official result: " + SHARED_REASON in head
    # The long skip reason sits in one collapsed note, once.
    note = re.search(r'<details class="note"><summary>(.*?)</summary>(.*?)</details>', head, re.S)
    assert note and "LPIPS was not computed for all 4 runs" in note.group(1)
    assert page.count(LPIPS_REASON[:60]) == 1 and LPIPS_REASON[:60] in note.group(2)
    body = head[head.index("<body>"):]
    visible = re.sub(r"<[^>]+>", "", re.sub(r"<details.*?</details>", "", body, flags=re.S))
    assert len(visible) < 600, visible  # a short header: title, one line of facts, the status, the contents
    # The runs table names only what a run adds to the shared reason.
    runs = page[page.index('<section id="runs">'):]
    assert "beyond the reason above" in runs and runs.count(EXTRA_REASON) == 1
    md = (report.parent / "report.md").read_text()
    assert md.count(SHARED_REASON) == 1


def significant_digits(text: str) -> int:
    digits = re.sub(r"[^0-9]", "", text).lstrip("0")
    return len(digits)


def test_numbers_print_to_three_or_four_significant_figures(report):
    rows = md_rows(report.parent / "tables" / "model_metrics.md")
    header = [line for line in (report.parent / "tables" / "model_metrics.md").read_text().splitlines()
              if line.startswith("| Model")][0]
    assert "BGDrift×10³" in header
    k_bg = 1 + list(METRICS).index("bgdrift")
    bg = {row[0]: row[k_bg].split(" ")[0] for row in rows}
    # x 1000 at the column's two decimals (about 3 significant figures at its typical value), not eight.
    assert bg == {"reference": "0.00", "alpha": "8.61", "beta": "**0.02**", "gamma": "<u>1.25</u>"}
    for row in rows:
        for cell in row[1:]:
            value = re.sub(r"<.*?>|\*", "", cell).split(" ")[0]
            if value in ("skipped", "n/a"):
                continue
            assert significant_digits(value) <= 4, (row[0], cell)
            decimals = len(value.split(".")[1]) if "." in value else 0
            assert decimals <= 6, (row[0], cell)


def test_tied_values_take_no_marks(report):
    rows = read_csv(report.parent / "tables" / "model_metrics.csv")
    ate3d = {r["model"]: r["mark"] for r in rows if r["metric"] == "ate3d"}
    assert ate3d == {"reference": "", "alpha": "", "beta": "", "gamma": ""}  # alpha and beta tie at 0
    bgdrift = {r["model"]: r["mark"] for r in rows if r["metric"] == "bgdrift"}
    # x 1000 at 2 decimals: beta 0.02 best, gamma 1.25 second; the reference's 0 takes no mark.
    assert bgdrift == {"reference": "", "alpha": "", "beta": "best", "gamma": "second"}
    k = 1 + list(METRICS).index("ate3d")
    assert not any("**" in row[k] or "<u>" in row[k] for row in md_rows(report.parent / "tables" / "model_metrics.md"))
    for row in read_csv(report.parent / "tables" / "by_task.csv"):
        if row["metric"] == "ate3d":
            assert row["mark"] == ""


def test_task_and_partition_tables(report):
    by_task = md_rows(report.parent / "tables" / "by_task.md")
    text = (report.parent / "tables" / "by_task.md").read_text()
    assert "| Model | Ball chain | Ramp collision | Drop into cluster | Bounce | Free fall | Ball chain |" in text
    csv_rows = read_csv(report.parent / "tables" / "by_task.csv")
    gamma = next(row for row in by_task if row[0] == "gamma")
    mean = float(next(r["mean"] for r in csv_rows if r["model"] == "gamma" and r["task"] == "bounce"
                      and r["metric"] == "ate3d"))
    assert gamma[4].split(" ")[0].strip("*") == f"{mean:.2f}"  # ATE-3D, Bounce column
    part = (report.parent / "tables" / "by_partition.md").read_text()
    assert "| Model | ID | Object | ID | Object |" in part  # ATE-3D then SSIM, partitions in the paper's order
    assert "ATE-3D" in (report.parent / "tables" / "by_partition.tex").read_text()
    page = report.read_text()
    for key in ("by_task", "all_by_task", "by_partition", "all_by_partition"):
        assert f'id="table-{key}"' in page
    all_task = md_rows(report.parent / "tables" / "all_by_task.md")
    assert len(all_task) == 5 * 4 and all_task[0][0].startswith("Ball chain (2)")


def test_probability_of_improvement_matrix(report):
    matrix = md_rows(report.parent / "tables" / "poi_ssim.md")
    header = [line for line in (report.parent / "tables" / "poi_ssim.md").read_text().splitlines()
              if line.startswith("| Row beats column")][0]
    order = [c.strip() for c in header.strip("|").split(" | ")][1:]
    assert sorted(order) == sorted(BGDRIFT) and [row[0] for row in matrix] == order
    poi = {(r["model"], r["opponent"]): float(r["poi"]) for r in read_csv(report.parent / "tables" / "poi_matrix.csv")
           if r["metric"] == "ssim"}
    for row in matrix:
        for opponent, cell in zip(order, row[1:]):
            value = cell.strip("*")
            if opponent == row[0]:
                assert value == "·"
            else:
                assert value == f"{poi[(row[0], opponent)]:.2f}"
    # Best first: the first row beats the others at least half the time on average.
    first = [float(c.strip("*")) for c in matrix[0][1:] if c.strip("*") != "·"]
    assert np.mean(first) >= 0.5
    page = report.read_text()
    assert 'id="table-poi_ate3d"' in page and 'id="table-poi_ssim"' in page and "background:#" in page
