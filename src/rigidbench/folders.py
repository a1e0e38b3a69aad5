"""Typed homes for the three folders a user handles: their file names and how to find what is in them.

- a split of bundles (``data/eval/``): one folder per example, ``<id>/`` with the files below
  (``SplitFolder``, ``BundleFolder``), and the model inputs file beside it (``inputs_path``);
- a predictions folder (``predictions/MODEL/``): ``<id>.<ext>`` videos (``VIDEO_EXTENSIONS``), the
  world state beside each (``<id>.state.npz``), ``generation.json``, and the hidden ``.stages/`` (the
  ledger), ``.hosted/`` and ``.scratch/`` (``PredictionsFolder``;
  ``find_prediction`` is the one rule for an example's video);
- a run folder (``runs/MODEL/``): ``results.json``, ``run.json``, ``examples/<id>.json|.npz|.readouts.json``
  and ``cache/`` (``RunFolder``).

Every producer and reader takes the names from here. Standard library only (and ``errors``):
``rigidbench.benchmark``, imported by ``import rigidbench``, uses it.
"""

from __future__ import annotations

import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path

from .errors import EvaluationError, VideoError

# -- a split of bundles --------------------------------------------------------------------------

FRAMES_DIR = "frames"
VIDEO_FILE = "video.mp4"
MASKS_FILE = "masks.npz"
DEPTH_FILE = "depth.npz"
TRAJECTORIES_FILE = "trajectories.npz"
CONTACTS_FILE = "contacts.json"
TRACKS_FILE = "tracks.npz"
METADATA_FILE = "metadata.json"
PROMPT_FILE = "prompt.txt"
SPEC_FILE = "scene_spec.json"
BUNDLE_FILES = (VIDEO_FILE, MASKS_FILE, DEPTH_FILE, TRAJECTORIES_FILE, CONTACTS_FILE, TRACKS_FILE, METADATA_FILE,
                PROMPT_FILE, SPEC_FILE)


def frame_name(k: int) -> str:
    """File name of frame ``k`` (0-based) inside ``frames/``."""
    return f"{k:05d}.png"


@dataclass(frozen=True)
class BundleFolder:
    """One example's reference bundle, ``<split>/<id>/``."""

    path: Path

    @property
    def sample_id(self) -> str:
        return self.path.name

    @property
    def metadata(self) -> Path:
        return self.path / METADATA_FILE

    @property
    def prompt(self) -> Path:
        return self.path / PROMPT_FILE

    @property
    def video(self) -> Path:
        return self.path / VIDEO_FILE

    @property
    def frames(self) -> Path:
        return self.path / FRAMES_DIR

    def frame(self, k: int) -> Path:
        return self.path / FRAMES_DIR / frame_name(k)


@dataclass(frozen=True)
class SplitFolder:
    """A split of bundles, ``data/<split>/``: ``<id>/`` per example."""

    path: Path

    def __post_init__(self):
        object.__setattr__(self, "path", Path(self.path))

    def bundle(self, sample_id: str) -> BundleFolder:
        return BundleFolder(self.path / sample_id)


#: The model inputs file that `rigidbench inputs`, `import` and `download` write (where: ``inputs_path``).
INPUTS_FILE = "inputs.jsonl"
#: The split directory whose inputs file lies beside it, in the data root, as the authors' release writes it.
EVAL_SPLIT = "eval"


def inputs_path(split_dir: str | Path) -> Path:
    """Where the inputs file of a split directory goes: ``DATA/inputs.jsonl`` for ``DATA/eval`` (the data
    root, as the authors' release writes it); a split directory of another name (``DATA/train``, or bundles
    directly in a folder) keeps its own, ``DIR/inputs.jsonl``."""
    split_dir = Path(split_dir)
    return (split_dir.parent if split_dir.name == EVAL_SPLIT else split_dir) / INPUTS_FILE


# -- a predictions folder ------------------------------------------------------------------------

#: Extensions read as videos (anything FFmpeg demuxes works; these are the ones we look for).
VIDEO_EXTENSIONS = (".mp4", ".webm", ".mov", ".mkv", ".avi", ".gif")
#: Largest prediction file read (bytes); a bigger one is refused before it is hashed or decoded.
MAX_VIDEO_BYTES = 2 * 1024 ** 3
STATE_SUFFIX = ".state.npz"  # the exact world state a built-in predictor writes beside its video
GENERATION_FILE = "generation.json"
HOSTED_DIR = ".hosted"  # hidden: validate, evaluate and the predict stage's scan skip it
#: A run's temporary files (re-rendered bundles, Blender's own); hidden, so validate and evaluate skip it.
SCRATCH_DIR = ".scratch"


def state_path(video_path: str | Path) -> Path:
    """The world-state file beside a prediction's video: ``<id>.state.npz`` for ``<id>.<ext>``."""
    video_path = Path(video_path)
    return video_path.with_name(video_path.stem + STATE_SUFFIX)


