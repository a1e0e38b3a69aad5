"""The fixed training (5,000) and evaluation (100) manifests.

Both are generated deterministically from ``configs/splits.yaml``; a row fixes the task, scene,
support surface, seed, partition and the allowed objects, so a sample id determines its example.

- Training: every training scene gets ``per_scene`` rows, task labels follow ``task_counts``
  (shuffled once with the training seed), objects are the training objects.
- Evaluation: each partition (in-distribution, OOD scene, OOD object, OOD both) holds
  ``per_task`` rows of every task; scenes cycle through the partition's scene set in a seeded
  order; allowed objects are the partition's object set.
- Seeds are distinct within and across the two splits, so no evaluation example repeats a
  training example.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .atomic import write_text
from .config import ConfigError, Registry

SPLITS = ("train", "eval")
_SEED_SPACE = 2**31 - 1


@dataclass(frozen=True)
class ManifestRow:
    sample_id: str
    split: str
    task: str
    scene: str
    surface: str
    seed: int
    partition: str
    allowed_objects: tuple[str, ...]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["allowed_objects"] = list(self.allowed_objects)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ManifestRow":
        return cls(sample_id=str(d["sample_id"]), split=str(d["split"]), task=str(d["task"]), scene=str(d["scene"]),
                   surface=str(d["surface"]), seed=int(d["seed"]), partition=str(d["partition"]),
                   allowed_objects=tuple(d["allowed_objects"]))


def _surface(rng: np.random.Generator, registry: Registry, scene: str) -> str:
    supports = registry.scene(scene).supports
    return supports[int(rng.integers(len(supports)))].name


def _unique_seeds(rng: np.random.Generator, n: int, exclude: set[int]) -> list[int]:
    seeds: list[int] = []
    seen = set(exclude)
    while len(seeds) < n:
        for s in rng.integers(0, _SEED_SPACE, size=n - len(seeds)).tolist():
            if s not in seen:
                seen.add(s)
                seeds.append(int(s))
    return seeds


def train_rows(registry: Registry) -> list[ManifestRow]:
    cfg = registry.splits
    scenes = registry.scenes_in("train")
    objects = registry.objects_in("train")
    total = cfg.train_per_scene * len(scenes)
    counted = sum(cfg.train_task_counts.values())
    if counted != total:
        raise ConfigError(f"splits.yaml: field 'train.task_counts': counts sum to {counted} but "
                          f"{len(scenes)} training scenes x {cfg.train_per_scene} per scene = {total}")
    rng = np.random.default_rng(cfg.train_seed)
    tasks = [t for t in sorted(cfg.train_task_counts) for _ in range(cfg.train_task_counts[t])]
    tasks = [tasks[i] for i in rng.permutation(total)]
    scene_list = [s for s in scenes for _ in range(cfg.train_per_scene)]
    scene_list = [scene_list[i] for i in rng.permutation(total)]
    seeds = _unique_seeds(rng, total, set())
    rows = []
    for i, (task, scene, seed) in enumerate(zip(tasks, scene_list, seeds)):
        rows.append(ManifestRow(f"{i:05d}", "train", task, scene, _surface(rng, registry, scene), seed,
                                "train", objects))
    return rows


def eval_rows(registry: Registry) -> list[ManifestRow]:
    cfg = registry.splits
    rng = np.random.default_rng(cfg.eval_seed)
    train_seeds = {r.seed for r in train_rows(registry)}
    tasks = sorted(registry.tasks)
    n = len(cfg.eval_partitions) * len(tasks) * cfg.eval_per_task
    seeds = _unique_seeds(rng, n, train_seeds)
    rows = []
    for part in cfg.eval_partitions:
        scenes = registry.scenes_in(part.scenes)
        objects = registry.objects_in(part.objects)
        per_part = len(tasks) * cfg.eval_per_task
        order = [scenes[i % len(scenes)] for i in range(per_part)]
        order = [order[i] for i in rng.permutation(per_part)]
        k = 0
        for task in tasks:
            for _ in range(cfg.eval_per_task):
                scene = order[k]
                k += 1
                idx = len(rows)
                rows.append(ManifestRow(f"{idx:05d}", "eval", task, scene, _surface(rng, registry, scene),
                                        seeds[idx], part.id, objects))
    return rows


def rows(split: str, registry: Registry) -> list[ManifestRow]:
    """All rows of ``split`` ("train" or "eval"), in sample-id order."""
    if split == "train":
        return train_rows(registry)
    if split == "eval":
        return eval_rows(registry)
    raise ValueError(f"unknown split '{split}'; choose one of {', '.join(SPLITS)}")


def select(all_rows: list[ManifestRow], ids: list[str] | None = None, limit: int | None = None) -> list[ManifestRow]:
    """Rows with the given ids (in the given order; unknown ids raise) and/or the first ``limit``."""
    if ids:
        by_id = {r.sample_id: r for r in all_rows}
        missing = [i for i in ids if i not in by_id]
        if missing:
            raise KeyError(f"unknown sample id(s) {', '.join(missing)}; ids run from {all_rows[0].sample_id} "
                           f"to {all_rows[-1].sample_id}")
        chosen = [by_id[i] for i in ids]
    else:
        chosen = list(all_rows)
    return chosen[:limit] if limit is not None else chosen


def write(path: str | Path, manifest_rows: list[ManifestRow]) -> Path:
    """Write rows as JSON Lines (atomically)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text(path, "".join(json.dumps(r.to_dict()) + "\n" for r in manifest_rows))


def read(path: str | Path) -> list[ManifestRow]:
    out = []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        if line.strip():
            try:
                out.append(ManifestRow.from_dict(json.loads(line)))
            except (KeyError, ValueError, TypeError) as exc:
                raise ValueError(f"{path}: line {n} is not a manifest row ({exc})") from None
    return out
