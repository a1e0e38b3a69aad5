"""Executors and shards without a cluster: the local executor, shard arithmetic, a missing Ray."""

import sys
import threading

import pytest

from rigidbench.errors import MissingExtra, UserError
from rigidbench.executors import LocalExecutor, RayExecutor, Shard, make_executor


class Doubler:
    """A worker: item -> record; remembers the threads it ran on."""

    threads: set = set()

    def __init__(self, job):
        self.offset = job["offset"]
        self.closed = False

    def __call__(self, item):
        Doubler.threads.add(threading.get_ident())
        return {"status": "succeeded", "value": 2 * item + self.offset}

    def close(self):
        self.closed = True


def test_the_local_executor_builds_one_worker_and_reports_every_item():
    seen = []
    out = LocalExecutor().map(f"{__name__}:Doubler", {"offset": 1}, [1, 2, 3], on_result=lambda i, r: seen.append(i))
    assert [r["value"] for _, r in out] == [3, 5, 7] and seen == [1, 2, 3]


def test_threads_and_a_ready_instance():
    Doubler.threads = set()
    worker = Doubler({"offset": 0})
    out = LocalExecutor(threads=3).map("unused:Name", {}, list(range(30)), instance=worker)
    # in completion order (each reported as it finishes), every item once, each with its own result
    assert sorted(item for item, _ in out) == list(range(30)) and worker.closed
    assert all(r["value"] == 2 * item for item, r in out)


@pytest.mark.parametrize("count", [1, 2, 3, 7])
def test_shards_partition_any_list(count):
    items = list(range(23))
    parts = [Shard(i, count).select(items) for i in range(count)]
    assert sorted(x for p in parts for x in p) == items
    assert max(map(len, parts)) - min(map(len, parts)) <= 1


def test_bad_executor_and_missing_ray_say_what_to_do(monkeypatch):
    with pytest.raises(UserError, match="choose one of local, ray"):
        make_executor("slurm")
    monkeypatch.setitem(sys.modules, "ray", None)  # as if the [ray] extra were not installed
    with pytest.raises(MissingExtra, match=r"^--executor ray needs ray, which is not installed: "
                                           r"pip install 'rigidbench\[ray\]'$"):
        RayExecutor().map(f"{__name__}:Doubler", {"offset": 0}, [1])
