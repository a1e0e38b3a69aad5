"""The stage driver: the one place that decides which examples a stage runs, whether one is already done,
how its output is committed, how a failure is recorded, what progress shows and what the run prints.

A *stage* (simulate, render, predict, evaluate, preprocess, probe extract, probe intervene) declares:

- ``name`` and ``root``: its output folder (a split of bundles, a predictions folder, a run folder, a cache);
- ``items()``: every candidate example, ``{id: payload}`` in a fixed order (the payload is JSON: what a
  worker needs besides the job, e.g. a manifest row);
- ``key(id, payload)``: a hash of the inputs and settings that determine the example's output;
- ``worker`` ("module:Class", a ``StageWorker``) and ``job()``: what builds the worker, in this process, in a
  child process or on a Ray actor;
- optionally ``resources``, ``prepare(todo)``, ``intact(id)`` and ``adopt(id, payload, key)``.

The driver (``run_stage``) then:

1. **selects** with a ``Selection`` (ids, limit, shard; an unknown id is one UserError);
2. **decides** per example from its *ledger entry*, ``ROOT/.stages/NAME/<id>.json`` (key, status, error, the
   worker's result): the same key, succeeded, and the output still ``intact`` -> up to date, skipped; else it
   runs again, and the run says why (new, settings or inputs changed, failed before, output missing). An
   output made before ledgers existed is taken over when the stage's ``adopt`` returns it as ``Adopted``;
3. **runs** the rest through an executor (this process, local child processes, Ray actors, a shard). On
   the executor's side, ``ItemRunner`` gives the worker an empty *staging* folder
   (``ROOT/.stages/NAME/staging/<id>/``; a killed run's leftovers are removed first), and **commits** what
   the worker wrote there: each output path (relative to ROOT) is renamed into place whole, in the order
   the worker lists them (the last one is the example's completion mark), then the ledger entry is
   written, fsynced. A failure (``RigidBenchError`` or ``OSError``: a bad example) writes a failed ledger
   entry and commits nothing; a bug raises;
4. **shows progress** (examples, and sub-steps such as rendered frames) and **summarises**: a
   ``StageReport`` with what ran, what was up to date, what failed and why, and why each was redone.

So a rerun with other settings redoes exactly the examples whose key changed, a killed run resumes from
the examples it had not committed, and the same example gives the same files whichever executor ran it.

Several processes may work on one folder at once (shards, or the same command started twice): whoever works
on an item holds its lock (``ItemLock``: ``fcntl.flock`` on ``ROOT/.stages/NAME/staging/<id>.lock``, taken by
``ItemRunner`` for as long as it makes, commits and records the item; the kernel drops it when the process
dies, so a killed run leaves no stale lock). Having taken it, the runner reads the ledger again: an item that
another process finished since the plan is not made twice (it counts as up to date). An item whose lock
another process holds is skipped and reported as being done elsewhere (``StageReport.elsewhere``), or, with
``wait`` (``--wait``), waited for after the other items. A stage's ``finish`` runs under a run-level lock
(``.stages/NAME/finish.lock``), so processes that finish at once write their run-level files one after the
other, the last from everything done by then.
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import time
from abc import ABC, abstractmethod
from contextlib import contextmanager
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterator, Mapping, Sequence

from .atomic import as_write_error, release_open_writers, replace_path
from .errors import EXAMPLE_ERRORS, UserError
from .executors import Executor, LocalExecutor, Resources, Shard
from .hashing import digest
from .jsonio import read_json, write_json
from .registry import load_target

log = logging.getLogger(__name__)

LEDGER_DIR = ".stages"  # hidden: bundle listings, validate and evaluate skip it
STAGING_DIR = "staging"
RUNNER = "rigidbench.driver:ItemRunner"
ELSEWHERE = "elsewhere"  # an item's status when another process holds its lock (it is being done there)
FINISH_LOCK = "finish.lock"  # the run-level lock around a stage's finish (e.g. evaluate's results.json)
LOCK_POLL_S = 0.2  # how often a process waiting for another's lock (--wait) looks again
STOPPED = "stopped"  # a record's status when the example's ledger entry could not be written

Progress = Callable[[int, int], None]


# -- selection -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Selection:
    """Which examples a stage runs: ``ids`` (in the stage's order), the first ``limit`` of those, then this
    ``shard``'s part. The one selection rule of every stage."""

    ids: tuple[str, ...] | None = None
    limit: int | None = None
    shard: Shard = Shard()

    @classmethod
    def of(cls, ids: Sequence[str] | None = None, limit: int | None = None, shard: Shard | str | None = None
           ) -> "Selection":
        shard = shard if isinstance(shard, Shard) else Shard.parse(shard)
        return cls(tuple(ids) if ids else None, limit, shard)

    def apply(self, candidates: Sequence[str], where: str,
              example_of: Callable[[str], str] | None = None) -> list[str]:
        """The selected ids of ``candidates`` (in their order); an id not among them is a UserError naming
        ``where`` (the folder or manifest the candidates come from). With ``example_of`` (item -> its example,
        for stages whose items are several samples of one example), ``ids`` and ``limit`` choose examples and
        every item of a chosen example goes with it; the shard then splits the items."""
        chosen = list(candidates)
        example = example_of or (lambda item: item)
        examples = list(dict.fromkeys(example(i) for i in chosen))
        if self.ids:
            known = set(examples)
            unknown = [i for i in dict.fromkeys(self.ids) if i not in known]
            if unknown:
                span = f" (ids run from {examples[0]} to {examples[-1]})" if examples else " (it holds none)"
                raise UserError(f"unknown example id(s) {', '.join(unknown)} in {where}{span}")
            wanted = set(self.ids)
            examples = [i for i in examples if i in wanted]
        if self.limit is not None:
            examples = examples[:self.limit]
        kept = set(examples)
        return self.shard.select([i for i in chosen if example(i) in kept])


@dataclass(frozen=True)
class RunOptions:
    """How a command runs a stage, built once from its arguments (``commands.run_options``): which examples
    (``selection``), where they run (``executor``; None: this process), whether bars show (``progress``), and
    whether to wait for the examples another process is making (``wait``, ``--wait``) or skip them."""

    selection: Selection = Selection()
    executor: Executor | None = None
    progress: bool = True
    wait: bool = False


# -- why an example is made again --------------------------------------------------------------------------


class Why(str, Enum):
    """Why an earlier output of an example is not reused (the reasons of ``StageReport.redone``)."""

    CHANGED = "its inputs or settings changed"
    FAILED_BEFORE = "it failed before"
    DAMAGED = "its output is missing or damaged"


class Redo(str):
    """Why an example is made again: a ``Why`` and a detail; as text, the reason the report prints
    ("it failed before (disk full)")."""

    why: Why
    detail: str

    def __new__(cls, why: Why, detail: str = "") -> "Redo":
        text = f"{why.value} ({detail})" if detail else why.value
        self = super().__new__(cls, text)
        self.why, self.detail = why, detail
        return self

    def __reduce__(self):
        return Redo, (self.why, self.detail)


@dataclass(frozen=True)
class Adopted:
    """What ``Stage.adopt`` found: an output made before ledgers existed that counts as made with the example's
    key. ``result``: the ledger entry's result (as a worker's ``ItemResult.result``); ``how``: how it was found
    (what the log says, e.g. "a bundle rendered at this preset")."""

    result: dict
    how: str


class Key(str):
    """An example's key (the digest the ledger records) with ``facts``: what computing it found that the
    stage needs later (content hashes, a file's path), JSON values. ``key()`` stays pure: the facts travel in
    the key to ``adopt``, to the worker (``run(..., facts=)``) and to ``finish`` (``report.keys[id].facts``)."""

    facts: Mapping[str, Any]

    def __new__(cls, digest: str, facts: Mapping[str, Any] | None = None) -> "Key":
        self = super().__new__(cls, digest)
        self.facts = dict(facts or {})
        return self

    def __reduce__(self):
        return Key, (str(self), dict(self.facts))


# -- what a stage declares -----------------------------------------------------------------------------


class Stage(ABC):
    """One stage of the pipeline, as the driver sees it (see the module docstring)."""

    name: ClassVar[str]
    worker: ClassVar[str]  # "module:Class" of its StageWorker
    resources: Resources = Resources()
    unit: ClassVar[str] = "example"
    #: what a worker's ``progress(done, total)`` counts (e.g. "frame"); None: no second progress bar
    steps: ClassVar[str | None] = None

    @property
    @abstractmethod
    def root(self) -> Path:
        """The output folder; the ledger and staging live under ``root/.stages/<name>/``."""

    @abstractmethod
    def items(self) -> Mapping[str, Any]:
        """Every candidate example: ``{id: JSON payload}``, in the stage's order."""

    @property
    def where(self) -> str:
        """Where the candidates come from, for the unknown-id error."""
        return str(self.root)

    def example_of(self, item_id: str) -> str:
        """The example an item belongs to (a stage whose items are several samples of an example says so, e.g.
        ``folders.sample_item``); ``--ids`` and ``--limit`` select examples. By default an item is its example."""
        return item_id

    @abstractmethod
    def key(self, item_id: str, payload: Any) -> "str | Key":
        """A hash of everything that determines the example's output (EXAMPLE_ERRORS: the example fails); a
        ``Key`` when it carries facts for later. Pure: it writes neither into ``payload`` nor into the stage."""

    @abstractmethod
    def job(self) -> dict:
        """The JSON description a worker is built from (anywhere: here, a child process, a Ray actor)."""

    def worker_instance(self) -> "StageWorker | None":
        """A ready worker for an in-process executor (it may hold objects that cannot travel); None: build
        one from ``job()``."""
        return None

    def check(self, selected: list[str]) -> None:
        """Refuse the selection as a whole before any key is computed or anything loads (UserError), e.g. a
        folder of imported bundles that must not be overwritten."""

    def intact(self, item_id: str) -> bool:
        """Whether the committed output of ``item_id`` is still there and sound (checked before skipping). By
        default: every output its ledger entry lists is still there as it was committed (``outputs_intact``);
        a stage that checks more calls this too."""
        return outputs_intact(self.root, read_ledger(self.root, self.name, item_id))

    def adopt(self, item_id: str, payload: Any, key: str) -> "Adopted | Redo | None":
        """An output made before ledgers existed (there is no ledger entry): ``Adopted`` when it counts as made
        with ``key`` (its ledger entry is then written from it); a ``Redo`` saying why an earlier output there
        does not count (it is made again, and the report says why); None: nothing there to take over."""
        return None

    def prepare(self, todo: list[str]) -> None:
        """Called once before the examples in ``todo`` run (e.g. a preflight check, a shared record)."""

    def finish(self, report: "StageReport") -> None:
        """Called once after the run, also when it was interrupted or stopped by a bug (``report.completed``
        says which), e.g. to write the run-level results."""


class StageWorker(ABC):
    """Produces one example's output per call. ``run`` writes the output under ``staging`` with the paths it
    will have under the stage's root and returns an ``ItemResult``; it raises RigidBenchError or OSError for
    a bad example (recorded as a failure) and anything else for a bug."""

    def __init__(self, job: dict):
        self.job = job

    @abstractmethod
    def run(self, item_id: str, payload: Any, staging: Path, progress: Progress) -> "ItemResult":
        """Make example ``item_id`` (``payload``: its item) into ``staging``; ``progress(done, total)`` reports
        sub-steps. A stage whose ``key`` returns a ``Key`` with facts has them passed as ``facts=``."""

    def stop(self) -> None:
        """Start nothing new (a graceful interrupt); optional."""

    def stopped(self) -> bool:
        """Whether ``stop`` was called (a runner waiting for another process's lock then gives up)."""
        return False

    def close(self) -> None:
        """Release what the worker holds (models, sessions)."""


@dataclass
class ItemResult:
    """What a worker made: ``outputs`` (paths under staging and root, committed in this order, each
    replaced whole; the last marks the example done) and a small JSON ``result`` for the ledger and the
    stage's summary. ``status`` other than "succeeded" (e.g. "interrupted") commits nothing and leaves the
    example to run again."""

    outputs: list[str] = field(default_factory=list)
    result: dict = field(default_factory=dict)
    status: str = "succeeded"
    error: str | None = None


# -- the ledger -------------------------------------------------------------------------------------------


def stage_dir(root: str | Path, name: str) -> Path:
    return Path(root) / LEDGER_DIR / name


def ledger_path(root: str | Path, name: str, item_id: str) -> Path:
    return stage_dir(root, name) / f"{item_id}.json"


def read_ledger(root: str | Path, name: str, item_id: str) -> dict | None:
    """The ledger entry of ``item_id``, or None (absent, or damaged: the example then simply runs again)."""
    doc = read_json(ledger_path(root, name, item_id), "the example runs again")
    return doc if isinstance(doc, dict) and doc.get("id") == item_id else None


def write_ledger(root: str | Path, name: str, item_id: str, key: str, status: str, *, result: dict | None = None,
                 error: str | None = None, seconds: float | None = None, **extra: Any) -> dict:
    entry = {"stage": name, "id": item_id, "key": key, "status": status, "error": error,
             "seconds": None if seconds is None else round(seconds, 3),
             "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "result": result or {}, **extra}
    write_json(ledger_path(root, name, item_id), entry, durable=True)
    return entry


def staging_path(root: str | Path, name: str, item_id: str) -> Path:
    return stage_dir(root, name) / STAGING_DIR / item_id


def lock_path(root: str | Path, name: str, item_id: str) -> Path:
    """The lock file of ``item_id`` (``ItemLock``), beside its staging folder."""
    return stage_dir(root, name) / STAGING_DIR / f"{item_id}.lock"


class ItemLock:
    """An exclusive lock between processes (``fcntl.flock`` on ``path``), held from ``acquire`` to ``release``.
    The kernel drops it when its process dies (a kill -9 leaves no stale lock). The holder removes the file
    when it releases; a process that locked a file removed meanwhile (its holder released it between this
    process's open and flock) sees another file at the path and tries again, so two never hold it at once."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.fd: int | None = None

    def acquire(self, wait: bool = False, stopped: Callable[[], bool] = lambda: False) -> bool:
        """Take the lock: True when taken; False when another process holds it (and ``wait`` is off, or
        ``stopped()`` became true while waiting). ``wait``: look again every LOCK_POLL_S seconds."""
        while True:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            except FileNotFoundError:  # another run removed the empty folder between the two: again
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                if not wait or stopped():
                    return False
                time.sleep(LOCK_POLL_S)
                continue
            try:
                at_path, locked = os.stat(self.path), os.fstat(fd)
                current = (at_path.st_dev, at_path.st_ino) == (locked.st_dev, locked.st_ino)
            except FileNotFoundError:
                current = False
            if current:
                self.fd = fd
                return True
            os.close(fd)  # the file its holder removed on release: lock the one at the path now

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        finally:
            os.close(self.fd)  # closing drops the lock
            self.fd = None


def fresh_staging(root: str | Path, name: str, item_id: str) -> Path:
    """An empty staging folder for ``item_id`` (a killed run's leftovers there are removed first). Only the
    holder of the item's lock (``ItemLock``) makes or removes it, so processes sharing a folder never meet
    in it."""
    path = staging_path(root, name, item_id)
    if path.exists() or path.is_symlink():
        shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
    for attempt in range(3):  # another run (a shard) may remove the empty staging folder between the two mkdirs
        try:
            path.mkdir(parents=True)
            break
        except FileNotFoundError:
            if attempt == 2:
                raise
    return path


def commit(staging: Path, root: Path, outputs: Sequence[str]) -> None:
    """Rename each of ``outputs`` from ``staging`` into ``root``, in order, each replacing whatever was at
    its path (a directory whole: the old one is moved aside first and removed after)."""
    for rel in outputs:
        rel_path = Path(rel)
        if rel_path.is_absolute() or ".." in rel_path.parts:
            raise ValueError(f"output path {rel!r} must be relative to the stage's root")
        src, dst = staging / rel_path, root / rel_path
        if not (src.exists() or src.is_symlink()):
            raise FileNotFoundError(f"{src}: the worker listed this output but did not write it")
        dst.parent.mkdir(parents=True, exist_ok=True)
        replace_path(src, dst)


#: the kinds of committed output ``output_kinds`` records; a JSON file's kind is the type of its document
_JSON_KINDS: dict[str, type] = {"object": dict, "list": list}


def output_kinds(root: Path, outputs: Sequence[str]) -> dict[str, str]:
    """``{output: kind}`` of committed outputs (paths under ``root``), for the ledger entry: "directory", a JSON
    file's document type ("object" or "list"), or "file"."""
    kinds = {}
    for rel in outputs:
        path = Path(root) / rel
        kind = "directory" if path.is_dir() else "file"
        if kind == "file" and path.suffix == ".json":
            doc = read_json(path, "it is checked as a plain file")
            kind = next((k for k, t in _JSON_KINDS.items() if isinstance(doc, t)), kind)
        kinds[rel] = kind
    return kinds


def outputs_intact(root: str | Path, entry: dict | None) -> bool:
    """Whether every output a ledger entry lists (``output_kinds``, recorded at commit) is still there as it
    was committed: a directory still a directory, a file still a file, a JSON file still parses to the same
    type of document (a truncated, emptied or replaced one does not). An entry from before outputs were
    recorded lists none: nothing to check. A damaged JSON file is logged as a warning naming it."""
    listed = (entry or {}).get("outputs") or {}
    if not isinstance(listed, dict):
        return False
    for rel, kind in listed.items():
        path = Path(root) / rel
        if kind == "directory":
            ok = path.is_dir()
        elif kind in _JSON_KINDS:
            ok = read_json(path, "the example is made again", expect=_JSON_KINDS[kind]) is not None
        else:
            ok = path.is_file()
        if not ok:
            return False
    return True


class ItemRunner:
    """What an executor calls per example, wherever it runs: builds the stage's worker from the job, takes
    the example's lock (``ItemLock``), runs the worker into a fresh staging folder, commits the outputs and
    writes the ledger entry. Task: ``{"id", "payload", "key"}``, and from ``plan`` ``"seen"`` (the ledger entry
    the plan read, as a digest) and ``"wait"``; returns the ledger entry. Status ``ELSEWHERE``: another
    process holds the lock (nothing done here); an entry with ``"elsewhere": True``: another process finished
    the example since the plan (the ledger's entry, nothing done here)."""

    def __init__(self, job: dict, instance: StageWorker | None = None):
        self.stage, self.root = job["stage"], Path(job["root"])
        self.worker = instance if instance is not None else load_target(job["worker"], "stage worker")(job["job"])

    def __call__(self, task: dict, progress: Progress | None = None) -> dict:
        item_id, key = task["id"], task["key"]
        lock = ItemLock(lock_path(self.root, self.stage, item_id))
        try:
            taken = lock.acquire(wait=bool(task.get("wait")), stopped=self.worker.stopped)
        except OSError as exc:  # the lock file cannot be made (a read-only folder, a full disk)
            return {"stage": self.stage, "id": item_id, "key": key, "status": STOPPED,
                    "error": str(as_write_error(exc, lock.path))}
        if not taken:
            return {"stage": self.stage, "id": item_id, "key": key, "status": ELSEWHERE, "result": {},
                    "error": "being done by another process"}
        try:
            if "seen" in task:  # another process may have finished it since the plan read the ledger
                entry = read_ledger(self.root, self.stage, item_id)
                if (entry is not None and entry.get("key") == key and entry.get("status") in ("succeeded", "failed")
                        and digest(entry) != task["seen"]):
                    return {**entry, "elsewhere": True}
            return self._make(task, progress)
        finally:
            lock.release()

    def _make(self, task: dict, progress: Progress | None = None) -> dict:
        item_id, key = task["id"], task["key"]
        started = time.time()
        staging = None
        try:
            staging = fresh_staging(self.root, self.stage, item_id)
            facts = {"facts": task["facts"]} if task.get("facts") else {}  # the Key's facts (Stage.key)
            made = self.worker.run(item_id, task.get("payload"), staging, progress or (lambda done, total: None),
                                   **facts)
            if made.status in ("succeeded", "failed"):
                committed = {}
                if made.status == "succeeded":
                    commit(staging, self.root, made.outputs)
                    committed = {"outputs": output_kinds(self.root, made.outputs)}  # what intactness checks
                return write_ledger(self.root, self.stage, item_id, key, made.status, result=made.result,
                                    error=made.error, seconds=time.time() - started, **committed)
            # interrupted: nothing recorded, the example runs again
            return {"stage": self.stage, "id": item_id, "key": key, "status": made.status, "error": made.error,
                    "result": made.result, "seconds": round(time.time() - started, 3)}
        except EXAMPLE_ERRORS as exc:
            if isinstance(exc, OSError) and staging is not None:  # a write into staging failed (a full disk)
                release_open_writers(exc, staging)
                if exc.filename is None:  # a failed write() names no file: name the example's folder
                    exc = as_write_error(exc, staging)
            error = str(exc) or type(exc).__name__
            try:
                return write_ledger(self.root, self.stage, item_id, key, "failed", error=error,
                                    seconds=time.time() - started)
            except OSError as unrecorded:  # not even the ledger can be written: nothing can go on
                return {"stage": self.stage, "id": item_id, "key": key, "status": STOPPED,
                        "error": str(as_write_error(unrecorded, ledger_path(self.root, self.stage, item_id)))}
        finally:
            if staging is not None:
                shutil.rmtree(staging, ignore_errors=True)

    def stop(self) -> None:
        self.worker.stop()

    def close(self) -> None:
        self.worker.close()


class _Lent:
    """A runner lent to an executor for one round of ``run_stage``: the executor's ``close`` at the end of the
    round is left to ``run_stage``, which may need the runner for a second round (``--wait``)."""

    def __init__(self, runner: ItemRunner):
        self.runner = runner

    def __call__(self, task: dict, progress: Progress | None = None) -> dict:
        return self.runner(task, progress)

    def close(self) -> None:
        pass


# -- the run ----------------------------------------------------------------------------------------------


@dataclass
class StageReport:
    """What a stage run did. ``selected``: the ids, in order; ``ran``: committed now; ``reused``: up to date
    (skipped); ``failed``: id -> reason; ``redone``: id -> why an earlier output was not reused;
    ``results``: id -> the worker's result (ran and reused); ``interrupted``: ids stopped before they ran;
    ``elsewhere``: ids another process was working on (their lock was held), not done here; ``keys``: id ->
    the key this run computed (``plan``; a ``Key`` with its facts when the stage returns one); ``facts``: the
    stage's own results (a small dataclass its facade sets, e.g. evaluate's results.json), which its command
    prints after the common ``lines``."""

    stage: str
    root: Path
    selected: list[str] = field(default_factory=list)
    unit: str = "example"
    ran: list[str] = field(default_factory=list)
    reused: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    redone: dict[str, Redo] = field(default_factory=dict)
    results: dict[str, dict] = field(default_factory=dict)
    interrupted: list[str] = field(default_factory=list)
    elsewhere: list[str] = field(default_factory=list)
    keys: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    completed: bool = False  # every selected example was attempted (not stopped by an interrupt or a bug)
    facts: Any = None  # stage-specific results (the stage's facade sets them; its command prints them)

    @property
    def succeeded(self) -> list[str]:
        """Selected ids with a committed output (ran now or up to date), in selection order."""
        ok = set(self.ran) | set(self.reused)
        return [i for i in self.selected if i in ok]

    def lines(self) -> tuple[list[str], list[str]]:
        """What every command prints after running a stage, the same words for every stage: (lines for
        stdout, lines for stderr). The first says how many were made, up to date, failed, not started and
        being made elsewhere; then one line per reason examples were made again; the failures; what to do."""
        unit = self.unit
        parts = [f"{len(self.ran)} made", f"{len(self.reused)} up to date", f"{len(self.failed)} failed"]
        if self.interrupted:
            parts.append(f"{len(self.interrupted)} not started")
        if self.elsewhere:
            parts.append(f"{len(self.elsewhere)} being made by another process")
        out = [f"{self.stage}: {', '.join(parts)} of {len(self.selected)} {unit}(s) -> {self.root}"]
        for why in Why:
            ids = [i for i in self.ran if i in self.redone and getattr(self.redone[i], "why", None) is why]
            if ids:
                more = f" and {len(ids) - 10} more" if len(ids) > 10 else ""
                out.append(f"  made again, {why.value}: {', '.join(ids[:10])}{more}")
        err = [f"  FAILED {item_id}: {reason}" for item_id, reason in self.failed.items()]
        if self.elsewhere:
            err.append(f"  {len(self.elsewhere)} {unit}(s) being made by another process: rerun when it is done, "
                       "or pass --wait")
        if self.failed or self.interrupted:
            err.append(f"  rerun the same command to retry what failed or did not start; finished {unit}s are kept")
        return out, err

    def exit_status(self) -> int:
        """1 when any selected example failed or was not started, else 0."""
        return 1 if self.failed or self.interrupted else 0

    def to_json(self) -> dict:
        return {"stage": self.stage, "root": str(self.root), "selected": len(self.selected), "ran": self.ran,
                "reused": self.reused, "failed": self.failed, "redone": self.redone,
                "interrupted": self.interrupted, "elsewhere": self.elsewhere, "seconds": round(self.seconds, 3)}


def plan(stage: Stage, ids: Sequence[str], items: Mapping[str, Any], report: StageReport,
         write: bool = True) -> list[dict]:
    """The tasks still to run: every selected id whose ledger entry does not show a committed output with
    the same key (the driver's one resume rule); fills ``report.reused``, ``.failed`` (a key that cannot be
    computed), ``.redone`` and ``.keys``. ``write=False`` (a dry run) writes no ledger entry for adopted
    outputs. Each task holds ``seen``, a digest of the ledger entry read here (None: none), by which its runner
    tells whether another process has finished the example since."""
    todo = []
    for item_id in ids:
        payload = items[item_id]
        try:
            key = stage.key(item_id, payload)
        except EXAMPLE_ERRORS as exc:
            report.failed[item_id] = str(exc)
            log.warning("%s: example %s failed: %s", stage.name, item_id, exc)
            continue
        report.keys[item_id] = key
        entry = read_ledger(stage.root, stage.name, item_id)
        why = None
        if entry is None:
            adopted = stage.adopt(item_id, payload, key)
            if isinstance(adopted, Redo):  # an earlier output that does not count, and why
                why = adopted
            elif isinstance(adopted, Adopted):
                log.info("%s: %s %s is taken over from before ledgers: %s", stage.name, stage.unit, item_id,
                         adopted.how)
                if write:
                    write_ledger(stage.root, stage.name, item_id, key, "succeeded", result=adopted.result,
                                 adopted=True)
                report.reused.append(item_id)
                report.results[item_id] = adopted.result
                continue
            elif adopted is not None:
                raise TypeError(f"{type(stage).__name__}.adopt returned a {type(adopted).__name__}: it returns an "
                                "Adopted, a Redo or None")
        elif entry.get("key") != key:
            why = Redo(Why.CHANGED)
        elif entry.get("status") != "succeeded":
            why = Redo(Why.FAILED_BEFORE, entry.get("error") or "no reason recorded")
        elif not stage.intact(item_id):
            why = Redo(Why.DAMAGED)
        else:
            report.reused.append(item_id)
            report.results[item_id] = entry.get("result") or {}
            continue
        if why is not None:
            report.redone[item_id] = why
        task = {"id": item_id, "payload": payload, "key": str(key), "seen": None if entry is None else digest(entry)}
        if getattr(key, "facts", None):
            task["facts"] = dict(key.facts)
        todo.append(task)
    return todo


def ledger_outcomes(stage: Stage, report: StageReport) -> tuple[dict[str, dict], dict[str, str]]:
    """What the ledger holds now for the selected examples, whichever process made them (for run-level files
    such as evaluate's results.json): ``done``, id -> ledger entry of those whose latest entry, with this run's
    key, succeeded; ``failed``, id -> reason of those whose latest entry failed, and of those whose key could
    not be computed. In selection order; an example not attempted, or still being made elsewhere, is in
    neither."""
    done: dict[str, dict] = {}
    failed: dict[str, str] = {}
    for item_id in report.selected:
        if item_id not in report.keys:
            if item_id in report.failed:
                failed[item_id] = report.failed[item_id]
            continue
        entry = read_ledger(stage.root, stage.name, item_id)
        if entry is None or entry.get("key") != report.keys[item_id]:
            continue
        if entry.get("status") == "succeeded":
            done[item_id] = entry
        elif entry.get("status") == "failed":
            failed[item_id] = entry.get("error") or "failed"
    return done, failed


def _remove_if_empty(path: Path) -> None:
    try:
        path.rmdir()
    except OSError:  # absent, or another run (a shard) is staging an example there
        pass


def _remove_leftovers(stage: Stage, item_id: str) -> None:
    """Remove a killed run's staging leftovers of ``item_id`` (its folder, its lock file), an example that is
    done after all; not while another process holds its lock (it is working on the example again)."""
    leftover = staging_path(stage.root, stage.name, item_id)
    lock = ItemLock(lock_path(stage.root, stage.name, item_id))
    if not (leftover.exists() or lock.path.exists()):
        return
    try:
        if lock.acquire():
            shutil.rmtree(leftover, ignore_errors=True)
    except OSError:  # a folder that cannot be written: the leftovers stay
        pass
    finally:
        lock.release()


@contextmanager
def _finishing(stage: Stage) -> Iterator[None]:
    """The run-level lock (``FINISH_LOCK``) held around ``stage.finish``: processes that finish at once write
    their run-level files one after the other. None when the stage has no ledger folder (nothing ran)."""
    folder = stage_dir(stage.root, stage.name)
    lock = ItemLock(folder / FINISH_LOCK)
    try:
        if folder.is_dir():
            lock.acquire(wait=True)
    except OSError:  # a folder that cannot be written: finish says so itself
        pass
    try:
        yield
    finally:
        lock.release()


def validate_selection(stage: Stage, run: RunOptions = RunOptions(), items: Mapping[str, Any] | None = None
                       ) -> list[str]:
    """Phases 1 to 3 of a run: the candidates (``items``, or the stage's), the selection of them (an unknown id
    is a UserError naming ``where``) and the stage's ``check`` of it; returns the selected ids. ``run_stage``
    starts with it; a facade with heavy work to do before its stage runs (``probe intervene`` fits its bases
    first) calls it before that work, so that a wrong id fails before anything heavy loads."""
    items = stage.items() if items is None else items
    ids = run.selection.apply(list(items), stage.where, stage.example_of)
    stage.check(ids)
    return ids


def _planned(stage: Stage, run: RunOptions, write: bool) -> tuple[StageReport, list[dict]]:
    """Phases 1 to 4 of a run: the selection (``validate_selection``), then the plan (keys, ledger, adopted
    outputs; written only with ``write``). Returns the report so far and the tasks still to run."""
    items = stage.items()
    ids = validate_selection(stage, run, items)
    report = StageReport(stage.name, stage.root, selected=ids, unit=stage.unit)
    return report, plan(stage, ids, items, report, write=write)


def plan_only(stage: Stage, run: RunOptions = RunOptions()) -> tuple[StageReport, list[dict]]:
    """What ``run_stage`` would do, writing nothing (a dry run): the selection, the stage's ``check`` and the
    plan, as a run makes them. Returns the report (``reused``, ``failed``, ``redone``, ``keys``) and the tasks
    a run would make."""
    return _planned(stage, run, write=False)


class _Collector:
    """This process's side of a run: the progress bars, and each example's ledger entry as it comes back
    (``report``), with the examples another process held put aside for a second round (``deferred``, when
    ``run.wait``)."""

    def __init__(self, stage: Stage, report: StageReport, total: int, run: RunOptions,
                 on_result: Callable[[str, dict], None] | None):
        from tqdm import tqdm

        self.stage, self.report, self.total, self.run, self.on_result = stage, report, total, run, on_result
        self.bar = tqdm(total=total, unit=stage.unit, desc=stage.name, disable=not run.progress or not total,
                        position=0)
        self.sub: Any = None  # the second bar (a worker's sub-steps), opened by the first progress call
        self.done: dict[str, int] = {}
        self.deferred: list[dict] = []

    def on_progress(self, task: dict, done: int, total: int) -> None:
        if not self.run.progress:
            return
        if self.sub is None:
            from tqdm import tqdm

            self.sub = tqdm(total=self.total * total, unit=self.stage.steps, desc=f"{self.stage.name} "
                            f"{self.stage.steps}s", position=1)
        self.sub.update(done - self.done.get(task["id"], 0))
        self.done[task["id"]] = done

    def __call__(self, task: dict, entry: dict) -> None:
        report, item_id, status = self.report, task["id"], entry.get("status")
        if status == ELSEWHERE:
            if self.run.wait and not task.get("wait"):
                self.deferred.append({**task, "wait": True})
                return
            report.elsewhere.append(item_id)
        elif status == "succeeded":  # made here, or by another process since the plan (then up to date)
            (report.reused if entry.get("elsewhere") else report.ran).append(item_id)
            report.results[item_id] = entry.get("result") or {}
        elif status == "failed":
            report.failed[item_id] = entry.get("error") or "failed"
            if self.run.progress:
                self.bar.write(f"FAILED {item_id}: {report.failed[item_id]}")
            else:
                log.warning("%s: example %s failed: %s", self.stage.name, item_id, report.failed[item_id])
        elif status == STOPPED:  # its ledger entry cannot be written (ItemRunner): stop, as one clear line
            report.interrupted.append(item_id)
            raise UserError(f"{self.stage.name} stopped at example {item_id}: {entry.get('error')}")
        else:
            report.interrupted.append(item_id)
        self.bar.update(1)
        if self.on_result is not None and status != ELSEWHERE:
            self.on_result(item_id, entry)

    def close(self) -> None:
        self.bar.close()
        if self.sub is not None:
            self.sub.close()


def _execute(stage: Stage, executor: Executor, todo: list[dict], collect: _Collector) -> None:
    """Run ``todo`` through ``executor`` (in this process: one runner around the stage's ready worker), then,
    in a second round, the examples ``collect`` put aside to wait for."""
    job = {"stage": stage.name, "root": str(Path(stage.root).resolve()), "worker": stage.worker, "job": stage.job()}
    runner = ItemRunner(job, stage.worker_instance()) if executor.in_process else None
    try:
        tasks = todo
        while tasks:  # a second round only for the examples waited for (wait)
            executor.map(RUNNER, job, tasks, stage.resources, on_result=collect,
                         instance=_Lent(runner) if runner is not None else None,
                         on_progress=collect.on_progress if stage.steps else None)
            tasks, collect.deferred[:] = list(collect.deferred), []
            if tasks:
                log.info("%s: waiting for %d %s(s) that another process is working on in %s", stage.name,
                         len(tasks), stage.unit, stage.root)
    finally:
        if runner is not None:
            runner.close()


def _planned_notes(stage: Stage, report: StageReport) -> None:
    """After the plan: a killed run's leftovers of the examples up to date removed; what is skipped, and what
    is made again because it changed, logged."""
    for item_id in report.reused:
        _remove_leftovers(stage, item_id)
    if report.reused:
        log.info("%s: %d of %d selected %ss are up to date in %s; skipping them", stage.name, len(report.reused),
                 len(report.selected), stage.unit, stage.root)
    changed = [i for i, why in report.redone.items() if why.why is Why.CHANGED]
    if changed:
        log.warning("%s: %d %s(s) made with other inputs or settings are made again: %s", stage.name, len(changed),
                    stage.unit, ", ".join(changed[:10]) + (" ..." if len(changed) > 10 else ""))


def _settle(stage: Stage, report: StageReport, todo: list[dict], started: float) -> None:
    """After the run, finished or not: what was never attempted counts as not started, lists in selection
    order, the time, the examples left to another process logged, the empty staging folder removed."""
    ids = report.selected
    finished = set(report.ran) | set(report.reused) | set(report.failed) | set(report.interrupted) \
        | set(report.elsewhere)
    report.interrupted += [t["id"] for t in todo if t["id"] not in finished]
    report.ran.sort(key=ids.index)
    report.reused.sort(key=ids.index)
    report.seconds = time.time() - started
    if report.elsewhere:
        log.warning("%s: %d %s(s) are being done by another process in %s, not here: %s; rerun when it is done "
                    "(or pass --wait to wait for them)", stage.name, len(report.elsewhere), stage.unit, stage.root,
                    ", ".join(report.elsewhere[:10]) + (" ..." if len(report.elsewhere) > 10 else ""))
    _remove_if_empty(stage_dir(stage.root, stage.name) / STAGING_DIR)


def run_stage(stage: Stage, run: RunOptions = RunOptions(),
              on_result: Callable[[str, dict], None] | None = None) -> StageReport:
    """Run ``stage`` as ``run`` says (see the module docstring); returns the report. In this order: the
    candidates (``items``), the selection (an unknown id is a UserError naming ``where``), the stage's
    ``check`` of the selection, the plan (keys, ledger, adopted outputs), ``prepare`` (only when something is
    to run), the run, ``finish``. ``on_result(id, ledger entry)`` is called on this process as each example
    finishes (e.g. to update a shared record). ``run.wait``: wait for the examples another process is
    working on (after the others), rather than skip them (``report.elsewhere``)."""
    started = time.time()
    report, todo = _planned(stage, run, write=True)
    _planned_notes(stage, report)
    executor = run.executor or LocalExecutor()
    if todo:  # before any bar opens: a preflight error is then one clean line
        stage_dir(stage.root, stage.name).mkdir(parents=True, exist_ok=True)
        stage.prepare([t["id"] for t in todo])
    collect = _Collector(stage, report, len(todo), run, on_result)
    try:
        if todo:
            _execute(stage, executor, todo, collect)
        report.completed = True
    finally:
        collect.close()
        _settle(stage, report, todo, started)
        with _finishing(stage):
            stage.finish(report)
    return report


__all__ = ["Adopted", "ELSEWHERE", "ItemLock", "ItemResult", "ItemRunner", "Key", "LEDGER_DIR", "Redo", "RunOptions",
           "Selection", "Stage", "StageReport", "StageWorker", "Why", "commit", "fresh_staging", "ledger_outcomes",
           "ledger_path", "lock_path", "output_kinds", "outputs_intact", "plan", "plan_only", "read_ledger",
           "run_stage", "stage_dir", "staging_path", "validate_selection", "write_ledger"]
