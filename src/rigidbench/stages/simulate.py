"""The simulate stage: manifest rows -> scene_spec.json, trajectories.npz, contacts.json per example, run by
the stage driver (``driver.run_stage``).

An example's key is a digest of its scene spec (built from the manifest row), the configuration the
simulation reads besides the spec (its objects' entries: shape, size, mesh; the contact and support
settings) and ``SIMULATE_FORMAT``. A rerun skips the examples simulated with the same key, simulates again
exactly those whose key changed and says why, and resumes a killed run from the examples it had not
committed: each example is written into the driver's staging folder and renamed into ``OUT/<id>/`` whole.
An example simulated before the driver kept a ledger (its ``contacts.json`` is there) is taken over.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Sequence

from ..blender.physics import CONTACTS_FILE, SCENE_SPEC_FILE, TRAJECTORIES_FILE, simulate_to_dir
from ..config import Registry, plain, registry as load_registry
from ..driver import Adopted, ItemResult, Progress, RunOptions, Stage, StageReport, StageWorker, run_stage
from ..errors import EXAMPLE_ERRORS
from ..hashing import digest
from ..manifest import ManifestRow
from ..scene_spec.build import build_scene_spec
from ..scene_spec.types import SceneSpec

log = logging.getLogger(__name__)

SIMULATE_WORKER = "rigidbench.stages.simulate:SimulateWorker"
#: Bump when the simulation writes other files or values for the same spec and configuration.
SIMULATE_FORMAT = 1
SIMULATION_FILES = (SCENE_SPEC_FILE, TRAJECTORIES_FILE, CONTACTS_FILE)


def simulate_key(spec: SceneSpec, registry: Registry) -> str:
    """The simulate stage's key of one example (see the module docstring)."""
    assets = sorted({b.asset for b in spec.bodies if b.ramp is None})
    return digest("simulate", SIMULATE_FORMAT, spec.to_dict(), {a: plain(registry.object(a)) for a in assets},
                  plain(registry.sim))


class SimulateWorker(StageWorker):
    """Simulates one manifest row into ``staging/<id>/``. Bullet's and Blender's own errors (RuntimeError)
    fail the example like a bad spec does."""

    def __init__(self, job: dict, registry: Registry | None = None):
        super().__init__(job)
        self.registry = registry if registry is not None else load_registry(job["config_dirs"])

    def run(self, item_id: str, payload: Any, staging: Path, progress: Progress) -> ItemResult:
        row = ManifestRow.from_dict(payload)
        try:
            result = simulate_to_dir(build_scene_spec(row, self.registry), staging / item_id, self.registry,
                                     overwrite=True)
        except (*EXAMPLE_ERRORS, RuntimeError) as exc:  # RuntimeError: Blender's own errors
            log.error("example %s failed: %s", item_id, exc)
            return ItemResult(status="failed", error=str(exc))
        return ItemResult(outputs=[item_id], result={"frames": int(result.frames), "contacts": len(result.contacts)})


class SimulateStage(Stage):
    """Simulate ``rows`` (the candidates) into ``out_dir/<id>/``. ``registry`` must be the one ``config_dirs``
    produce (a worker elsewhere rebuilds it from the directories)."""

    name = "simulate"
    worker = SIMULATE_WORKER

    def __init__(self, out_dir: str | Path, rows: Sequence[ManifestRow], registry: Registry,
                 config_dirs: Sequence[str | Path] = ()):
        self.out_dir, self.registry = Path(out_dir), registry
        self.rows = {r.sample_id: r for r in rows}
        self.config_dirs = [str(d) for d in config_dirs]

    @property
    def root(self) -> Path:
        return self.out_dir

    @property
    def where(self) -> str:
        splits = sorted({r.split for r in self.rows.values()})
        return f"the {splits[0]} manifest" if len(splits) == 1 else "the manifest rows given"

    def items(self) -> dict[str, dict]:
        return {sample_id: row.to_dict() for sample_id, row in self.rows.items()}

    def key(self, item_id: str, payload: Any) -> str:
        return simulate_key(build_scene_spec(self.rows[item_id], self.registry), self.registry)

    def job(self) -> dict:
        return {"config_dirs": self.config_dirs}

    def worker_instance(self) -> SimulateWorker:
        return SimulateWorker(self.job(), self.registry)

    def intact(self, item_id: str) -> bool:
        return all((self.root / item_id / name).is_file() for name in SIMULATION_FILES)

    def adopt(self, item_id: str, payload: Any, key: str) -> Adopted | None:
        """An example simulated before ledgers existed counts when its contacts.json is there (the old rule:
        written last, inside one directory renamed into place)."""
        done = (self.root / item_id / CONTACTS_FILE).is_file()
        return Adopted({}, f"a simulation with its {CONTACTS_FILE}") if done else None


def simulate_stage(stage: SimulateStage, run: RunOptions = RunOptions()) -> StageReport:
    """Run ``stage`` as ``run`` says (in this process by default); returns the driver's report."""
    stage.root.mkdir(parents=True, exist_ok=True)
    return run_stage(stage, run)


def simulate_rows(rows, registry: Registry, out_dir: Path, run: RunOptions = RunOptions(), *,
                  config_dirs: Sequence[str | Path] = ()) -> StageReport:
    """Simulate the selected rows that are not up to date into ``out_dir/<id>/``; returns the driver's report."""
    return simulate_stage(SimulateStage(out_dir, rows, registry, config_dirs), run)


__all__ = ["SIMULATE_FORMAT", "SimulateStage", "SimulateWorker", "simulate_key", "simulate_rows", "simulate_stage"]
