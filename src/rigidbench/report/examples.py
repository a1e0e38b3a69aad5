"""Example filmstrips: a few examples, the reference and every model's prediction at the same moments.

For each chosen example (one per task, where the models' ATE-3D differ most) the report shows one
strip per row, reference first: frames at 0, 1/8, 1/4, 1/2 and all of the clip, cropped to the
same frame-shaped box around the reference's moving objects (objects are small in a room-sized
view), and every row outlines the reference's moving objects at that moment: on a prediction the
outlines show where the objects should be, so a model's error reads directly off the strip. With
``outlines="perceived"`` a prediction is outlined with the masks perception recovered from it (the
run's perception cache, ``cache/<id>-*.npz``; the reference's where there is none) instead: that
costs decompressing every frame's masks up to the last moment shown, about 0.3 s per paper-size
clip. Each row also gets a short looping H.264 clip of the whole frame at the reference frame times.

Inputs are found through run.json (``predictions`` and ``data``, resolved against the current
directory and the run directory's parents when relative). Anything missing is skipped with a
one-line note; a missing reference bundle skips the whole section. Frames are decoded once per
clip and kept only at tile size; masks are streamed from their .npz one frame at a time.
"""

from __future__ import annotations

import logging
import math
import os
import re
import warnings
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigidbench.errors import RigidBenchError
from rigidbench.folders import RunFolder, SplitFolder, find_prediction
from rigidbench.groundtruth.bundle import Sample
from rigidbench.metrics import METRICS
from rigidbench.perception.base import packed_frames
from rigidbench.report.analysis import ReportData
from rigidbench.report.load import RunInfo
from rigidbench.video import write_video

log = logging.getLogger(__name__)

#: what an unreadable bundle, video or cache raises: its filmstrip row is skipped with the reason
READ_ERRORS = (RigidBenchError, OSError, ValueError, KeyError, zipfile.BadZipFile)

FRAME_FRACTIONS = (0.0, 0.125, 0.25, 0.5, 1.0)  # of the clip: the start, the early motion, the rest state
TILE_CSS = 200          # display width of one frame, CSS px
MAX_STORE_SCALE = 2.0   # tiles are stored at up to twice their display width (sharp on HiDPI screens)
GAP = 4                 # stored px between tiles
CLIP_WIDTH = 320        # looping clips: at most this many px wide
OUTLINE_COLORS = ((255, 214, 10), (50, 210, 255), (255, 45, 146), (48, 209, 88), (255, 149, 0), (191, 90, 242))
MISSING_GREY = 200

Box = tuple[float, float, float, float]  # (x0, y0, x1, y1) in fractions of the frame's width and height
FULL: Box = (0.0, 0.0, 1.0, 1.0)


@dataclass(frozen=True)
class StripRow:
    """One row: `label` (model or 'Reference'), per-example `scores` text, strip image and clip (None when absent),
    and `note` (which outlines, or why there is no strip)."""

    label: str
    scores: str
    image: Path | None
    video: Path | None
    note: str = ""


@dataclass(frozen=True)
class ExampleStrips:
    sample_id: str
    task: str
    partition: str
    times_s: tuple[float, ...]   # the moments shown, seconds from the first frame
    tile_css: int                # display width of one frame
    strip_css: int               # display width of a whole strip
    rows: tuple[StripRow, ...]
    cropped: bool = False        # the stills show the part of the frame around the moving objects
    outlines: str = "reference"  # what the prediction rows outline: "reference" or "perceived" masks


@dataclass(frozen=True)
class Filmstrips:
    examples: tuple[ExampleStrips, ...]
    note: str = ""  # one line when the section, or part of it, was skipped


# ------------------------------------------------------------------------------------- choosing


