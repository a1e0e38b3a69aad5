"""The leaderboard's numbers and pages, without a browser: boards against independent computations (means,
bootstrap intervals, ranks, seed spread), the paper's rows per view, paired comparisons against hand-counted
differences and wins, and the HTML a browser would get (escaping, header buttons, labelled filters, hidden
views, relative links, the paper's marker), plus filmstrips of a clip with known frames and the command."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from fixtures import leaderboard_bundles as lb
from rigidbench.cli import main
from rigidbench.leaderboard.entries import entries_from, example_groups, score_array, unique_slugs
from rigidbench.leaderboard.filmstrips import MISSING_GREY, STRIP_TIMES_S, compose, nearest_frames
from rigidbench.leaderboard.html import flatten
from rigidbench.leaderboard.pages import envelope_tables
from rigidbench.leaderboard.scores import ALL, View, boards, compare, views_of
from rigidbench.leaderboard.site import build_site
from rigidbench.metrics import METRICS
from rigidbench.report.paper import load_paper_numbers
from rigidbench.stats import bootstrap_ci, paired_difference_samples, probability_of_improvement
from rigidbench.submissions import Submission, load_submission

MARKER = "reported in the paper, not re-scored here"
B = 300  # bootstrap resamples in these tests


def submission(name: str, scores: dict[str, dict], samples: dict[str, list[dict]] | None = None) -> Submission:
    """A Submission as load_submission returns it, with records of ``scores`` (id -> metric -> value)."""
    records = {}
    for sample_id, metrics in scores.items():
        task, partition = lb.group_of(int(sample_id))
        records[sample_id] = {"id": sample_id, "task": task, "partition": partition, "metrics": metrics}
        if samples and sample_id in samples:
            records[sample_id]["samples"] = [{"metrics": m} for m in samples[sample_id]]
    return Submission(name=name, card={"name": name}, provenance={}, results={"official": False}, records=records,
                      readouts={}, videos={i: None for i in records}, path=Path(f"{name}.tar.gz"))


@pytest.fixture(scope="module")
def two():
    ids = lb.example_ids(20)
    a = lb.random_scores(ids, 1)
    a["00003"]["iou"] = None  # one non-finite value
    b = lb.random_scores(ids[:12], 2)
    return entries_from([submission("Alpha", a), submission("Beta", b)])


def test_the_board_means_and_intervals_are_bootstrap_ci_of_the_examples_in_each_view(two):
    alpha, beta = two
    groups = example_groups(two)
    views = views_of(groups)
    got = boards(two, groups, views, ("iou", "ate3d"), resamples=B, seed=3)
    iou = np.array([alpha.records[i]["metrics"]["iou"] for i in groups], dtype=float)  # None -> nan
    row = next(r for r in got["iou"][ALL] if r.key == "alpha")
    assert (row.n_finite, row.n_examples) == (19, 20)
    assert row.mean == pytest.approx(np.nanmean(iou), abs=1e-12)
    assert (row.mean, row.lo, row.hi) == pytest.approx(bootstrap_ci(iou[np.isfinite(iou)], B, 0.95, 3), abs=1e-12)
    task = "bounce"
    in_task = np.array([groups[i][0] == task for i in groups])
    row = next(r for r in got["iou"][View(task, "")] if r.key == "alpha")
    assert row.mean == pytest.approx(np.nanmean(iou[in_task]), abs=1e-12)
    assert row.n_examples == in_task.sum() == 4
    # beta has only the first 12 examples: its view counts are its own
    row = next(r for r in got["ate3d"][View("", "ood_both")] if r.key == "beta")
    assert row.n_examples == sum(1 for i in list(groups)[:12] if groups[i][1] == "ood_both")
    # a task within a partition: the one example of bounce in in_distribution
    both = View("bounce", "in_distribution")
    only = [i for i, g in groups.items() if g == ("bounce", "in_distribution")]
    row = next(r for r in got["iou"][both] if r.key == "alpha")
    assert len(only) == 1 and row.mean == pytest.approx(alpha.records[only[0]]["metrics"]["iou"])
    assert math.isnan(row.lo)  # one example: no interval


def test_ranks_follow_the_direction_and_paper_rows_are_never_ranked(two):
    groups = example_groups(two)
    paper = load_paper_numbers()
    got = boards(two, groups, [ALL], ("iou", "ate3d"), paper, resamples=B)
    for metric in ("iou", "ate3d"):
        rows = got[metric][ALL]
        scored = [r for r in rows if not r.paper]
        best = (max if METRICS[metric].higher_is_better else min)(scored, key=lambda r: r.mean)
        assert best.rank == 1 and sorted(r.rank for r in scored) == [1, 2]
        assert all(r.rank is None for r in rows if r.paper)
        means = [r.mean for r in rows]
        assert means == sorted(means, reverse=METRICS[metric].higher_is_better)  # best first, paper rows among them
    wan = next(r for r in got["iou"][ALL] if r.paper and r.name == "Wan 2.2")
    assert (wan.text, wan.mean, wan.n_examples) == ("0.183", 0.183, 100)
    veo = next(r for r in boards(two, groups, [ALL], ("iddrift",), paper, resamples=B)["iddrift"][ALL]
               if r.name == "Veo 3.1")
    assert veo.n_finite == 98  # the paper's two clips without valid patch pairs


def test_the_paper_rows_of_a_view_are_the_numbers_it_prints_for_that_subset(two):
    groups = example_groups(two)
    paper = load_paper_numbers()
    views = [ALL, View("ball_chain", ""), View("", "ood_scene"), View("ball_chain", "ood_scene")]
    got = boards(two, groups, views, ("ate3d", "ssim", "iou"), paper, resamples=B)

    def printed(metric, view):
        return {r.name: r.text for r in got[metric][view] if r.paper}

    assert len(printed("iou", ALL)) == 8
    assert printed("ate3d", View("ball_chain", ""))["Veo 3.1"] == "0.75"  # tab:task-ate3d
    assert len(printed("ate3d", View("ball_chain", ""))) == 8
    assert printed("iou", View("ball_chain", "")) == {}  # the paper prints no IoU by task
    assert printed("ssim", View("", "ood_scene")) == {"Wan 2.2": "0.906"}  # the base row of tab:finetuning-splits
    assert printed("ate3d", View("ball_chain", "ood_scene")) == {}


def test_several_samples_give_the_mean_of_example_means_and_the_seed_spread():
    ids = lb.example_ids(6)
    first = {i: {"iou": 0.1 * k} for k, i in enumerate(ids)}
    second = {i: [{"iou": 0.1 * k}, {"iou": 0.1 * k + 0.2}] for k, i in enumerate(ids)}
    second[ids[0]] = [{"iou": 0.0}]  # fewer samples on one example
    entries = entries_from([submission("K2", first, second)])
    arr = score_array(entries[0], ids, ("iou",))
    assert arr.shape == (1, 6, 2) and math.isnan(arr[0, 0, 1])
    groups = example_groups(entries)
    row = boards(entries, groups, [ALL], ("iou",), resamples=B)["iou"][ALL][0]
    example_means = [0.0] + [0.1 * k + 0.1 for k in range(1, 6)]
    assert row.mean == pytest.approx(np.mean(example_means))
    column_means = [np.mean([0.1 * k for k in range(6)]), np.mean([0.1 * k + 0.2 for k in range(1, 6)])]
    assert row.seed_std == pytest.approx(np.std(column_means, ddof=1))
    assert row.samples == 2


def test_a_comparison_is_paired_on_the_shared_examples_and_reads_the_same_from_both_sides(two):
    alpha, beta = two
    groups = example_groups(two)
    views = views_of(groups, combined=False)
    c = compare(alpha, beta, groups, views, ("ate3d", "ssim"), resamples=B, seed=0)
    shared = lb.example_ids(12)
    assert c.shared == tuple(shared)
    for metric in ("ate3d", "ssim"):
        a = np.array([alpha.records[i]["metrics"][metric] for i in shared])
        b = np.array([beta.records[i]["metrics"][metric] for i in shared])
        cell = c.cells[metric][ALL]
        assert cell.diff == pytest.approx(np.mean(a - b))
        wins = (a > b) if METRICS[metric].higher_is_better else (a < b)
        assert cell.poi == pytest.approx(wins.mean()) and cell.n == 12
        assert (cell.diff, cell.diff_lo, cell.diff_hi) == pytest.approx(
            paired_difference_samples(a[:, None], b[:, None], B, 0.95, 0), abs=1e-12)
        assert (cell.poi, cell.poi_lo, cell.poi_hi) == pytest.approx(
            probability_of_improvement(a, b, METRICS[metric].higher_is_better, B, 0.95, 0), abs=1e-12)
        back = c.swapped().cells[metric][ALL]
        assert (back.diff, back.diff_lo, back.diff_hi) == pytest.approx((-cell.diff, -cell.diff_hi, -cell.diff_lo))
        assert (back.poi, back.poi_lo, back.poi_hi) == pytest.approx((1 - cell.poi, 1 - cell.poi_hi,
                                                                      1 - cell.poi_lo))
    in_bounce = [i for i in shared if groups[i][0] == "bounce"]
    a = np.array([alpha.records[i]["metrics"]["ate3d"] for i in in_bounce])
    b = np.array([beta.records[i]["metrics"]["ate3d"] for i in in_bounce])
    assert c.cells["ate3d"][View("bounce", "")].diff == pytest.approx(np.mean(a - b))


def test_slugs_are_unique_and_safe_in_a_path():
    assert unique_slugs(["Wan 2.2", "wan-2.2", "<b>", "", "A/../b"]) == ["wan-2-2", "wan-2-2-2", "b", "entry",
                                                                        "a-b"]


def test_cards_flatten_to_dotted_keys():
    card = {"model": {"name": "M", "digest": None}, "gpu": {"type": "H100", "count": 8}, "best_of_n": False,
            "tags": ["a", "b"], "runs": [{"k": 1}]}
    assert flatten(card) == [("model.name", "M"), ("model.digest", "\u2014"), ("gpu.type", "H100"),
                             ("gpu.count", "8"), ("best_of_n", "no"), ("tags", "a, b"), ("runs[0].k", "1")]


def test_the_envelope_shows_one_row_per_measurement_and_one_column_per_number():
    text = envelope_tables({"overall": {"iou": {"inside": 0.75, "excess": 0.0125}, "ssim": {"inside": 1.0}},
                            "by_task": {"bounce": {"iou": {"inside": 0.5}}}})
    assert text.count("<table") == 2 and "task bounce" in text
    first = text.split("<table")[1]
    assert re.findall(r'data-col="\d+">([^<]+)</button>', first) == ["Measurement", "excess", "inside"]
    assert "0.0125" in first and "0.75" in first


# ------------------------------------------------------------------------------------------ the site


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("site")
    ids = lb.example_ids(20)
    folders = [lb.write_bundle(root / "bundles", 'Evil <script>alert("x")</script>', lb.random_scores(ids, 1)),
               lb.write_bundle(root / "bundles", "Plain", lb.random_scores(ids, 2), seed=2,
                               envelope={"overall": {"ate3d": {"inside": 0.5, "excess": 0.2}}})]
    return build_site([lb.as_archive(folders[0]), folders[1]], root / "site", resamples=B)


def test_every_page_is_written_and_every_link_is_relative_and_resolves(site, tmp_path):
    assert len(list(site.parent.rglob("*.html"))) == 1 + 2 + 1 + 2 + 1 + 20  # index, entries, compare, examples
    assert lb.broken_links(site.parent) == []
    out = shutil.copytree(site.parent, tmp_path / "site")  # now break a copy: the check finds each fault
    (out / "entries" / "plain.html").unlink()
    (out / "extra.html").write_text('<a href="https://example.org">x</a><a href="/abs.html">y</a>'
                                    '<a href="index.html#m-nothing">z</a><a href="../outside.html">w</a>')
    (out.parent / "outside.html").write_text("")
    found = "\n".join(lb.broken_links(out))
    for needle in ("https://example.org: not a relative", "/abs.html: not a relative", "#m-nothing: no element",
                   "../outside.html: no such file", "entries/plain.html: no such file"):
        assert needle in found, found


def test_names_are_escaped_and_headers_are_buttons_and_filters_are_labelled(site):
    text = site.read_text()
    assert "<script>alert" not in text and "&lt;script&gt;alert(&quot;x&quot;)" in text
    for m in METRICS:
        board = text.split(f'id="board-{m}"')[1].split("</table>")[0]
        heads = re.findall(r'<button type="button" class="sort" data-col="(\d+)">([^<]+)</button>', board)
        assert [h for _, h in heads] == ["Rank", "Entry", "Mean", "95% interval", "Examples (finite/all)", "Seed std",
                                         "Samples"]
        assert [int(k) for k, _ in heads] == list(range(7))
    for ident, label in (("filter-task", "Task"), ("filter-partition", "Partition")):
        assert f'<label for="{ident}">{label}</label><select id="{ident}">' in text
    assert re.findall(r'<option value="([^"]*)">', text.split('id="filter-task"')[1].split("</select>")[0]) == [
        "", *lb.TASKS]


def test_only_the_all_examples_view_shows_before_filtering_and_paper_rows_are_marked(site):
    text = site.read_text()
    board = text.split('id="board-ate3d"')[1].split("</table>")[0]
    rows = re.findall(r"<tr([^>]*)>(.*?)</tr>", board)[1:]
    shown = [(attrs, body) for attrs, body in rows if " hidden" not in attrs]
    assert all('data-task="" data-partition=""' in attrs for attrs, _ in shown)
    assert len(shown) == 2 + 8  # two entries and the paper's eight rows
    assert sum(MARKER in body for _, body in shown) == 8
    views = {(re.search(r'data-task="([^"]*)"', a).group(1), re.search(r'data-partition="([^"]*)"', a).group(1))
             for a, _ in rows}
    assert len(views) == (1 + 5) * (1 + 4)
    data = json.loads((site.parent / "leaderboard.json").read_text())
    assert {v["task"] for v in data["boards"]["iou"]} == {"", *lb.TASKS}


def test_the_entry_page_has_the_card_the_breakdowns_the_readouts_and_the_envelope(site):
    page = (site.parent / "entries" / "plain.html").read_text()
    for needle in ("Submission card", "model.name", "Provenance", 'id="by-task"', 'id="by-partition"',
                   'id="readouts"', "Physical envelope", "excess", 'id="examples"'):
        assert needle in page, needle
    assert "Physical envelope" not in (site.parent / "entries" / "evil-script-alert-x-script.html").read_text()


def test_no_paper_leaves_the_papers_rows_out(tmp_path):
    ids = lb.example_ids(5)
    folder = lb.write_bundle(tmp_path, "Solo", lb.random_scores(ids, 4))
    index = build_site([folder], tmp_path / "site", paper=False, resamples=B)
    assert MARKER not in index.read_text() and "Wan 2.2" not in index.read_text()


def test_filmstrips_hold_the_frames_nearest_the_strip_times(tmp_path):
    from rigidbench.video import write_video

    levels = np.arange(13) * 18  # frame k is a flat grey of level 18 k, at k / 6 s
    frames = np.repeat(levels[:, None, None, None], 3, axis=-1) * np.ones((13, 16, 32, 3))
    write_video(tmp_path / "clip.mp4", frames.astype(np.uint8), fps=6.0)
    got = nearest_frames(tmp_path / "clip.mp4")
    assert [int(round(float(f.mean()) / 18)) for f in got] == [round(t * 6) for t in STRIP_TIMES_S]
    write_video(tmp_path / "short.mp4", frames[:5].astype(np.uint8), fps=6.0)  # 0 to 0.67 s
    short = nearest_frames(tmp_path / "short.mp4")
    assert [f is None for f in short] == [False, False, True, True, True]
    strip = compose(short, tile_height=10)
    assert strip.shape == (10, 5 * 20 + 4 * 2, 3)
    assert (strip[:, -20:] == MISSING_GREY).all()


def test_the_command_builds_the_site_and_refuses_a_changed_bundle(tmp_path, capsys):
    ids = lb.example_ids(5)
    good = lb.write_bundle(tmp_path / "b", "Good", lb.random_scores(ids, 5))
    bad = lb.write_bundle(tmp_path / "b", "Edited", lb.random_scores(ids, 6))
    assert load_submission(bad).name == "Edited"
    results = json.loads((bad / "results.json").read_text())
    results["overall"]["iou"]["mean"] = 0.99
    (bad / "results.json").write_text(json.dumps(results))
    out = tmp_path / "site"
    assert main(["leaderboard", str(good), str(bad), "--out", str(out), "--resamples", "50"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "results.json" in err[0] and not out.exists()
    assert main(["leaderboard", str(good), "--out", str(out), "--resamples", "50", "--no-paper"]) == 0
    assert (out / "index.html").is_file() and (out / "entries" / "good.html").is_file()
