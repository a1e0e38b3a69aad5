"""Where a stage's items run: in this process, one child process per item, or on Ray actors.

The stage driver (``driver.run_stage``) hands an executor a *runner* ("module:Class", normally
``driver.ItemRunner``), the JSON the runner is built from (the stage's name, root and worker options) and
the items still to do, each a JSON dict (its id, data, key and the digest of the ledger entry the plan
read). The executor builds the runner where the items run and calls ``runner(item)`` (or
``runner(item, progress=f)`` when the driver shows sub-steps) once per item; the runner makes the item in
a staging folder, commits it and writes its ledger entry, and returns that entry. ``map`` hands each entry
back to the driver (``on_result``) as the item finishes, in completion order. A runner raises only for
bugs: a bad example comes back as a failed ledger entry. So the same example gives the same files
whichever executor ran it.

- ``LocalExecutor`` (``in_process``): one runner in this process, items one after another, or ``threads``
  at once. The driver may lend it a runner around a worker it built itself (``Stage.worker_instance``),
  which may hold objects that cannot travel.
- ``ProcessExecutor``: each item in a fresh child Python process, ``workers`` at once, so a crash (Blender's,
  a segfault) loses only that item; progress and the entry come back on a pipe (render's default).
- ``RayExecutor``: Ray actors, one runner each (a model loads once per actor), with the resources the stage
  asks for (``num_gpus=1`` for a GPU model, CPUs for rendering), ``max_restarts`` and ``max_task_retries``
  so an item whose actor died runs again elsewhere, and a bounded number of items in flight. Ray is an
  optional extra (``pip install 'rigidbench[ray]'``).

``Shard(i, n)`` is not an executor but part of the driver's ``Selection``: the i-th of n deterministic,
disjoint parts of the selected items (by position), for job arrays of schedulers without Ray.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
from abc import ABC, abstractmethod
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Sequence

from .errors import UserError
from .extras import require
from .logsafe import configure_logging
from .registry import load_target

log = logging.getLogger(__name__)

EXECUTORS = ("local", "ray")
ProgressHook = Callable[[Any, int, int], None]


@dataclass(frozen=True)
class Shard:
    """The ``index``-th of ``count`` parts of a sorted item list: items k with k % count == index."""

    index: int = 0
    count: int = 1

    @classmethod
    def parse(cls, text: str | None) -> "Shard":
        """'i/n' with 0 <= i < n (None: the whole list)."""
        if text is None:
            return cls()
        try:
            i, n = (int(v) for v in str(text).split("/"))
        except ValueError:
            raise UserError(f"--shard {text}: expected i/n, e.g. 0/4 (the first of four shards)") from None
        if n < 1 or not 0 <= i < n:
            raise UserError(f"--shard {text}: need 0 <= i < n")
        return cls(i, n)

    def select(self, items: Sequence) -> list:
        """The items of this shard, in their order; the n shards partition ``items``."""
        return [item for k, item in enumerate(items) if k % self.count == self.index]

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


@dataclass(frozen=True)
class Resources:
    """What one worker needs: CPUs and GPUs (Ray schedules by these; locally they are advisory)."""

    num_cpus: float = 1.0
    num_gpus: float = 0.0


@dataclass
class Executor(ABC):
    """Base: ``map`` yields (item, record) as items finish, in completion order."""

    name: str = "local"
    #: whether items run in this process (the driver may then lend the executor a worker it built itself)
    in_process: ClassVar[bool] = False

    @abstractmethod
    def map(self, worker: str, job: dict, items: Sequence, resources: Resources = Resources(),
            on_result: Callable[[Any, dict], None] | None = None, instance: Any = None,
            on_progress: ProgressHook | None = None) -> list[tuple[Any, dict]]:
        """Run ``worker`` ("module:Class", built as Class(job)) on every item; ``on_result(item, record)`` is
        called on this process as each finishes. ``instance``: a ready worker a local executor uses instead
        (it may hold objects that cannot travel, e.g. models a test built). ``on_progress(item, done,
        total)``: sub-steps of an item (where the executor can report them), the worker being called as
        ``worker(item, progress=f)``."""

    def close(self) -> None:
        pass


@dataclass
class LocalExecutor(Executor):
    """One worker in this process; ``threads`` > 1 calls it from that many threads (it must be thread-safe),
    reporting each item as it finishes."""

    name: str = "local"
    threads: int = 1
    in_process: ClassVar[bool] = True

    def map(self, worker: str, job: dict, items: Sequence, resources: Resources = Resources(),
            on_result: Callable[[Any, dict], None] | None = None, instance: Any = None,
            on_progress: ProgressHook | None = None) -> list[tuple[Any, dict]]:
        if not items:
            return []
        instance = instance if instance is not None else load_target(worker, "worker")(job)
        out: list[tuple[Any, dict]] = []
        try:
            if self.threads <= 1:
                for item in items:
                    record = (instance(item) if on_progress is None else
                              instance(item, progress=lambda done, total, item=item: on_progress(item, done, total)))
                    out.append((item, record))
                    if on_result:
                        on_result(item, record)
            else:
                with ThreadPoolExecutor(max_workers=self.threads) as pool:  # results as they finish
                    futures = {pool.submit(instance, item): item for item in items}
                    for future in as_completed(futures):
                        item, record = futures[future], future.result()  # a worker's bug raises here
                        out.append((item, record))
                        if on_result:
                            on_result(item, record)
        finally:
            close = getattr(instance, "close", None)
            if close is not None:
                close()
        return out


class _RayWorkerHost:
    """The Ray actor: builds one worker from the job and calls it per item."""

    def __init__(self, worker: str, job: dict):
        self.worker = load_target(worker, "worker")(job)

    def run(self, item):
        return self.worker(item)

    def pid(self) -> int:
        return os.getpid()


@dataclass
class RayExecutor(Executor):
    """Ray actors on a cluster (``address``; None starts or joins a local one).

    ``workers``: actors to start (default: as many as the cluster's resources allow, at most the
    number of items); ``max_in_flight``: items submitted and not yet finished, per actor 2 by
    default; ``max_retries``: how often an item whose actor died is run again (on a restarted actor)."""

    name: str = "ray"
    address: str | None = None
    workers: int | None = None
    max_in_flight: int | None = None
    max_retries: int = 3
    init_options: dict = field(default_factory=dict)

    def _ray(self):
        ray = require("ray", "--executor ray")
        if not ray.is_initialized():
            ray.init(address=self.address, ignore_reinit_error=True, log_to_driver=False, **self.init_options)
        return ray

    def default_workers(self, resources: Resources) -> int:
        """How many workers with ``resources`` the cluster holds at once (at least 1)."""
        return self._actor_count(self._ray(), resources, 1 << 30)

    def _actor_count(self, ray, resources: Resources, n_items: int) -> int:
        if self.workers:
            return max(1, min(self.workers, n_items))
        total = ray.cluster_resources()
        fit = []
        if resources.num_cpus:
            fit.append(int(total.get("CPU", 1) // resources.num_cpus))
        if resources.num_gpus:
            fit.append(int(total.get("GPU", 0) // resources.num_gpus))
        return max(1, min([n_items] + [f for f in fit if f > 0] or [1]))

    def map(self, worker: str, job: dict, items: Sequence, resources: Resources = Resources(),
            on_result: Callable[[Any, dict], None] | None = None, instance: Any = None,
            on_progress: ProgressHook | None = None) -> list[tuple[Any, dict]]:
        if not items:
            return []
        ray = self._ray()
        total = ray.cluster_resources()
        if resources.num_gpus > total.get("GPU", 0):
            raise UserError(f"this stage needs {resources.num_gpus:g} GPU per worker but the Ray cluster has "
                            f"{total.get('GPU', 0):g}; add GPU nodes or run it on CPUs with --device cpu")
        host = ray.remote(_RayWorkerHost).options(
            num_cpus=resources.num_cpus, num_gpus=resources.num_gpus,
            max_restarts=self.max_retries, max_task_retries=self.max_retries)
        actors = [host.remote(worker, job) for _ in range(self._actor_count(ray, resources, len(items)))]
        limit = self.max_in_flight or 2 * len(actors)
        pending: dict[Any, tuple[Any, Any]] = {}  # object ref -> (item, actor)
        queue = list(items)
        idle = list(actors) * max(1, limit // len(actors))
        out: list[tuple[Any, dict]] = []
        try:
            while queue or pending:
                while queue and idle and len(pending) < limit:
                    actor = idle.pop(0)
                    item = queue.pop(0)
                    pending[actor.run.remote(item)] = (item, actor)
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    item, actor = pending.pop(ref)
                    idle.append(actor)
                    try:
                        record = ray.get(ref)
                    except ray.exceptions.RayActorError as exc:  # retries exhausted: the worker kept dying
                        record = {"status": "failed", "error": f"worker died {self.max_retries + 1} times: "
                                                               f"{type(exc).__name__}"}
                    except ray.exceptions.RayTaskError as exc:  # a bug inside the worker: stop, as locally
                        raise exc.as_instanceof_cause() from None
                    out.append((item, record))
                    if on_result:
                        on_result(item, record)
        finally:
            for actor in actors:
                ray.kill(actor)
        return out


# -- child processes -----------------------------------------------------------------------------------
#
# Each item runs in ``python -c "...; _child_main()"`` (not multiprocessing, whose spawn mode re-imports the
# caller's __main__). The task comes as one JSON argument; messages come back as JSON lines on a pipe whose
# descriptor is the second argument, so the worker's own stdout (Blender's) stays separate.

_CHILD_CODE = "from rigidbench.executors import _child_main; _child_main()"
POLL_S = 0.2


def _die_with_parent() -> None:
    """Linux: have the kernel kill this child when the parent process dies (no orphaned workers)."""
    if sys.platform.startswith("linux"):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def _child_main() -> None:
    """Child entry: argv = [task JSON, message fd]. Builds the worker, runs one item, sends its record."""
    _die_with_parent()
    task = json.loads(sys.argv[1])
    out = os.fdopen(int(sys.argv[2]), "w", buffering=1)

    def send(*msg: Any) -> None:
        out.write(json.dumps(msg) + "\n")

    configure_logging(logging.WARNING, f"%(levelname)s [{task.get('label', '')}] %(name)s: %(message)s")
    worker = load_target(task["worker"], "worker")(task["job"])
    try:
        record = worker(task["item"], progress=lambda done, total: send("progress", int(done), int(total)))
    finally:
        close = getattr(worker, "close", None)
        if close is not None:
            close()
    send("result", record)


def _exit_reason(code: int | None) -> str:
    if code is not None and code < 0:
        try:
            return f"worker process killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"worker process killed by signal {-code}"
    return f"worker process exited with code {code} without a result (see the traceback above)"


@dataclass
class _Child:
    item: Any
    proc: Any
    fd: int
    buffer: bytes = b""
    record: dict | None = None


@dataclass
class ProcessExecutor(Executor):
    """Each item in its own child Python process, ``workers`` at a time. A child that dies (a crash inside
    Blender, a kill) fails only its item. ``quiet`` sends the children's stdout to /dev/null; ``label``
    names an item in the children's log lines (``label(item)``)."""

    name: str = "processes"
    workers: int = 1
    quiet: bool = True
    label: Callable[[Any], str] | None = None

    def map(self, worker: str, job: dict, items: Sequence, resources: Resources = Resources(),
            on_result: Callable[[Any, dict], None] | None = None, instance: Any = None,
            on_progress: ProgressHook | None = None) -> list[tuple[Any, dict]]:
        import selectors
        import subprocess

        if self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {self.workers}")
        pending = list(items)
        running: dict[int, _Child] = {}
        out: list[tuple[Any, dict]] = []
        sel = selectors.DefaultSelector()

        def start(item) -> None:
            r, w = os.pipe()
            task = {"worker": worker, "job": job, "item": item, "label": self.label(item) if self.label else ""}
            try:
                proc = subprocess.Popen([sys.executable, "-c", _CHILD_CODE, json.dumps(task), str(w)],
                                        pass_fds=(w,), stdin=subprocess.DEVNULL,
                                        stdout=subprocess.DEVNULL if self.quiet else None)
            finally:
                os.close(w)
            running[r] = _Child(item=item, proc=proc, fd=r)
            sel.register(r, selectors.EVENT_READ, running[r])

        def handle(child: _Child, line: bytes) -> None:
            try:
                msg = json.loads(line)
            except ValueError:
                log.warning("unreadable worker message %r", line[:200])
                return
            if msg[0] == "progress" and on_progress is not None:
                on_progress(child.item, int(msg[1]), int(msg[2]))
            elif msg[0] == "result":
                child.record = msg[1]

        def finish(child: _Child) -> None:
            sel.unregister(child.fd)
            os.close(child.fd)
            del running[child.fd]
            code = child.proc.wait()
            record = child.record if child.record is not None else {"status": "failed", "error": _exit_reason(code)}
            out.append((child.item, record))
            if on_result:
                on_result(child.item, record)

        try:
            while pending or running:
                while pending and len(running) < self.workers:
                    start(pending.pop(0))
                for key, _ in sel.select(timeout=POLL_S):
                    child = key.data
                    chunk = os.read(child.fd, 65536)
                    if not chunk:  # the child closed its end: it has exited (or is exiting)
                        if child.buffer.strip():
                            handle(child, child.buffer)
                        finish(child)
                        continue
                    child.buffer += chunk
                    *lines, child.buffer = child.buffer.split(b"\n")
                    for line in lines:
                        if line.strip():
                            handle(child, line)
        except KeyboardInterrupt:
            for child in running.values():
                child.proc.terminate()
            for child in running.values():
                child.proc.wait(5)
            raise
        finally:
            for child in list(running.values()):
                os.close(child.fd)
            sel.close()
        return out


def usable_cores(at_most: int | None = None) -> int:
    """The cores this process may run on (its CPU affinity where the system tells it), at least 1 and at most
    ``at_most``: how many threads a step that releases the GIL (frame decoding, image filters) splits over."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, cores if at_most is None else min(cores, at_most))


def make_executor(name: str = "local", *, ray_address: str | None = None, threads: int = 1,
                  workers: int | None = None) -> Executor:
    """The executor ``--executor`` names ("local", "processes" or "ray")."""
    if name == "local":
        return LocalExecutor(threads=threads)
    if name == "processes":
        return ProcessExecutor(workers=workers or 1)
    if name == "ray":
        return RayExecutor(address=ray_address, workers=workers)
    raise UserError(f"--executor {name}: choose one of {', '.join(EXECUTORS)}")


def failure_record(exc: BaseException) -> dict:
    """The record of an example whose input was bad."""
    return {"status": "failed", "error": str(exc)}


__all__ = ["EXECUTORS", "Executor", "LocalExecutor", "ProcessExecutor", "RayExecutor", "Resources", "Shard", "failure_record",
           "make_executor"]