def choose_examples(data: ReportData, n: int) -> list[int]:
    """Indices into the shared examples: one per task (in task order) where the models' ATE-3D (else the
    first measurement with values) spreads most, the tasks with the largest spread first, at most n."""
    t = data.table
    if n <= 0 or not t.example_ids:
        return []
    spread = np.zeros(len(t.example_ids))
    for metric in ("ate3d", "iou", *t.metrics):
        if metric not in t.metrics:
            continue
        values = t.scores[:, :, t.metric_index(metric)]
        if np.isfinite(values).any():
            rows = values[data.ranked] if data.ranked.any() else values
            with warnings.catch_warnings():  # all-NaN columns: 'Degrees of freedom <= 0'
                warnings.simplefilter("ignore", RuntimeWarning)
                spread = np.nan_to_num(np.nanstd(rows, axis=0), nan=0.0)
            break
    chosen: list[int] = []
    for task in data.tasks:
        idx = np.flatnonzero(t.tasks == task)
        chosen.append(int(idx[np.argmax(spread[idx])]))
    chosen.sort(key=lambda j: -spread[j])
    chosen = chosen[:n]
    for j in np.argsort(-spread, kind="stable"):  # fewer tasks than n: the next largest spreads
        if len(chosen) >= n:
            break
        if int(j) not in chosen:
            chosen.append(int(j))
    order = {task: i for i, task in enumerate(data.tasks)}
    return sorted(chosen, key=lambda j: (order.get(t.tasks[j], len(order)), t.example_ids[j]))


# ------------------------------------------------------------------------------------- locating


def resolve_dir(recorded: str, run_dir: Path) -> Path | None:
    """A directory run.json recorded: as given if absolute, else against the current directory and then each
    parent of the run directory (the run may have been evaluated from elsewhere). None if none exists."""
    if not recorded:
        return None
    path = Path(recorded)
    if path.is_absolute():
        return path if path.is_dir() else None
    for base in (Path.cwd(), *Path(run_dir).resolve().parents):
        if (base / path).is_dir():
            return base / path
    return None


def find_bundle(runs: tuple[RunInfo, ...], sample_id: str) -> Path | None:
    """The reference bundle of `sample_id` under the first run's recorded data directory that holds it."""
    for run in runs:
        data = resolve_dir(run.data, run.path)
        if data is not None and SplitFolder(data).bundle(sample_id).metadata.is_file():
            return data / sample_id
    return None


def perception_cache(run_dir: Path, sample_id: str) -> Path | None:
    """The newest perception cache of this example in the run (``cache/<id>-<backend>-<key>.npz``), or None."""
    found = [p for p in RunFolder(run_dir).cache_dir.glob(f"{sample_id}-*.npz") if not p.name.endswith(".tmp.npz")]
    return max(found, key=lambda p: p.stat().st_mtime) if found else None


# ----------------------------------------------------------------------------------------- arrays


def npz_frames(path: Path, key: str, indices) -> dict[int, np.ndarray]:
    """Frames `indices` (along axis 0) of array `key` in an .npz, read one frame at a time: only the frames
    asked for are kept, and nothing after the last is decompressed. Returns index -> array."""
    from numpy.lib import format as npformat

    wanted = sorted({int(i) for i in indices})
    packed = packed_frames(path, key, wanted)  # the perception cache stores bool masks bit-packed per frame
    if packed is not None:
        return packed
    out: dict[int, np.ndarray] = {}
    with zipfile.ZipFile(path) as archive, archive.open(f"{key}.npy") as fh:
        version = npformat.read_magic(fh)
        reader = npformat.read_array_header_1_0 if version == (1, 0) else npformat.read_array_header_2_0
        shape, fortran, dtype = reader(fh)
        if fortran or dtype.hasobject or not shape:
            with np.load(path, allow_pickle=False) as z:
                arr = z[key]
            return {i: np.array(arr[i]) for i in wanted if i < len(arr)}
        per_frame = int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize
        for i in range(min(wanted[-1] + 1, shape[0]) if wanted else 0):
            buf = fh.read(per_frame)
            if len(buf) < per_frame:
                break
            if i in wanted:
                out[i] = np.frombuffer(buf, dtype=dtype).reshape(shape[1:]).copy()
    return out


def _resize(image: np.ndarray, size: tuple[int, int], nearest: bool = False) -> np.ndarray:
    """image (H,W[,3]) uint8 or bool -> size (W,H)."""
    from PIL import Image

    if image.shape[1] == size[0] and image.shape[0] == size[1]:
        return image
    if image.dtype == bool:
        return np.asarray(Image.fromarray(image.astype(np.uint8) * 255).resize(size, Image.NEAREST)) > 127
    if nearest:
        return np.asarray(Image.fromarray(image).resize(size, Image.NEAREST))
    # reducing_gap: a box reduction first, then the bilinear resize; several times faster on large frames.
    return np.asarray(Image.fromarray(image).resize(size, Image.BILINEAR, reducing_gap=2.0))


