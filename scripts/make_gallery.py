"""Regenerate docs/gallery/: a contact sheet for one eval example of every task and every scene.

    python scripts/make_gallery.py [--data /tmp/rigidbench_gallery] [--quality preview] [--workers 1]

Picks eval manifest rows so that every scene appears once and, among them, every task (one row
per scene, preferring a task not yet covered; a task still missing gets its first row), renders
them with the normal pipeline (``rigidbench render``'s code: complete bundles in the scratch data
directory are reused), writes each contact sheet (``rigidbench show``'s code) and saves it as a
palette PNG under ``MAX_BYTES``: ``task_<task>.png`` and ``scene_<scene>.png``, plus README.md
listing them. Takes about 15 minutes on a 2-core CPU at `preview`.
"""

from __future__ import annotations

import argparse
import io
import logging
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT_DIR = ROOT / "docs" / "gallery"
MAX_BYTES = 300_000
DPI_STEPS = (110, 95, 80, 65)  # contact-sheet resolutions tried, largest first, until the PNG fits

log = logging.getLogger("make_gallery")


def pick_rows(rows: list, tasks: list[str], scenes: list[str]) -> tuple[dict, dict]:
    """rows: eval ManifestRows. Returns ({task: row}, {scene: row}) covering every task and scene."""
    by_scene, by_task = {}, {}
    for scene in scenes:
        candidates = [r for r in rows if r.scene == scene]
        if not candidates:
            raise ValueError(f"no eval row uses scene '{scene}'; check configs/splits.yaml")
        fresh = [r for r in candidates if r.task not in by_task]
        row = (fresh or candidates)[0]
        by_scene[scene] = row
        by_task.setdefault(row.task, row)
    for task in tasks:
        if task not in by_task:
            by_task[task] = next(r for r in rows if r.task == task)
    return by_task, by_scene


def sheet_png(sample, max_bytes: int = MAX_BYTES) -> bytes:
    """Contact sheet of ``sample`` as PNG bytes (256-colour palette) no larger than ``max_bytes``."""
    from PIL import Image

    from rigidbench.groundtruth.contact_sheet import write_contact_sheet

    data = b""
    for dpi in DPI_STEPS:
        with tempfile.TemporaryDirectory() as tmp:
            path = write_contact_sheet(sample, Path(tmp) / "sheet.png", dpi=dpi)
            image = Image.open(path).convert("RGB")
        buf = io.BytesIO()
        image.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
            buf, format="PNG", optimize=True)
        data = buf.getvalue()
        if len(data) <= max_bytes:
            return data
    log.warning("%s: contact sheet is %d bytes even at %d dpi", sample.sample_id, len(data), DPI_STEPS[-1])
    return data


def readme(by_task: dict, by_scene: dict, quality: str) -> str:
    lines = ["# Gallery", "",
             f"Contact sheets of eval examples rendered at the `{quality}` preset: first, middle and last "
             "frame with the ground-truth point tracks (o visible, x occluded), the actor masks in colour, "
             "and the depth. Regenerate with `python scripts/make_gallery.py`; one sheet of any rendered "
             "example comes from `rigidbench show ID`.", "", "## One example per task", "",
             "| task | example | scene | sheet |", "|---|---|---|---|"]
    for task, row in sorted(by_task.items()):
        lines.append(f"| {task} | {row.sample_id} | {row.scene} | [task_{task}.png](task_{task}.png) |")
    lines += ["", "## One example per scene", "", "| scene | example | task | sheet |", "|---|---|---|---|"]
    for scene, row in sorted(by_scene.items()):
        lines.append(f"| {scene} | {row.sample_id} | {row.task} | [scene_{scene}.png](scene_{scene}.png) |")
    lines += ["", *[f"![{t}](task_{t}.png)" for t in sorted(by_task)], ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(tempfile.gettempdir()) / "rigidbench_gallery"),
                        help="scratch data directory for the bundles (reused between runs)")
    parser.add_argument("--quality", default="preview")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--out", default=str(OUT_DIR))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    from rigidbench import manifest
    from rigidbench.config import registry
    from rigidbench.groundtruth.bundle import Sample
    from rigidbench.pipeline.render import bundle_dir, render_rows

    reg = registry()
    rows = list(manifest.rows("eval", reg))
    by_task, by_scene = pick_rows(rows, sorted(reg.tasks), sorted(reg.scenes))
    chosen = sorted({r.sample_id: r for r in [*by_task.values(), *by_scene.values()]}.values(),
                    key=lambda r: r.sample_id)
    log.info("rendering %d examples at %s into %s: %s", len(chosen), args.quality, args.data,
             " ".join(r.sample_id for r in chosen))
    data = Path(args.data)
    _, failures = render_rows(chosen, reg, data, quality=args.quality, workers=args.workers)
    if failures:
        for f in failures:
            log.error("example %s failed: %s", getattr(f, "sample_id", f), getattr(f, "reason", ""))
        return 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for prefix, picks in (("task", by_task), ("scene", by_scene)):
        for key, row in sorted(picks.items()):
            png = sheet_png(Sample(bundle_dir(data, row)))
            (out / f"{prefix}_{key}.png").write_bytes(png)
            log.info("wrote %s (%d KB)", out / f"{prefix}_{key}.png", len(png) // 1024)
    (out / "README.md").write_text(readme(by_task, by_scene, args.quality))
    return 0


if __name__ == "__main__":
    sys.exit(main())
