"""The leaderboard site in a real browser: headless Chromium opens every page from file:// with no console
message, and sorting, filtering, the keyboard and the compare form change what it shows as they should.

Needs Debian's `chromium` package (`apt-get install -y chromium`); skipped without it. The site is built from
three submission bundles (one packed as .tar.gz, one with two clips) over 20 examples, plus the paper's rows.
One Chromium run loads a probe page written beside index.html: it opens every page of the site in an iframe
(file:// pages may reach each other with --allow-file-access-from-files), notes its title and images, then
drives index.html, examples/index.html and compare/index.html as a user would and writes the row orders it
saw into the DOM, which `--dump-dom` prints. Chromium's console goes to stderr (--enable-logging=stderr): any
console line (an uncaught error, a failed script) fails the test. The expected orders are computed here from
leaderboard.json, which holds the same rows.
"""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from fixtures import leaderboard_bundles as lb
from rigidbench.leaderboard import build_site
from rigidbench.video import write_video

CHROMIUM = next((path for name in ("chromium", "chromium-browser", "google-chrome")
                 if (path := shutil.which(name))), None)
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium is not installed; install Debian's "
                                                         "`chromium` package: apt-get install -y chromium")

PROBE = """<!doctype html><html><head><meta charset="utf-8"><link rel="icon" href="data:,"></head><body>
<pre id="probe">pending</pre><iframe id="frame" style="width:1200px;height:800px"></iframe>
<script>
const PAGES = %(pages)s;
const frame = document.getElementById("frame");
const out = {pages: [], steps: {}};
function load(url) {
  return new Promise(done => { frame.onload = () => done(frame.contentDocument); frame.src = url; });
}
function keys(doc, id) {
  return Array.from(doc.getElementById(id).tBodies[0].rows).filter(r => !r.hidden)
    .map(r => r.getAttribute("data-key") || r.cells[0].textContent.trim());
}
function button(doc, id, heading) {
  return Array.from(doc.getElementById(id).querySelectorAll("button.sort")).find(b => b.textContent === heading);
}
function choose(doc, id, value) {
  const el = doc.getElementById(id);
  el.value = value;
  el.dispatchEvent(new Event("change", {bubbles: true}));
}
function press(el, key) {
  el.dispatchEvent(new KeyboardEvent("keydown", {key: key, bubbles: true, cancelable: true}));
}
(async () => {
  try {
    for (const page of PAGES) {
      const doc = await load(page);
      out.pages.push({page: page, title: doc.title, h1: (doc.querySelector("h1") || {}).textContent || "",
                      images: Array.from(doc.images).map(i => ({src: i.getAttribute("src"),
                                                                ok: i.complete && i.naturalWidth > 0}))});
    }
    let doc = await load("index.html");
    const s = out.steps;
    s.initial = keys(doc, "board-iou");
    button(doc, "board-iou", "Entry").click();
    s.byNameUp = keys(doc, "board-iou");
    button(doc, "board-iou", "Entry").click();
    s.byNameDown = keys(doc, "board-iou");
    button(doc, "board-iou", "Mean").click();
    s.byMeanUp = keys(doc, "board-iou");
    s.ariaMean = button(doc, "board-iou", "Mean").closest("th").getAttribute("aria-sort");
    s.ariaEntry = button(doc, "board-iou", "Entry").closest("th").getAttribute("aria-sort");
    choose(doc, "filter-task", "bounce");
    s.bounce = keys(doc, "board-ate3d");
    choose(doc, "filter-partition", "ood_scene");
    s.bounceOodScene = keys(doc, "board-ate3d");
    s.label = doc.querySelector("[data-filter-label]").textContent;
    choose(doc, "filter-task", "");
    s.oodScene = keys(doc, "board-ate3d");
    choose(doc, "filter-partition", "");
    const mean = button(doc, "board-ssim", "Mean");
    mean.focus();
    s.focused = doc.activeElement === mean;
    press(mean, "Enter");
    s.enter = keys(doc, "board-ssim");
    press(mean, " ");
    s.space = keys(doc, "board-ssim");
    s.ariaSpace = mean.closest("th").getAttribute("aria-sort");
    doc = await load("examples/index.html");
    choose(doc, "filter-task", "free_fall");
    s.freeFall = keys(doc, "examples");
    doc = await load("compare/index.html");
    const form = doc.getElementById("compare-form");
    form.elements.a.value = form.elements.b.value;
    form.requestSubmit();
    s.sameMessage = doc.querySelector("[data-compare-message]").textContent;
    form.elements.a.value = %(a)s;
    form.elements.b.value = %(b)s;
    const navigated = new Promise(done => { frame.onload = () => done(frame.contentDocument); });
    form.requestSubmit();
    doc = await navigated;
    const where = frame.contentWindow.location.pathname.split("/").slice(-2).join("/");
    s.compared = [where, doc.querySelector("h1").textContent];
  } catch (err) {
    out.error = String(err) + " " + err.stack;
  }
  document.getElementById("probe").textContent = JSON.stringify(out);
})();
</script></body></html>
"""


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("leaderboard")
    ids = lb.example_ids(20)
    frames = np.full((13, 36, 64, 3), 90, np.uint8)
    for t in range(13):
        frames[t, 10:18, 4 + 4 * t:12 + 4 * t] = (220, 30, 30)
    clip = root / "clip.mp4"
    write_video(clip, frames, fps=6.0)
    bundles = [lb.as_archive(lb.write_bundle(root / "b", "Model A", lb.random_scores(ids, 1), seed=1)),
               lb.write_bundle(root / "b", "Model B", lb.random_scores(ids, 2, 0.05), seed=2,
                               videos={"00000": clip, "00003": clip}),
               lb.write_bundle(root / "b", "Model C", lb.random_scores(ids[:16], 3, -0.05), seed=3)]
    return build_site(bundles, root / "site", resamples=500).parent