def outline(mask: np.ndarray, width: int = 1) -> np.ndarray:
    """mask (H,W) bool -> (H,W) bool boundary (pixels of the mask with a neighbour outside), thickened by
    `width` - 1 pixels on each side."""
    m = np.pad(mask, 1, constant_values=False)
    inner = m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
    edge = mask & ~inner
    for _ in range(max(width - 1, 0)):
        e = np.pad(edge, 1, constant_values=False)
        edge = e[1:-1, 1:-1] | e[:-2, 1:-1] | e[2:, 1:-1] | e[1:-1, :-2] | e[1:-1, 2:]
    return edge


def draw_outlines(tile: np.ndarray, masks: np.ndarray | None, width: int) -> np.ndarray:
    """tile (h,w,3) uint8; masks (N,H,W) bool at any resolution, or None. Returns a copy with coloured outlines."""
    if masks is None:
        return tile
    out = tile.copy()
    for n, mask in enumerate(masks):
        edge = outline(_resize(np.asarray(mask, bool), (tile.shape[1], tile.shape[0])), width)
        out[edge] = OUTLINE_COLORS[n % len(OUTLINE_COLORS)]
    return out


def nearest_indices(times: np.ndarray, wanted: np.ndarray, tol: float) -> list[int | None]:
    """For each wanted time, the index of the nearest of `times` (None when none lies within `tol` s)."""
    times = np.asarray(times, dtype=np.float64)
    out: list[int | None] = []
    for t in np.asarray(wanted, dtype=np.float64):
        if times.size == 0:
            out.append(None)
            continue
        i = int(np.argmin(np.abs(times - t)))
        out.append(i if abs(times[i] - t) <= tol else None)
    return out


def crop(image: np.ndarray, box: Box) -> np.ndarray:
    """image (H,W,...) cropped to `box` (x0, y0, x1, y1) in fractions of its width and height."""
    if box == FULL:
        return image
    h, w = image.shape[:2]
    x0, x1 = int(round(box[0] * w)), max(int(round(box[2] * w)), int(round(box[0] * w)) + 1)
    y0, y1 = int(round(box[1] * h)), max(int(round(box[3] * h)), int(round(box[1] * h)) + 1)
    return image[y0:y1, x0:x1]


def action_box(masks, margin: float = 1.6, smallest: float = 0.4, largest: float = 0.8) -> Box:
    """masks: iterable of (N,H,W) bool. Returns the frame-shaped box (fractions) around all of them, grown by
    `margin` and at least `smallest` of the frame; the full frame when nothing is masked or the box would
    cover more than `largest` of it."""
    union = None
    for m in masks:
        if m is not None and np.asarray(m).size:
            u = np.asarray(m, bool).reshape((-1,) + np.asarray(m).shape[-2:]).any(axis=0)
            union = u if union is None else union | u
    if union is None or not union.any():
        return FULL
    h, w = union.shape
    ys, xs = np.nonzero(union)
    side = max((xs.max() - xs.min() + 1) / w, (ys.max() - ys.min() + 1) / h) * margin
    side = max(side, smallest)
    if side >= largest:
        return FULL
    cx, cy = (xs.min() + xs.max() + 1) / 2 / w, (ys.min() + ys.max() + 1) / 2 / h
    x0 = float(np.clip(cx - side / 2, 0.0, 1.0 - side))
    y0 = float(np.clip(cy - side / 2, 0.0, 1.0 - side))
    return (x0, y0, x0 + side, y0 + side)


