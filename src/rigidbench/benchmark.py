"""What a video model is given: the first frame, the prompt and the negative prompt (the dataset API, kept at the
release's import path; benchmarks/ at the repository root holds timing scripts).

    for example in rigidbench.Benchmark.load("data/eval"):
        video = my_model(example.image, example.prompt, example.negative_prompt)
        save(video, f"predictions/my_model/{example.id}.mp4")

The prompt is the task prompt followed by the paper's fixed suffix (appendix B.1); the negative
prompt is the paper's, verbatim, for models that accept one.

``Benchmark.load`` reads our renders and bundles made by ``rigidbench import`` from the published
evaluation set alike, given a split directory (``data/eval``) or a data root holding one
(``data``). A folder still in the published archive's own layout is refused with the command that
converts it. ``write_inputs`` writes ``inputs.jsonl`` with the keys of the authors' release
(``id``, ``image`` relative to the file's folder, ``scene_prompt``, ``prompt``, ``negative_prompt``,
``duration_seconds``, ``reference_fps``, ``reference_frames``, ``reference_resolution``, ``task``,
``protocol``) beside ours (``partition``, ``task_prompt``), so a generation script written for the
release runs unchanged. The file goes where the release puts it, ``DATA/inputs.jsonl`` beside
``DATA/eval`` (``inputs_path``), whichever of the two ``--data`` names. ``BenchmarkExample`` and
``export_inputs_jsonl`` are the release's names for ``Example`` and ``write_inputs``; like the
release's ``Benchmark``, ours is indexed by position (``bench[0]``), and by id as well
(``bench["00007"]``).

Standard library only: ``import rigidbench`` imports this module.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from .atomic import write_text
from .errors import BundleError
from .folders import BundleFolder, inputs_path
from .groundtruth.layout import (SAMPLE_WHAT, PublishedLayoutError, check_not_published_layout,  # noqa: F401
                                 find_published_layout, is_published_metadata, published_layout_message,
                                 sample_dirs)

PROMPT_SUFFIX = (
    "Static shot, locked-off camera, fixed tripod, stationary framing. No camera movement, no pan, no tilt, "
    "no zoom, no dolly, no drift, no handheld shake. Real-time playback at natural speed, 24 fps, no slow motion, "
    "no time-lapse. Realistic rigid-body physics: gravity, momentum, friction, and collisions consistent with "
    "reality. Photorealistic, continuous single take, no cuts. Motion begins on the first frame."
)

NEGATIVE_PROMPT = (
    "camera motion, camera shake, pan, tilt, zoom, dolly, parallax, handheld, tracking shot, slow motion, slo-mo, "
    "time-lapse, sped-up, motion blur, static start, frozen start, hesitation, delayed action, pause at beginning, "
    "floating object, levitation, hovering, teleportation, morphing, warping, deformed geometry, scene cut, "
    "jump cut, montage, transition, multiple shots, text, watermark, low quality, low resolution"
)

#: The evaluation protocol's name, as the authors' release writes it into inputs.jsonl.
PROTOCOL = "rigidbench-v1"
#: What a bundle whose metadata.json does not say is assumed to hold (the paper preset; video.REFERENCE_*).
DEFAULT_FPS = 24.0
DEFAULT_FRAMES = 49
DEFAULT_RESOLUTION = (1280, 704)


def full_prompt(task_prompt: str) -> str:
    return f"{task_prompt.strip()} {PROMPT_SUFFIX}"


@dataclass(frozen=True)
class Example:
    id: str
    image: Path  # the conditioning first frame (PNG)
    prompt: str  # task prompt + suffix
    negative_prompt: str
    task: str
    partition: str
    task_prompt: str  # the task prompt without the suffix (the release calls it scene_prompt)
    reference_fps: float = DEFAULT_FPS
    reference_frames: int = DEFAULT_FRAMES
    reference_resolution: tuple[int, int] = DEFAULT_RESOLUTION  # (W, H)
    protocol: str = PROTOCOL

    @property
    def scene_prompt(self) -> str:
        """The release's name for the task prompt without the suffix."""
        return self.task_prompt

    @property
    def duration_seconds(self) -> float:
        """Seconds from the first to the last reference frame, (frames - 1) / fps: 2.0 for 49 frames at 24 fps."""
        return (self.reference_frames - 1) / self.reference_fps

    def to_dict(self, relative_to: str | Path | None = None) -> dict[str, Any]:
        """One inputs.jsonl row: the release's keys, then ours.

        ``image`` is a POSIX path relative to ``relative_to`` (the folder of the inputs file) when the
        frame lies below it, else absolute; without ``relative_to`` it is the path as loaded.
        """
        fps = self.reference_fps
        return {"id": self.id, "image": _image_path(self.image, relative_to), "scene_prompt": self.scene_prompt,
                "prompt": self.prompt, "negative_prompt": self.negative_prompt,
                "duration_seconds": self.duration_seconds,
                "reference_fps": int(fps) if float(fps).is_integer() else fps,
                "reference_frames": self.reference_frames, "reference_resolution": list(self.reference_resolution),
                "task": self.task, "protocol": self.protocol, "partition": self.partition,
                "task_prompt": self.task_prompt}


def _image_path(image: Path, folder: str | Path | None) -> str:
    """Links are not followed: an imported bundle's frame linked into the extracted archive stays
    ``eval/<id>/frames/00000.png``."""
    if folder is None:
        return str(image)
    absolute = Path(os.path.abspath(image))
    try:
        return absolute.relative_to(os.path.abspath(folder)).as_posix()
    except ValueError:
        return str(absolute)


