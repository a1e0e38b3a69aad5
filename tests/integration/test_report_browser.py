"""report.html in a real browser: headless Chromium loads every image and clip, and no table overflows the page.

Needs Debian's `chromium` package (`apt-get install -y chromium`); skipped without it. The report is built
from synthetic runs shaped like the paper's: eight models with long names, 20 examples over five tasks and
four partitions, all ten measurements with a few non-finite values, and tiny reference bundles and
predictions so the example filmstrips and clips are there too. A copy of the page with a small probe
script (the report itself has none) opens every <details>, waits for the page to load and writes what
it measured into the DOM, which `chromium --dump-dom` prints.
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

from rigidbench.metrics import METRICS
from rigidbench.report import build_report
from rigidbench.video import write_video

CHROMIUM = next((path for name in ("chromium", "chromium-browser", "google-chrome")
                 if (path := shutil.which(name))), None)
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium is not installed; install Debian's "
                                                         "`chromium` package: apt-get install -y chromium")

MODELS = ("reference", "Wan 2.2", "Cosmos 2.5", "Veo 3.1", "Veo 3.1 Fast", "Kling 3.0", "Seedance 2.0 Fast",
          "Grok Imagine")
TASKS = ("ball_chain", "ramp_collision", "drop_into_cluster", "bounce", "free_fall")
PARTITIONS = ("in_distribution", "ood_scene", "ood_object", "ood_both")
W, H, T, FPS = 96, 54, 13, 6.0
VIEWPORT = (1280, 1000)

PROBE = """
<pre id="browser-check">pending</pre>
<script>
window.addEventListener("load", () => {
  document.querySelectorAll("details").forEach(d => { d.open = true; });
  setTimeout(() => {
    const doc = document.documentElement;
    const out = {page: {scrollWidth: doc.scrollWidth, clientWidth: doc.clientWidth}, images: [], tables: [],
                 videos: []};
    for (const img of document.images)
      out.images.push({src: img.getAttribute("src"), ok: img.complete && img.naturalWidth > 0});
    for (const t of document.querySelectorAll("table")) {
      const box = t.getBoundingClientRect(), holder = t.parentElement;
      out.tables.push({id: t.id || t.className, right: box.right, width: box.width,
                       holderScroll: holder.scrollWidth, holderClient: holder.clientWidth});
    }
    for (const v of document.querySelectorAll("video"))
      out.videos.push({src: v.getAttribute("src"), error: v.error ? v.error.code : null});
    document.getElementById("browser-check").textContent = JSON.stringify(out);
  }, 500);
});
</script>
"""


def _frames(n_frames: int, speed: float) -> tuple[np.ndarray, np.ndarray]:
    """A ball moving right over a grey room: (T,H,W,3) uint8 frames and (T,2,H,W) masks (ball, block)."""
    masks = np.zeros((n_frames, 2, H, W), bool)
    for t in range(n_frames):
        x = int(10 + speed * t)
        masks[t, 0, 20:30, x:x + 10] = True
        masks[t, 1, 40:50, 50:90] = True
    frames = np.full((n_frames, H, W, 3), 120, np.uint8)
    frames[masks[:, 1]] = (120, 80, 40)
    frames[masks[:, 0]] = (220, 30, 30)
    return frames, masks


def write_world(root: Path) -> list[Path]:
    """Reference bundles, predictions and eight run directories as `rigidbench evaluate` leaves them."""
    from PIL import Image

    rng = np.random.default_rng(0)
    ids = [f"{i:05d}" for i in range(len(TASKS) * len(PARTITIONS))]
    tasks = [TASKS[i % len(TASKS)] for i in range(len(ids))]
    partitions = [PARTITIONS[i // len(TASKS)] for i in range(len(ids))]
    data = root / "data" / "eval"
    frames, masks = _frames(T, 4.0)
    for sample_id, task, part in zip(ids, tasks, partitions):
        bundle = data / sample_id
        (bundle / "frames").mkdir(parents=True)
        for k, frame in enumerate(frames):
            Image.fromarray(frame).save(bundle / "frames" / f"{k:05d}.png")
        write_video(bundle / "video.mp4", frames, fps=FPS)
        np.savez_compressed(bundle / "masks.npz", masks=masks, names=np.array(["ball", "block"]),
                            roles=np.array(["active", "passive"]))
        (bundle / "metadata.json").write_text(json.dumps({"sample_id": sample_id, "task": task, "partition": part,
                                                          "frames": T, "fps": FPS, "resolution": [W, H]}))
    run_dirs = []
    for m, model in enumerate(MODELS):
        preds = root / "predictions" / model.replace(" ", "_")
        pred_frames, _ = _frames(T, 4.0 - 0.4 * m)
        for sample_id in ids:
            write_video(preds / f"{sample_id}.mp4", pred_frames, fps=FPS)
        run_dir = root / "runs" / model.replace(" ", "_")
        (run_dir / "examples").mkdir(parents=True)
        for j, (sample_id, task, part) in enumerate(zip(ids, tasks, partitions)):
            metrics = {k: float(rng.uniform(0.05, 0.95)) * (10 if k in ("ate3d", "chamfer") else 1) for k in METRICS}
            metrics["bgdrift"] = float(rng.uniform(0.0, 0.012))
            metrics["si_mse"] = float(rng.uniform(0.0, 0.004))
            if model == "reference":
                metrics.update(iou=1.0, centroid_l2=0.0, ate=0.0, ate3d=0.0, ssim=1.0, lpips=0.0, bgdrift=0.0)
            if model == "Veo 3.1" and j in (3, 7):
                metrics["iddrift"] = None  # non-finite: the cells get n= notes
            record = {"id": sample_id, "model": model, "task": task, "partition": part, "metrics": metrics,
                      "skipped": {}}
            (run_dir / "examples" / f"{sample_id}.json").write_text(json.dumps(record))
        results = {"model": model, "perception": "neural", "official": False, "n_examples": len(ids),
                   "n_reference": 100, "failed": {}, "skipped_metrics": {},
                   "why_not_official": [f"the reference directory holds {len(ids)} examples, not the 100 of the "
                                        "eval split"]}
        (run_dir / "results.json").write_text(json.dumps(results))
        (run_dir / "run.json").write_text(json.dumps({"model": model, "predictions": str(preds), "data": str(data),
                                                      "perception": {"backend": "neural", "version": "2"}}))
        run_dirs.append(run_dir)
    return run_dirs


def browser_check(page: Path, tmp_path: Path) -> dict:
    """Load a probe copy of `page` beside it in headless Chromium at VIEWPORT; returns what the probe measured."""
    probe = page.with_name("_browser_probe.html")
    probe.write_text(page.read_text().replace("</body>", PROBE + "</body>"))
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           f"--user-data-dir={tmp_path / 'chromium-profile'}", f"--window-size={VIEWPORT[0]},{VIEWPORT[1]}",
           "--virtual-time-budget=20000", "--dump-dom", probe.as_uri()]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    found = re.search(r'<pre id="browser-check">(.*?)</pre>', done.stdout, re.S)
    assert found, f"chromium printed no probe result (exit {done.returncode}): {done.stderr[-2000:]}"
    assert found.group(1) != "pending", "the page never finished loading in chromium"
    return json.loads(html.unescape(found.group(1)))


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("browser")
    return build_report(write_world(root), root / "report", resamples=500, seed=0, examples=3)


def test_every_image_and_clip_loads_and_no_table_overflows(report, tmp_path):
    result = browser_check(report, tmp_path)
    images = result["images"]
    assert len(images) >= 4 + 3 * (1 + len(MODELS)), images  # 4 figures, 3 examples x (reference + 8 runs)
    broken = [img["src"] for img in images if not img["ok"]]
    assert not broken, f"images that did not load: {broken}"
    errors = [v for v in result["videos"] if v["error"] is not None]
    assert result["videos"] and not errors, f"clips the browser could not play: {errors}"
    width = result["page"]["clientWidth"]
    assert width == VIEWPORT[0]
    assert result["page"]["scrollWidth"] <= width, "the page scrolls sideways"
    tables = result["tables"]
    assert len(tables) >= 8
    for table in tables:
        assert table["right"] <= width + 0.5, f"table {table['id']} runs off the page: {table}"
        assert table["holderScroll"] <= table["holderClient"] + 1, f"table {table['id']} needs scrolling: {table}"