def decoded_frames(path: Path, until_s: float):
    """Yields (seconds from the first frame, av.VideoFrame) up to the first frame at or after `until_s`.

    Unlike `rigidbench.video.iter_video`, frames stay undecoded to RGB until asked, so the report
    converts only the few stills at full size and lets FFmpeg scale the clip frames down as it converts.
    Timestamps are pts x time base from the first frame (index / frame rate without them)."""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        rate = float(stream.average_rate) if stream.average_rate else None
        first, t_last = None, -math.inf
        for index, frame in enumerate(container.decode(stream)):
            if frame.pts is not None and (frame.time_base or stream.time_base):
                first = frame.pts if first is None else first
                t = float((frame.pts - first) * (frame.time_base or stream.time_base))
            elif rate:
                t = index / rate
            else:
                raise ValueError(f"{path}: frames carry no timestamps and the stream has no frame rate")
            if t <= t_last:
                continue
            t_last = t
            yield t, frame
            if t >= until_s:
                return


def scan_video(path: Path, still_times: np.ndarray, clip_times: np.ndarray, still_size: tuple[int, int],
               clip_size: tuple[int, int], tol: float, box: Box = FULL,
               ) -> tuple[list[np.ndarray | None], np.ndarray | None]:
    """Decode a clip once. Returns the frames nearest `still_times`, cropped to `box` and at `still_size` (None
    past the clip's end), and the whole frames nearest `clip_times` at `clip_size` (T,h,w,3) (None when the
    clip has no frame near any of them)."""
    stills: list = [None] * len(still_times)
    still_dt = np.full(len(still_times), np.inf)
    clip: list = [None] * len(clip_times)
    clip_dt = np.full(len(clip_times), np.inf)
    until = float(max(still_times.max(), clip_times.max())) + tol

    def still(frame) -> np.ndarray:
        return _resize(crop(frame.to_ndarray(format="rgb24"), box), still_size)

    def small(frame) -> np.ndarray:
        return frame.reformat(width=clip_size[0], height=clip_size[1], format="rgb24").to_ndarray()

    for t, frame in decoded_frames(path, until):
        for dst, dts, times, make in ((stills, still_dt, still_times, still), (clip, clip_dt, clip_times, small)):
            dt = np.abs(times - t)
            closer = np.flatnonzero((dt < dts) & (dt <= tol))
            if closer.size:
                image = make(frame)
                for i in closer:
                    dst[i], dts[i] = image, dt[i]
    if all(c is None for c in clip):
        return stills, None
    last = next(c for c in reversed(clip) if c is not None)
    filled, prev = [], None
    for c in clip:  # before the clip's first frame, hold it; after its last, hold that
        prev = c if c is not None else (prev if prev is not None else last)
        filled.append(prev)
    return stills, np.stack(filled)


def compose_strip(tiles: list[np.ndarray | None], size: tuple[int, int]) -> np.ndarray:
    """tiles: F frames (h,w,3) uint8 (None: a grey tile, the clip ended) -> one (h, F*w + gaps, 3) strip."""
    w, h = size
    strip = np.full((h, len(tiles) * w + (len(tiles) - 1) * GAP, 3), 255, np.uint8)
    for i, tile in enumerate(tiles):
        x = i * (w + GAP)
        strip[:, x:x + w] = tile if tile is not None else MISSING_GREY
    return strip


def _save_jpeg(image: np.ndarray, path: Path) -> Path:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    # Full-resolution colour (no 4:2:0 subsampling): the outlines are thin lines of saturated colour.
    # No optimize=True: with 4:4:4 sampling, PIL's buffer estimate for optimised Huffman tables is too small
    # for detailed images and the encoder fails ("Suspension not allowed here").
    Image.fromarray(image).save(path, quality=88, subsampling=0)
    return path


def _save_clip(frames: np.ndarray, fps: float, path: Path) -> Path | None:
    try:
        write_video(path, frames, fps=fps, crf=26, preset="veryfast")
        return path
    except READ_ERRORS as exc:  # a clip is optional: its strip is still shown
        log.warning("could not write the clip %s: %s", path, exc)
        return None


def slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "run"


# ------------------------------------------------------------------------------------------ build


def _scores_text(data: ReportData, m: int, j: int) -> str:
    t = data.table
    parts = []
    for metric in ("ate3d", "iou", "ssim"):
        if metric in t.metrics:
            v = t.scores[m, j, t.metric_index(metric)]
            if math.isfinite(v):
                parts.append(f"{METRICS[metric].display_name} {v:#.3g}")
    return " · ".join(parts)


