"""What a video model is given: the first frame, the prompt and the negative prompt.

    for example in rigidbench.Benchmark.load("data/eval"):
        video = my_model(example.image, example.prompt, example.negative_prompt)
        save(video, f"predictions/my_model/{example.id}.mp4")

The prompt is the task prompt followed by the paper's fixed suffix (appendix B.1); the negative
prompt is the paper's, verbatim, for models that accept one.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator

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
    task_prompt: str

    def to_dict(self) -> dict:
        d = asdict(self)
        d["image"] = str(self.image)
        return d


class Benchmark:
    """The examples of one rendered split directory (``data/eval`` holds the 100 evaluation examples)."""

    def __init__(self, root: Path, examples: list[Example]):
        self.root = root
        self.examples = examples

    @classmethod
    def load(cls, data_dir: str | Path) -> "Benchmark":
        root = Path(data_dir)
        if not root.is_dir():
            raise FileNotFoundError(f"{root}: no rendered examples here; run `rigidbench render --split eval "
                                    f"--data {root.parent if root.name in ('eval', 'train') else root}` first")
        examples = []
        for sample_dir in sorted(p for p in root.iterdir() if p.is_dir()):
            meta_path = sample_dir / "metadata.json"
            if not meta_path.exists():
                continue  # an unfinished render; complete bundles always carry metadata.json
            meta = json.loads(meta_path.read_text())
            image = sample_dir / "frames" / "00000.png"
            if not image.exists():
                raise FileNotFoundError(f"{image}: the first frame of example {sample_dir.name} is missing; "
                                        "re-render this example")
            examples.append(Example(id=sample_dir.name, image=image, prompt=full_prompt(meta["prompt"]),
                                    negative_prompt=NEGATIVE_PROMPT, task=meta["task"],
                                    partition=meta["partition"], task_prompt=meta["prompt"]))
        if not examples:
            raise FileNotFoundError(f"{root}: no rendered examples (directories with metadata.json) found")
        return cls(root, examples)

    def __iter__(self) -> Iterator[Example]:
        return iter(self.examples)

    def __len__(self) -> int:
        return len(self.examples)

    def __getitem__(self, sample_id: str) -> Example:
        for ex in self.examples:
            if ex.id == sample_id:
                return ex
        raise KeyError(f"no example '{sample_id}' in {self.root}")


def write_inputs(data_dir: str | Path, out: str | Path | None = None) -> Path:
    """Write inputs.jsonl (one example per line) for model runners in any language."""
    bench = Benchmark.load(data_dir)
    out = Path(out) if out else Path(data_dir) / "inputs.jsonl"
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text("".join(json.dumps(ex.to_dict()) + "\n" for ex in bench))
    tmp.replace(out)
    return out
