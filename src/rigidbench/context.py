"""The run context: what every stage of one command shares, built once by the command line.

It carries the configuration directories layered over the packaged configs (``--config`` and
``$RIGIDBENCH_CONFIG_PATH``, which only the command line reads), the configuration registry they
produce, the device for networks and the cache directory. Stages receive it as an argument, and
render workers receive its configuration directories in their job description, so the same
example gives the same output however and wherever it runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .config import Registry, registry


@dataclass(frozen=True)
class RunContext:
    """config_dirs: extra configuration directories, in layering order; device: "cuda", "cpu" or None
    (CUDA when available); cache_dir: where stages may cache model outputs (None: next to their outputs)."""

    config_dirs: tuple[Path, ...] = ()
    device: str | None = None
    cache_dir: Path | None = None

    @property
    def registry(self) -> Registry:
        """The configuration registry of these directories (loaded once per process, ``config.registry``)."""
        return registry(self.config_dirs)

    def job(self) -> dict:
        """The JSON-serialisable part a worker process needs to rebuild this context."""
        return {"config_dirs": [str(d) for d in self.config_dirs], "device": self.device,
                "cache_dir": None if self.cache_dir is None else str(self.cache_dir)}

    @classmethod
    def from_job(cls, job: dict) -> "RunContext":
        return cls(tuple(Path(d) for d in job.get("config_dirs", ())), job.get("device"),
                   None if job.get("cache_dir") is None else Path(job["cache_dir"]))