class _Example:
    """One reference bundle and what every row shares: the moments shown, the crop, tile and clip sizes, and the
    reference's ground-truth masks of the active actors at those moments."""

    def __init__(self, bundle: Path, clips: bool = True, outlines: str = "reference"):
        self.sample = Sample(bundle)
        self.clips = clips
        self.outlines = outlines
        self.fps = self.sample.fps
        n = self.sample.n_frames
        self.ks = sorted({int(round(f * (n - 1))) for f in FRAME_FRACTIONS})
        self.still_times = np.array(self.ks, dtype=np.float64) / self.fps
        self.clip_times = np.arange(n, dtype=np.float64) / self.fps
        self.tol = 0.75 / self.fps
        self.masks = self._reference_masks()
        self.box = action_box(self.masks.values()) if self.masks else FULL
        w, h = self.sample.resolution
        crop_w = (self.box[2] - self.box[0]) * w
        sw = int(round(min(max(crop_w, TILE_CSS), TILE_CSS * MAX_STORE_SCALE)))
        self.still_size = (sw, max(1, int(round(sw * h / w))))
        cw = int(min(w, CLIP_WIDTH)) // 2 * 2
        self.clip_size = (cw, max(2, int(round(h * cw / w)) // 2 * 2))
        self.line = max(2, int(round(1.5 * sw / TILE_CSS)))  # about 1.5 CSS px

    def _reference_masks(self) -> dict[int, np.ndarray]:
        """frame index -> (A,H,W) ground-truth masks of the active actors; empty if unreadable."""
        path = self.sample.path / "masks.npz"
        try:
            with np.load(path, allow_pickle=False) as z:
                roles = [str(r) for r in z["roles"]]
            active = [k for k, r in enumerate(roles) if r == "active"] or list(range(len(roles)))
            return {k: v[active] for k, v in npz_frames(path, "masks", self.ks).items()}
        except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
            log.warning("%s: no mask outlines (%s)", path, exc)
            return {}

    def tiles(self, stills, masks) -> np.ndarray:
        """stills: F frames (cropped, tile size) or None; masks: F (N,H,W) full-frame masks or None -> the strip."""
        tiles = [None if s is None else draw_outlines(s, None if m is None else crop(np.moveaxis(m, 0, -1), self.box)
                                                      .transpose(2, 0, 1), self.line)
                 for s, m in zip(stills, masks)]
        return compose_strip(tiles, self.still_size)


def _reference_row(ex: _Example, out: Path) -> StripRow:
    sample = ex.sample
    try:
        if all(p.is_file() for p in (sample.frame_paths[k] for k in ex.ks)):
            stills = [_resize(crop(sample.frame(k), ex.box), ex.still_size) for k in ex.ks]
            clip = None
            if ex.clips and sample.video_path.is_file():
                _, clip = scan_video(sample.video_path, ex.still_times[:1], ex.clip_times, ex.still_size,
                                     ex.clip_size, ex.tol)
        else:
            stills, clip = scan_video(sample.video_path, ex.still_times, ex.clip_times, ex.still_size, ex.clip_size,
                                      ex.tol, ex.box)
    except READ_ERRORS as exc:
        return StripRow("Reference", "", None, None, f"reference frames unreadable: {exc}")
    image = _save_jpeg(ex.tiles(stills, [ex.masks.get(k) for k in ex.ks]), out / "00_reference.jpg")
    video = _save_clip(clip, ex.fps, out / "00_reference.mp4") if clip is not None and ex.clips else None
    return StripRow("Reference", "ground truth", image, video, "" if ex.masks else "no masks to outline")


def _model_row(data: ReportData, m: int, j: int, ex: _Example, out: Path) -> StripRow:
    run = data.table.runs[m]
    sample_id = data.table.example_ids[j]
    label, scores = run.name, _scores_text(data, m, j)
    pred_dir = resolve_dir(run.predictions, run.path)
    if pred_dir is None:
        where = f"'{run.predictions}' (from run.json)" if run.predictions else "not recorded in run.json"
        return StripRow(label, scores, None, None, f"no filmstrip: predictions directory {where} not found")
    try:  # evaluate's rule (folders.find_prediction): several videos for one id, or an unreadable one, is not loaded
        pred = find_prediction(pred_dir, sample_id)
    except READ_ERRORS as exc:
        return StripRow(label, scores, None, None, f"no filmstrip: prediction not loaded ({exc})")
    if pred is None:
        return StripRow(label, scores, None, None, f"no filmstrip: no prediction for {sample_id} in {pred_dir}")
    try:
        stills, clip = scan_video(pred, ex.still_times, ex.clip_times, ex.still_size, ex.clip_size, ex.tol, ex.box)
    except READ_ERRORS as exc:
        return StripRow(label, scores, None, None, f"no filmstrip: prediction unreadable ({exc})")
    masks, notes = None, []
    cache = perception_cache(run.path, sample_id) if ex.outlines == "perceived" else None
    if cache is not None:
        try:
            with np.load(cache, allow_pickle=False) as z:
                times = z["times_s"]
            idx = nearest_indices(times, ex.still_times, ex.tol)
            frames = npz_frames(cache, "masks", [i for i in idx if i is not None])
            masks = [None if i is None else frames.get(i) for i in idx]
        except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
            log.warning("%s: perception cache unreadable (%s); outlining the reference masks", cache, exc)
    if masks is None:
        masks = [ex.masks.get(k) for k in ex.ks]
        if ex.outlines == "perceived":
            notes.append("outlines: the reference's masks (no perception cache)")
    if any(s is None for s in stills):
        notes.append("grey: the prediction ended before that moment")
    name = f"{m + 1:02d}_{slug(run.name)}"
    image = _save_jpeg(ex.tiles(stills, masks), out / f"{name}.jpg")
    video = _save_clip(clip, ex.fps, out / f"{name}.mp4") if clip is not None and ex.clips else None
    return StripRow(label, scores, image, video, "; ".join(notes))


def build_filmstrips(data: ReportData, out_dir: Path, n_examples: int = 3, clips: bool = True,
                     outlines: str = "reference", workers: int | None = None) -> Filmstrips:
    """Write <out_dir>/<id>/<row>.jpg (and .mp4) for up to n_examples examples. outlines: "reference" (where the
    objects should be) or "perceived" (what perception found in each prediction). Never raises for missing or
    unreadable inputs: those rows, or the whole section, are skipped with a note."""
    if outlines not in ("reference", "perceived"):
        raise ValueError(f"outlines must be 'reference' or 'perceived', not {outlines!r}")
    t = data.table
    picks = choose_examples(data, n_examples)
    if not picks:
        return Filmstrips(())
    bundles = {j: find_bundle(t.runs, t.example_ids[j]) for j in picks}
    missing = [t.example_ids[j] for j, b in bundles.items() if b is None]
    if len(missing) == len(picks):
        recorded = sorted({r.data for r in t.runs if r.data})
        where = f" (run.json records {', '.join(recorded)})" if recorded else " (run.json records none)"
        return Filmstrips((), f"No example filmstrips: the reference bundles are not on this machine{where}.")
    workers = workers or max(1, min(4, os.cpu_count() or 1))
    examples = []
    with ThreadPoolExecutor(workers) as pool:
        for j in picks:
            if bundles[j] is None:
                continue
            sample_id = t.example_ids[j]
            out = out_dir / sample_id
            try:
                ex = _Example(bundles[j], clips, outlines)
            except READ_ERRORS as exc:
                log.warning("%s: reference bundle unreadable (%s)", bundles[j], exc)
                missing.append(sample_id)
                continue
            jobs = [pool.submit(_reference_row, ex, out)]
            jobs += [pool.submit(_model_row, data, m, j, ex, out) for m in range(len(t.models))]
            rows = tuple(job.result() for job in jobs)
            n = len(ex.ks)
            strip_css = round((n * ex.still_size[0] + (n - 1) * GAP) * TILE_CSS / ex.still_size[0])
            examples.append(ExampleStrips(sample_id, str(t.tasks[j]), str(t.partitions[j]),
                                          tuple(float(x) for x in ex.still_times), TILE_CSS, strip_css, rows,
                                          cropped=ex.box != FULL, outlines=outlines))
    note = f"No reference bundle for {', '.join(missing)}; those examples are not shown." if missing else ""
    log.info("wrote filmstrips of %d examples to %s", len(examples), out_dir)
    return Filmstrips(tuple(examples), note)