# -- loading -------------------------------------------------------------------------------------


def _reference_facts(meta: dict, meta_path: Path) -> tuple[float, int, tuple[int, int]]:
    try:
        fps = float(meta.get("fps", DEFAULT_FPS))
        frames = int(meta.get("frames", DEFAULT_FRAMES))
        width, height = (int(v) for v in meta.get("resolution", DEFAULT_RESOLUTION))
    except (TypeError, ValueError) as exc:
        raise BundleError(f"{meta_path}: fps, frames or resolution malformed ({exc})") from None
    if fps <= 0 or frames < 1 or width <= 0 or height <= 0:
        raise BundleError(f"{meta_path}: implausible fps {fps}, frames {frames} or resolution {width}x{height}")
    return fps, frames, (width, height)


def _load_example(sample_dir: Path) -> Example:
    bundle = BundleFolder(sample_dir)
    meta_path = bundle.metadata
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError) as exc:
        raise BundleError(f"{meta_path}: cannot read ({exc})") from None
    if is_published_metadata(meta):
        raise PublishedLayoutError(published_layout_message(sample_dir.parent, SAMPLE_WHAT))
    prompt = meta.get("prompt")
    if prompt is None and bundle.prompt.is_file():
        prompt = bundle.prompt.read_text().strip()
    if not prompt or "task" not in meta:
        raise BundleError(f"{meta_path}: no prompt or task; re-render or re-import example {sample_dir.name}")
    image = bundle.frame(0)
    if not image.exists():
        raise FileNotFoundError(f"{image}: the first frame of example {sample_dir.name} is missing; "
                                "re-render (or re-import) this example")
    fps, frames, resolution = _reference_facts(meta, meta_path)
    return Example(id=sample_dir.name, image=image, prompt=full_prompt(prompt), negative_prompt=NEGATIVE_PROMPT,
                   task=meta["task"], partition=meta.get("partition", ""), task_prompt=prompt.strip(),
                   reference_fps=fps, reference_frames=frames, reference_resolution=resolution)


class Benchmark:
    """The examples of one split directory (``data/eval`` holds the 100 evaluation examples)."""

    def __init__(self, root: Path, examples: list[Example]):
        self.root = root
        self.examples = examples

    @classmethod
    def load(cls, data_dir: str | Path, split: str = "eval") -> "Benchmark":
        """data_dir: a split directory (``data/eval``: one bundle per subdirectory) or a data root holding
        ``split`` (``data``). Renders and imported bundles alike; the published layout is refused."""
        root = Path(data_dir)
        if not root.is_dir():
            raise FileNotFoundError(f"{root}: no rendered examples here; run `rigidbench render --split eval "
                                    f"--data {root.parent if root.name in ('eval', 'train') else root}` first")
        check_not_published_layout(root)
        bundles = list(sample_dirs(root))
        split_dir = root
        if not bundles:
            split_dir = root / split
            bundles = list(sample_dirs(split_dir))
        if not bundles:
            raise FileNotFoundError(f"{root}: no examples (directories with metadata.json) here or in "
                                    f"{root / split}; render them with `rigidbench render --split {split}` or "
                                    f"import the published set with `rigidbench import`")
        return cls(split_dir, [_load_example(d) for d in bundles])

    def __iter__(self) -> Iterator[Example]:
        return iter(self.examples)

    def __len__(self) -> int:
        return len(self.examples)

    def __getitem__(self, key: int | slice | str) -> Any:
        """``bench[0]``: the first example, by position as in the authors' release (negative counts from
        the end; IndexError past it; ``bench[:10]`` a list); ``bench["00007"]``: the example of that id
        (KeyError when none)."""
        if isinstance(key, slice):
            return self.examples[key]
        if isinstance(key, str):
            for ex in self.examples:
                if ex.id == key:
                    return ex
            raise KeyError(f"no example '{key}' in {self.root}")
        if isinstance(key, bool) or not hasattr(key, "__index__"):
            raise TypeError(f"a Benchmark is indexed by position (int) or example id (str), not {type(key).__name__}")
        try:
            return self.examples[key]
        except IndexError:
            raise IndexError(f"example {key} out of range: {self.root} has {len(self.examples)} examples") from None


#: The release's name for an example.
BenchmarkExample = Example


def write_inputs(data_dir: str | Path, out: str | Path | None = None) -> Path:
    """Write inputs.jsonl (one example per line) for model runners in any language; returns its path.

    data_dir: as for ``Benchmark.load``; out defaults to ``inputs_path`` of the split directory loaded
    (``DATA/inputs.jsonl`` whether ``data_dir`` is ``DATA`` or ``DATA/eval``). Each row's ``image`` is
    relative to the file's own folder (absolute when the frame is not below it). The file is replaced
    atomically.
    """
    bench = Benchmark.load(data_dir)
    out = Path(out) if out else inputs_path(bench.root)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = "".join(json.dumps(ex.to_dict(relative_to=out.parent), ensure_ascii=False) + "\n" for ex in bench)
    return write_text(out, text, encoding="utf-8", unique=True)


def export_inputs_jsonl(data_dir: str | Path, output: str | Path | None = None) -> Path:
    """The authors' release's name and argument for ``write_inputs``."""
    return write_inputs(data_dir, output)
