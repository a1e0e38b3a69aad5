"""Preflight check of a predictions directory against the reference samples, before evaluation (the ``validate``
command; ``validation/`` is something else: the metrics' own validation, ``validate-metrics``).

Fast and CPU only: it reads container metadata and demuxed packet timestamps, and decodes just
the first frame of each file, so a hundred clips validate in seconds. Blocking errors (a missing
example, an undecodable file, a clip that does not cover the reference span, duplicate files for
one example, a first frame that is not the reference's first frame, a reference folder still in the
published archive's layout, a damaged reference bundle) give a non-zero exit code; warnings (extra files, an aspect ratio that resizing
will distort, header frame rate disagreeing with the timestamps) do not.

Several samples (generations) per example follow the one naming rule (``folders.sample_item``): ``<id>.s<k>.<ext>``
is sample k of example ``<id>`` and ``<id>.<ext>`` is sample 0, so ``<id>.mp4`` beside ``<id>.s0.mp4`` is an error
naming both. Every sample is checked as one video is; the report says how many samples per example it found.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from rigidbench.benchmark import find_published_layout, is_published_metadata, published_layout_message
from rigidbench.firstframe import (MISMATCH_KIND, compare_first_frames, mismatch_message, read_first_frame,
                                   read_reference_first_frame)
from rigidbench.folders import GENERATION_FILE, METADATA_FILE, SAMPLE_MARK, STATE_SUFFIX, is_sample_stem
from rigidbench.groundtruth.bundle import bundle_dirs, check_bundle, repair_hint
from rigidbench.video import (REFERENCE_FPS, REFERENCE_FRAMES, REFERENCE_SIZE, VIDEO_EXTENSIONS, VideoError,
                              VideoInfo, aligned_length, check_decodable, probe_video, reference_times)

ERROR = "error"
WARNING = "warning"

#: Files `rigidbench predict` writes into a predictions directory besides the videos.
RUN_FILES = frozenset({GENERATION_FILE})
#: Relative aspect-ratio difference above which resizing visibly distorts the clip.
ASPECT_TOLERANCE = 0.02
#: Relative disagreement between header and timestamp frame rates reported as a warning.
FPS_TOLERANCE = 0.01


@dataclass(frozen=True)
class ReferenceSpec:
    """What one reference sample expects: resolution (W,H) in pixels, fps in Hz, frame count."""

    example_id: str
    width: int
    height: int
    fps: float
    frames: int
    #: metadata["source"] of an imported bundle (dataset name, version, ...); None for our renders
    source: Mapping[str, Any] | None = field(default=None, compare=False)

    @property
    def span_s(self) -> float:
        """Seconds from the first to the last reference frame, (frames - 1) / fps."""
        return (self.frames - 1) / self.fps


@dataclass(frozen=True)
class Issue:
    """One finding: severity 'error' (blocks evaluation) or 'warning', with the example and file."""

    severity: str
    kind: str
    message: str
    example_id: str | None = None
    path: Path | None = None


@dataclass
class ValidationReport:
    """Everything validate_predictions found; ``ok`` is False when anything blocks evaluation."""

    pred_dir: Path
    data_dir: Path
    references: dict[str, ReferenceSpec] = field(default_factory=dict)
    files: dict[Path, VideoInfo] = field(default_factory=dict)
    matched: dict[str, Path] = field(default_factory=dict)  # example -> the video of its first sample read
    #: example -> {sample index: video} of every sample read (one sample per example: {0: <id>.<ext>})
    samples: dict[str, dict[int, Path]] = field(default_factory=dict)
    issues: list[Issue] = field(default_factory=list)

    def add(self, severity: str, kind: str, message: str, example_id: str | None = None,
            path: Path | None = None) -> None:
        self.issues.append(Issue(severity, kind, message, example_id, path))

    def of_kind(self, kind: str) -> list[Issue]:
        return [issue for issue in self.issues if issue.kind == kind]

    @property
    def errors(self) -> list[Issue]:
        return [issue for issue in self.issues if issue.severity == ERROR]

    @property
    def warnings(self) -> list[Issue]:
        return [issue for issue in self.issues if issue.severity == WARNING]

    @property
    def missing(self) -> list[str]:
        return sorted(issue.example_id for issue in self.of_kind("missing"))

    @property
    def ok(self) -> bool:
        return not self.errors

    def samples_per_example(self) -> tuple[int, int] | None:
        """(fewest, most) samples read per example that has any; None when none has."""
        counts = [len(found) for found in self.samples.values() if found]
        return (min(counts), max(counts)) if counts else None


def read_reference_specs(data_dir: Path, report: ValidationReport, *, ref_fps: float, ref_frames: int) -> None:
    """Fills report.references from every data_dir/<id>/metadata.json; bad metadata becomes an error."""
    for meta_path in (d / METADATA_FILE for d in bundle_dirs(data_dir)):  # hidden leftovers are not references
        example_id = meta_path.parent.name
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError) as exc:  # ValueError: JSONDecodeError, bytes that are not UTF-8
            report.add(ERROR, "bad_metadata", f"{meta_path}: cannot read ({exc}); {repair_hint(meta_path.parent)}",
                       example_id, meta_path)
            continue
        if not isinstance(meta, dict):
            report.add(ERROR, "bad_metadata", f"{meta_path}: not a JSON object; {repair_hint(meta_path.parent)}",
                       example_id, meta_path)
            continue
        if is_published_metadata(meta):
            report.add(ERROR, "published_layout", published_layout_message(
                meta_path.parent, "metadata.json with task_type and no sample_id"), example_id, meta_path)
            continue
        try:
            width, height = (int(v) for v in meta.get("resolution", REFERENCE_SIZE))
            fps = float(meta.get("fps", ref_fps))
            frames = int(meta.get("frames", ref_frames))
        except (TypeError, ValueError) as exc:
            report.add(ERROR, "bad_metadata", f"{meta_path}: resolution/fps/frames malformed ({exc})",
                       example_id, meta_path)
            continue
        if width <= 0 or height <= 0 or fps <= 0 or frames < 1:
            report.add(ERROR, "bad_metadata", f"{meta_path}: implausible resolution {width}x{height}, "
                       f"fps {fps} or frames {frames}", example_id, meta_path)
            continue
        source = meta.get("source") if isinstance(meta.get("source"), dict) else None
        report.references[example_id] = ReferenceSpec(example_id, width, height, fps, frames, source)
        check_reference(meta_path.parent, report)


def check_reference(bundle_dir: Path, report: ValidationReport) -> None:
    """Adds a damaged_reference error when the reference bundle fails ``check_bundle`` (a missing, truncated
    or inconsistent file), naming the files and what to do. Array shapes and dtypes are read from their
    headers (``deep=False``), so this costs milliseconds per example."""
    problems = check_bundle(bundle_dir, deep=False)
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        report.add(ERROR, "damaged_reference", f"{bundle_dir.name}: the reference bundle {bundle_dir} is damaged: "
                   f"{'; '.join(problems[:3])}{more}; {repair_hint(bundle_dir)}", bundle_dir.name, bundle_dir)


def sample_of_stem(stem: str, references: Mapping[str, Any]) -> tuple[str, int] | None:
    """(example id, sample index) a file stem names under the naming rule: ``<id>`` is sample 0, ``<id>.s<k>``
    sample k (an example id that itself looks like ``x.s1`` is that example); None for no example of
    ``references``."""
    if stem in references:
        return stem, 0
    if is_sample_stem(stem):
        example, _, k = stem.rpartition(SAMPLE_MARK)
        if example in references:
            return example, int(k)
    return None


def match_files(pred_dir: Path, report: ValidationReport) -> tuple[dict[str, dict[int, list[Path]]],
                                                                   dict[str, list[Path]]]:
    """Groups pred_dir entries by expected id: (videos by example and sample index, other files such as
    sidecars by example); strangers become warnings."""
    videos: dict[str, dict[int, list[Path]]] = {}
    others: dict[str, list[Path]] = {}
    for entry in sorted(pred_dir.iterdir()):
        if entry.name.startswith("."):
            continue  # hidden files, including half-written temporaries
        if entry.name.endswith(STATE_SUFFIX):
            continue  # world state written by built-in predictors beside their videos
        if entry.name in RUN_FILES:
            continue  # written by `rigidbench predict` beside the videos
        found = sample_of_stem(entry.stem, report.references)
        if found is None:
            report.add(WARNING, "extra", f"{entry.name}: '{entry.stem}' is not an example id in the data "
                       "directory (nor <id>.s<k>, sample k of one); ignored", None, entry)
        elif entry.suffix.lower() in VIDEO_EXTENSIONS:  # a FIFO or device so named is refused unread (probe)
            videos.setdefault(found[0], {}).setdefault(found[1], []).append(entry)
        else:
            others.setdefault(found[0], []).append(entry)  # e.g. <id>.json written beside the clip
    return videos, others


def duplicate_message(example_id: str, k: int, paths: list[Path]) -> str:
    """The error for several files of one sample: both names of sample 0, or one sample in several formats."""
    names = ", ".join(p.name for p in paths)
    if k == 0 and any(p.stem == example_id for p in paths) and any(p.stem != example_id for p in paths):
        return (f"{example_id}: {names} are both sample 0 (<id>.<ext> is read as sample 0, the same as "
                f"<id>.s0.<ext>); keep one, or rename {example_id}.s0 to the next free sample number")
    which = f"sample {k} of {example_id}" if k or any(p.stem != example_id for p in paths) else example_id
    return f"{which}: {len(paths)} files ({names}); keep exactly one"


def check_file(info: VideoInfo, ref: ReferenceSpec, report: ValidationReport) -> None:
    """Adds issues for one probed prediction: coverage of the reference span, frame rate, aspect ratio."""
    name = info.path.name
    # The rule `evaluate` compares with (video.aligned_length): every reference time must be covered.
    if aligned_length(info.times_s, reference_times(ref.frames, ref.fps)) < ref.frames:
        report.add(ERROR, "too_short", f"{name}: last frame at {info.duration_s:.3f} s ({info.n_frames} frames); "
                   f"it must cover 0 to {ref.span_s:.3f} s ({ref.frames} frames at {ref.fps:g} fps)",
                   ref.example_id, info.path)
    if info.fps_nominal and info.fps_measured:
        if abs(info.fps_nominal - info.fps_measured) > FPS_TOLERANCE * info.fps_nominal:
            report.add(WARNING, "frame_rate", f"{name}: header says {info.fps_nominal:.3f} fps but timestamps "
                       f"give {info.fps_measured:.3f} fps; scoring uses the real timestamps",
                       ref.example_id, info.path)
    aspect = info.width / info.height
    ref_aspect = ref.width / ref.height
    if abs(aspect / ref_aspect - 1.0) > ASPECT_TOLERANCE:
        report.add(WARNING, "aspect_ratio", f"{name}: {info.width}x{info.height} (aspect {aspect:.3f}) will be "
                   f"resized to {ref.width}x{ref.height} (aspect {ref_aspect:.3f}), distorting geometry",
                   ref.example_id, info.path)


def validate_predictions(pred_dir: str | Path, data_dir: str | Path, *, ref_fps: float = REFERENCE_FPS,
                         ref_frames: int = REFERENCE_FRAMES, first_frames: bool = True) -> ValidationReport:
    """pred_dir: <id>.<ext> clips; data_dir: <id>/metadata.json samples. Returns the ValidationReport.

    ref_fps and ref_frames are used for samples whose metadata.json gives no "fps" or "frames".
    first_frames=False skips the first-frame comparison (for randomly initialised test models, whose
    first frame is noise); the command line always makes it.
    """
    pred_dir, data_dir = Path(pred_dir), Path(data_dir)
    report = ValidationReport(pred_dir=pred_dir, data_dir=data_dir)
    if not data_dir.is_dir():
        report.add(ERROR, "no_data", f"data directory {data_dir} does not exist; render it with `rigidbench render`")
        return report
    published = find_published_layout(data_dir)
    if published is not None:  # one error for the folder, not one per sample (and never an "OK")
        report.add(ERROR, "published_layout", published_layout_message(*published), None, published[0])
        return report
    read_reference_specs(data_dir, report, ref_fps=ref_fps, ref_frames=ref_frames)
    if not report.references:
        report.add(ERROR, "no_data", f"{data_dir} holds no samples (subdirectories with metadata.json)")
    if not pred_dir.is_dir():
        report.add(ERROR, "no_predictions", f"predictions directory {pred_dir} does not exist")
        return report
    videos, others = match_files(pred_dir, report)
    for example_id, ref in report.references.items():
        by_sample = videos.get(example_id, {})
        if not by_sample:
            unread = [p.name for p in others.get(example_id, [])]
            hint = (f" (found {', '.join(unread)}, not a video extension we read: use one of "
                    f"{', '.join(VIDEO_EXTENSIONS)})" if unread else "")
            report.add(ERROR, "missing", f"{example_id}: no prediction video in {pred_dir}{hint}", example_id)
            continue
        for k, paths in sorted(by_sample.items()):
            if len(paths) > 1:
                report.add(ERROR, "duplicate", duplicate_message(example_id, k, paths), example_id)
            for path in paths:
                try:
                    info = probe_video(path)
                    check_decodable(path)
                except VideoError as exc:
                    report.add(ERROR, "undecodable", f"{path.name}: {exc.reason}", example_id, path)
                    continue
                report.files[path] = info
                report.matched.setdefault(example_id, path)
                report.samples.setdefault(example_id, {}).setdefault(k, path)
                check_file(info, ref, report)
                if first_frames:
                    check_first_frame_of(path, ref, data_dir, report)
    check_sample_counts(report)
    return report


def check_sample_counts(report: ValidationReport) -> None:
    """A warning when examples have different numbers of samples (each is scored by its own samples' mean, so
    an example with fewer weighs the same but is known less precisely)."""
    span = report.samples_per_example()
    if span is None or span[0] == span[1]:
        return
    counts: dict[int, int] = {}
    for found in report.samples.values():
        counts[len(found)] = counts.get(len(found), 0) + 1
    spread = ", ".join(f"{n} with {k}" for k, n in sorted(counts.items()))
    report.add(WARNING, "uneven_samples", f"examples have different numbers of samples ({spread}); each example "
               "is scored by the mean of its own samples")


def check_first_frame_of(path: Path, ref: ReferenceSpec, data_dir: Path, report: ValidationReport) -> None:
    """Adds a first_frame_mismatch error when the prediction at ``path`` does not start from its reference's
    first frame (generated from another set's inputs). A reference without a first frame (no frames/00000.png
    and no video.mp4) is not compared."""
    ref_first = _reference_first_frame(data_dir / ref.example_id)
    if ref_first is None:
        return
    try:
        pred_first = read_first_frame(path)
    except VideoError as exc:
        report.add(ERROR, "undecodable", f"{path.name}: {exc.reason}", ref.example_id, path)
        return
    first = compare_first_frames(pred_first, ref_first)
    if not first.matches:
        report.add(ERROR, MISMATCH_KIND, mismatch_message(path, ref.example_id, data_dir, {"source": ref.source},
                                                          first.correlation, first.orientation,
                                                          first.turned_correlation), ref.example_id, path)


def _reference_first_frame(bundle_dir: Path) -> np.ndarray | None:
    try:
        return read_reference_first_frame(bundle_dir)
    except (OSError, ValueError, VideoError):
        return None  # an unreadable reference frame is check_bundle's to report, not a prediction's fault


def format_report(report: ValidationReport) -> str:
    """Returns the report as plain text: a summary, one line per file, then errors and warnings."""
    n_expected = len(report.references)
    lines = [f"predictions: {report.pred_dir}", f"reference:   {report.data_dir} ({n_expected} examples)",
             f"found {len(report.matched)}/{n_expected} examples, {len(report.missing)} missing, "
             f"{len(report.errors)} errors, {len(report.warnings)} warnings"]
    span = report.samples_per_example()
    if span is not None and span[1] > 1:
        per = f"{span[0]}" if span[0] == span[1] else f"{span[0]} to {span[1]}"
        lines.append(f"samples per example: {per} ({len(report.files)} videos read; "
                     "<id>.<ext> is sample 0, <id>.s<k>.<ext> sample k)")
    lines.append("")
    if report.files:
        lines.append(f"{'file':<32} {'codec':<8} {'size':>11} {'fps hdr':>8} {'fps ts':>8} {'frames':>6} "
                     f"{'last t':>7}")
        for path, info in sorted(report.files.items()):
            hdr = f"{info.fps_nominal:.3f}" if info.fps_nominal else "-"
            meas = f"{info.fps_measured:.3f}" if info.fps_measured else "-"
            lines.append(f"{path.name:<32} {info.codec:<8} {info.width:>5}x{info.height:<5} {hdr:>8} {meas:>8} "
                         f"{info.n_frames:>6} {info.duration_s:>6.3f}s")
        lines.append("")
    for title, issues in (("ERRORS (block evaluation)", report.errors), ("WARNINGS", report.warnings)):
        if issues:
            lines.append(f"{title}:")
            lines.extend(f"  [{issue.kind}] {issue.message}" for issue in issues)
            lines.append("")
    lines.append("OK: ready for evaluation" if report.ok else
                 f"BLOCKED: fix the {len(report.errors)} errors above before `rigidbench evaluate`")
    return "\n".join(lines)


def main(pred_dir: str | Path, data_dir: str | Path) -> int:
    """Validates, prints the report, and returns the exit code: 0 when evaluation can run, 1 otherwise."""
    report = validate_predictions(pred_dir, data_dir)
    print(format_report(report))
    return 0 if report.ok else 1