def check_video_file(path: str | Path, max_bytes: int = MAX_VIDEO_BYTES, what: str = "video file") -> int:
    """path: a video file to read (a symbolic link to one is fine). Returns its size in bytes; raises
    VideoError, without reading it, for anything but a regular file (a FIFO, a device such as /dev/zero, a
    directory, a socket), an empty file, or one over ``max_bytes`` (MAX_VIDEO_BYTES), any of which could
    otherwise block or exhaust a reader."""
    path = Path(path)
    try:
        st = path.stat()  # follows symbolic links: what would be read
    except FileNotFoundError:
        raise VideoError(path, "file not found (or a broken symbolic link)") from None
    except OSError as exc:
        raise VideoError(path, f"cannot be read ({exc.strerror or exc})") from None
    if not stat.S_ISREG(st.st_mode):
        kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else "a character device" if
                stat.S_ISCHR(st.st_mode) else "a block device" if stat.S_ISBLK(st.st_mode) else "a directory"
                if stat.S_ISDIR(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
        target = f" (a link to {os.path.realpath(path)})" if path.is_symlink() else ""
        raise VideoError(path, f"is {kind}{target}, not a regular {what}; only regular files are read")
    if st.st_size == 0:
        raise VideoError(path, "file is empty (0 bytes)")
    if st.st_size > max_bytes:
        raise VideoError(path, f"is {st.st_size / 1e9:.2f} GB, over the {max_bytes / 1e9:.2f} GB limit for one "
                               f"{what} (MAX_VIDEO_BYTES); re-encode it (a 2-second clip needs far less)")
    return int(st.st_size)


def find_prediction(pred_dir: str | Path, sample_id: str) -> Path | None:
    """The one rule for an example's prediction: pred_dir/<id>.<ext> for the one video extension present
    (several: EvaluationError), None for none. The file is checked before anything reads it: a regular file
    (or a link to one) of at most MAX_VIDEO_BYTES, else VideoError (a FIFO or a link to /dev/zero would block
    a reader for ever); so is the world-state file beside it, where there is one."""
    pred_dir = Path(pred_dir)
    found = [pred_dir / f"{sample_id}{ext}" for ext in VIDEO_EXTENSIONS
             if (pred_dir / f"{sample_id}{ext}").exists() or (pred_dir / f"{sample_id}{ext}").is_symlink()]
    if len(found) > 1:
        raise EvaluationError(f"{sample_id}: several predictions ({', '.join(p.name for p in found)}); keep one")
    if not found:
        return None
    return check_prediction(found[0])


def check_prediction(path: Path) -> Path:
    """``path``, a prediction's video, once it and the world-state file beside it (where there is one) are
    checked as ``check_video_file`` checks a file (VideoError otherwise)."""
    check_video_file(path)
    state = state_path(path)
    if state.exists() or state.is_symlink():
        check_video_file(state, what="world-state file")
    return path


# -- several samples (generations) per example ----------------------------------------------------
# The one naming rule: sample k of example <id> is ``<id>.s<k>.<ext>`` (k = 0, 1, ...; no leading zeros), and
# ``<id>.<ext>`` is read as sample 0 (one sample per example, as always). ``rigidbench predict --samples K``
# writes sample 0 as ``<id>.<ext>`` and the others as ``<id>.s<k>.<ext>``, so raising K later pays only for the
# new samples. The driver's item for sample k is named like its file without the extension (``sample_item``).

SAMPLE_MARK = ".s"
_SAMPLE_SUFFIX = re.compile(r"\.s(0|[1-9][0-9]*)$")


def sample_item(example_id: str, k: int) -> str:
    """The name of sample ``k`` of ``example_id`` (its file's stem and the stages' item id): ``<id>`` for
    k = 0, ``<id>.s<k>`` otherwise."""
    k = int(k)
    if k < 0:
        raise ValueError(f"sample index must be >= 0, got {k}")
    return example_id if k == 0 else f"{example_id}{SAMPLE_MARK}{k}"


def find_samples(pred_dir: str | Path, example_id: str) -> dict[int, Path]:
    """Every sample of ``example_id`` in ``pred_dir``, ``{k: video}`` sorted by k (the naming rule above), each
    checked as ``find_prediction`` checks one. Both ``<id>.<ext>`` and ``<id>.s0.<ext>``, or one sample in
    two formats, is an EvaluationError naming the files."""
    found = sample_files(pred_dir, example_id)
    for path in found.values():
        check_prediction(path)
    return found


def sample_files(pred_dir: str | Path, example_id: str) -> dict[int, Path]:
    """``find_samples`` without checking the files (a stage that checks each sample on its own, so that one
    sample that is not a regular file fails alone). Both ``<id>.<ext>`` and ``<id>.s0.<ext>``, or one sample in
    two formats, is an EvaluationError naming the files."""
    pred_dir = Path(pred_dir)
    found: dict[int, list[Path]] = {}
    prefix = f"{example_id}{SAMPLE_MARK}"
    try:
        entries = list(os.scandir(pred_dir))
    except FileNotFoundError:
        return {}
    for entry in entries:
        path = Path(entry.path)
        if path.suffix.lower() not in VIDEO_EXTENSIONS or not path.name.startswith(example_id):
            continue
        stem = path.name[:-len(path.suffix)]
        if stem == example_id:
            found.setdefault(0, []).append(path)
        elif stem.startswith(prefix) and _SAMPLE_SUFFIX.search(stem) and stem[:stem.rfind(SAMPLE_MARK)] == example_id:
            found.setdefault(int(stem[len(prefix):]), []).append(path)
    for k, paths in found.items():
        if len(paths) > 1:
            names = ", ".join(sorted(p.name for p in paths))
            raise EvaluationError(f"{example_id}: sample {k} has several videos ({names}); keep one (the naming "
                                  f"rule: <id>.<ext> or <id>.s0.<ext> is sample 0, <id>.s<k>.<ext> sample k)")
    return {k: found[k][0] for k in sorted(found)}


def is_sample_stem(stem: str) -> bool:
    """Whether a file stem names a sample k of some example under the naming rule (``<id>.s<k>``)."""
    return bool(_SAMPLE_SUFFIX.search(stem))


def split_sample_item(stem: str) -> tuple[str, int]:
    """(example id, k) of a sample's name (``sample_item``'s inverse): ``<id>.s<k>`` -> (id, k), else (stem, 0).
    For a file whose record cannot be read; a readable record says its ``id`` and ``sample`` itself."""
    match = _SAMPLE_SUFFIX.search(stem)
    return (stem[:match.start()], int(match.group(1))) if match else (stem, 0)


@dataclass(frozen=True)
class PredictionsFolder:
    """A predictions folder, ``predictions/MODEL/``."""

    path: Path

    def __post_init__(self):
        object.__setattr__(self, "path", Path(self.path))

    def video(self, sample_id: str, ext: str = ".mp4") -> Path:
        return self.path / f"{sample_id}{ext}"

    def state(self, sample_id: str) -> Path:
        return state_path(self.video(sample_id))

    def find(self, sample_id: str) -> Path | None:
        return find_prediction(self.path, sample_id)

    @property
    def generation(self) -> Path:
        return self.path / GENERATION_FILE

    @property
    def hosted_dir(self) -> Path:
        return self.path / HOSTED_DIR

    def hosted_state(self, sample_id: str) -> Path:
        return self.hosted_dir / f"{sample_id}.json"

    @property
    def scratch_dir(self) -> Path:
        return self.path / SCRATCH_DIR


# -- a run folder --------------------------------------------------------------------------------

RESULTS_FILE = "results.json"
RUN_FILE = "run.json"
EXAMPLES_DIR = "examples"
CACHE_DIR = "cache"
READOUTS_SUFFIX = ".readouts.json"


@dataclass(frozen=True)
class RunFolder:
    """A run folder, ``runs/MODEL/``: what ``rigidbench evaluate`` writes and ``report``/``readouts`` read."""

    path: Path

    def __post_init__(self):
        object.__setattr__(self, "path", Path(self.path))

    @property
    def results(self) -> Path:
        return self.path / RESULTS_FILE

    @property
    def run(self) -> Path:
        return self.path / RUN_FILE

    @property
    def examples_dir(self) -> Path:
        return self.path / EXAMPLES_DIR

    @property
    def cache_dir(self) -> Path:
        return self.path / CACHE_DIR

    def record(self, sample_id: str) -> Path:
        """``examples/<id>.json``: the example's score record."""
        return self.examples_dir / f"{sample_id}.json"

    def arrays(self, sample_id: str) -> Path:
        """``examples/<id>.npz``: the example's per-frame values."""
        return self.examples_dir / f"{sample_id}.npz"

    def readouts(self, sample_id: str) -> Path:
        """``examples/<id>.readouts.json``: every readout of the example in full."""
        return self.examples_dir / f"{sample_id}{READOUTS_SUFFIX}"

    def records(self) -> list[Path]:
        """The score records, sorted: ``<id>.json`` and the samples' ``<id>.s<k>.json`` (not ``<id>.readouts.json``
        or other ``<id>.x.json``). A record's ``id`` and ``sample`` say which example and sample it scored."""
        return sorted(p for p in self.examples_dir.glob("*.json") if _record_stem(p.stem))


def _record_stem(stem: str) -> bool:
    """Whether ``stem`` names a score record: ``<id>`` or ``<id>.s<k>`` with k >= 1 (as ``sample_item`` names)."""
    example, k = split_sample_item(stem)
    return "." not in example and sample_item(example, k) == stem