def run_probe(site: Path, tmp_path: Path, a: str, b: str) -> tuple[dict, list[str]]:
    pages = sorted(p.relative_to(site).as_posix() for p in site.rglob("*.html"))
    probe = site / "_probe.html"
    probe.write_text(PROBE % {"pages": json.dumps(pages), "a": json.dumps(a), "b": json.dumps(b)})
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files",
           "--enable-logging=stderr", "--v=0", f"--user-data-dir={tmp_path / 'profile'}",
           "--virtual-time-budget=30000", "--dump-dom", probe.as_uri()]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    finally:
        probe.unlink()
    found = re.search(r'<pre id="probe">(.*?)</pre>', done.stdout, re.S)
    assert found, f"chromium printed no probe result (exit {done.returncode}): {done.stderr[-2000:]}"
    assert found.group(1) != "pending", "the probe never finished: " + done.stderr[-2000:]
    console = [line for line in done.stderr.splitlines() if ":CONSOLE" in line]
    return json.loads(html.unescape(found.group(1))), console


def test_the_site_in_chromium(site, tmp_path):
    data = json.loads((site / "leaderboard.json").read_text())
    result, console = run_probe(site, tmp_path, "model-c", "model-a")
    assert "error" not in result, result["error"]
    assert console == [], "console messages:\n" + "\n".join(console)

    # every page loaded, with its own title and heading, and every image decoded
    pages = {p["page"]: p for p in result["pages"]}
    assert len(pages) == 1 + 3 + 1 + 6 + 1 + 20
    assert all(p["title"].endswith("RigidBench leaderboard") and p["h1"] for p in pages.values())
    broken = [(p["page"], i["src"]) for p in pages.values() for i in p["images"] if not i["ok"]]
    assert not broken, broken
    assert [len(pages[f"examples/{i}.html"]["images"]) for i in ("00000", "00001", "00003")] == [1, 0, 1]
    assert lb.broken_links(site) == []

    def rows(metric, task="", partition=""):
        view = next(v for v in data["boards"][metric] if (v["task"], v["partition"]) == (task, partition))
        return view["rows"]

    steps = result["steps"]
    iou = rows("iou")
    assert len(iou) == 3 + 8 and steps["initial"] == [r["key"] for r in iou]
    by_name = sorted(iou, key=lambda r: r["name"].lower())
    assert steps["byNameUp"] == [r["key"] for r in by_name]
    assert steps["byNameDown"] == [r["key"] for r in reversed(by_name)]
    desc = list(reversed(by_name))
    assert steps["byMeanUp"] == [r["key"] for r in sorted(desc, key=lambda r: r["mean"])]
    assert (steps["ariaMean"], steps["ariaEntry"]) == ("ascending", "none")

    # filters: the rows of the chosen view, in their ranked order; the paper's rows where it prints a number
    assert steps["bounce"] == [r["key"] for r in rows("ate3d", "bounce")]
    assert sum(k.startswith("paper:") for k in steps["bounce"]) == 8  # tab:task-ate3d
    assert steps["bounceOodScene"] == [r["key"] for r in rows("ate3d", "bounce", "ood_scene")]
    assert steps["bounceOodScene"] == sorted(steps["bounceOodScene"], key=lambda k: k.startswith("paper:")) and \
        not any(k.startswith("paper:") for k in steps["bounceOodScene"])
    assert steps["label"] == "task bounce, partition ood_scene"
    assert steps["oodScene"] == [r["key"] for r in rows("ate3d", "", "ood_scene")]
    assert [k for k in steps["oodScene"] if k.startswith("paper:")] == ["paper:Wan 2.2"]  # tab:finetuning-splits

    # the keyboard: Enter and Space on a focused header sort up, then down
    ssim = rows("ssim")
    up = sorted(ssim, key=lambda r: r["mean"])
    assert steps["focused"] is True
    assert steps["enter"] == [r["key"] for r in up]
    assert steps["space"] == [r["key"] for r in sorted(up, key=lambda r: -r["mean"])]
    assert steps["ariaSpace"] == "descending"
    assert steps["enter"] != [r["key"] for r in ssim] or steps["space"] != [r["key"] for r in ssim]

    # the example index's filter, and the compare form
    assert steps["freeFall"] == [i for i in lb.example_ids(20) if lb.group_of(int(i))[0] == "free_fall"]
    assert steps["sameMessage"] == "Choose two different entries."
    assert steps["compared"] == ["compare/model-c--model-a.html", "Model C vs Model A"]


# -- the whole path: runs scored, submitted with `rigidbench submit`, published with `rigidbench leaderboard` -----

E2E_MODELS = ("reference", "gamma", "camera-shake")


@pytest.fixture(scope="module")
def submitted(tmp_path_factory, torch_single_thread) -> list[Path]:
    """Three bundles `rigidbench submit` wrote: the reference and two failure modes on the synthetic published
    set (three examples, MD5 verified, neural perception with tiny networks), one with its clips."""
    for module in ("av", "transformers"):  # torch: torch_single_thread
        pytest.importorskip(module)
    import yaml

    from fixtures import published_runs, tiny_perception
    from rigidbench.cli import main
    from rigidbench.driver import RunOptions
    from rigidbench.perception.features import FeatureNets, load_identity_features
    from rigidbench.stages.evaluate import evaluate

    root = tmp_path_factory.mktemp("submitted")
    config, data = published_runs.verified_test_set(root)
    nets = FeatureNets(lpips=tiny_perception.tiny_lpips(),
                       identity=load_identity_features(device="cpu", model=tiny_perception.tiny_dinov2()))
    card = yaml.safe_load((Path(__file__).resolve().parents[2] / "docs" / "card.example.yaml").read_text())
    bundles = []
    for k, model in enumerate(E2E_MODELS):
        preds, run = root / "predictions" / model, root / "runs" / model
        assert main(["predict", model, "--data", str(data), "--out", str(preds), "--severity", "0.5"]) == 0
        options = {"models": tiny_perception.tiny_models(), "depth_input_size": 56, "device": "cpu"}
        summary = evaluate(preds, data, run, perception="neural", perception_options=options, nets=nets,
                           run=RunOptions(progress=False))
        assert not summary.failed and not summary.facts.skipped_metrics
        (root / f"{model}.yaml").write_text(yaml.safe_dump({**card, "name": f"{model} entry"}))
        bundle = root / f"{model}.tar.gz"
        videos = ["--videos", str(preds)] if k == 1 else []
        assert main(["--config", str(config), "submit", str(run), "--card", str(root / f"{model}.yaml"),
                     "--out", str(bundle), *videos]) == 0
        bundles.append(bundle)
    return bundles


def test_submitted_bundles_make_a_site_that_loads_in_chromium(submitted, tmp_path):
    from rigidbench.cli import main

    site = tmp_path / "site"
    assert main(["leaderboard", *map(str, submitted), "--out", str(site), "--resamples", "200"]) == 0
    result, console = run_probe(site, tmp_path, "camera-shake-entry", "reference-entry")
    assert "error" not in result, result["error"]
    assert console == [], "console messages:\n" + "\n".join(console)
    pages = {p["page"]: p for p in result["pages"]}
    assert len(pages) == 1 + 3 + 1 + 6 + 1 + 3
    assert [len(pages[f"examples/{i}.html"]["images"]) for i in ("00000", "00001", "00002")] == [1, 1, 1]
    assert all(i["ok"] for p in pages.values() for i in p["images"])
    assert lb.broken_links(site) == []
    assert result["steps"]["compared"] == ["compare/camera-shake-entry--reference-entry.html",
                                           "camera-shake entry vs reference entry"]
    # each board's all-examples mean is the mean results.json holds (aggregated by evaluate, read by submit)
    from rigidbench.submissions import load_submission

    data = json.loads((site / "leaderboard.json").read_text())
    results = {s.name: s.results["overall"] for s in map(load_submission, submitted)}
    for metric, views in data["boards"].items():
        rows = next(v for v in views if v["task"] == v["partition"] == "")["rows"]
        assert sum(r["reported_in_paper"] for r in rows) == 8
        for r in rows:
            if not r["reported_in_paper"]:
                want = results[r["name"]][metric]["mean"]  # None: no finite value (tiny random networks)
                assert r["mean"] == (None if want is None else pytest.approx(want, rel=1e-12, abs=0)), metric
                assert r["finite"] == results[r["name"]][metric]["finite"]
    assert all("test-eval 0.1, not the paper's" in e["paper_footing"] for e in data["entries"])
