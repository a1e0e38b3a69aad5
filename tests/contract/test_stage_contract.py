"""The stage contract, checked on every cheap stage (fixtures.stage_cases.CASES): a rerun makes nothing and
touches nothing; a changed setting makes every item again, saying its inputs or settings changed; a run
killed after making one item (staged, not committed) resumes to the outputs of a clean run, making only that
item and those after it; an unknown id is one error before anything is prepared or written; ``key()`` is pure
(called twice, the same key, and neither the item's data nor the stage's attributes changed)."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import pytest

from fixtures.children import kill_when
from fixtures.stage_cases import CASES
from rigidbench.driver import Why, ledger_path, read_ledger, staging_path
from rigidbench.errors import UserError


@pytest.fixture(scope="module", params=sorted(CASES))
def case(request, tmp_path_factory):
    made = CASES[request.param]()
    inputs = tmp_path_factory.mktemp(f"{made.name}-inputs")
    made.inputs(inputs)
    return made, inputs


def stamps(case, out: Path) -> dict[str, int]:
    """Each file's mtime, but the run-level files the stage's ``finish`` writes after every run."""
    skip = {(case.root(out) / name).relative_to(out).as_posix() for name in case.rewritten}
    return {name: p.stat().st_mtime_ns for p in sorted(out.rglob("*"))
            if p.is_file() and (name := p.relative_to(out).as_posix()) not in skip}


def ledger(case, out: Path, item_id: str) -> dict | None:
    return read_ledger(case.root(out), case.name, item_id)


def ledger_keys(case, out: Path) -> dict[str, str | None]:
    return {i: (ledger(case, out, i) or {}).get("key") for i in case.ids}


def test_a_rerun_makes_nothing_and_touches_nothing(case, tmp_path):
    case, inputs = case
    out = tmp_path / "out"
    case.run(inputs, out)
    assert all(ledger(case, out, i)["status"] == "succeeded" for i in case.ids)
    before, seen = stamps(case, out), case.snapshot(out)
    report = case.run(inputs, out)
    assert stamps(case, out) == before and not report.redone
    assert case.snapshot(out) == seen


def test_a_changed_setting_makes_every_item_again(case, tmp_path):
    case, inputs = case
    out = tmp_path / "out"
    case.run(inputs, out)
    keys = ledger_keys(case, out)
    report = case.run(inputs, out, **case.changed)
    assert {i: why.why for i, why in report.redone.items()} == {i: Why.CHANGED for i in case.ids}
    assert all(new != keys[i] for i, new in ledger_keys(case, out).items())
    clean = tmp_path / "clean"
    case.run(inputs, clean, **case.changed)
    assert case.snapshot(out) == case.snapshot(clean)


def test_a_killed_run_resumes_to_the_outputs_of_a_clean_run(case, tmp_path):
    case, inputs = case
    out, marker, hang = tmp_path / "out", tmp_path / "hanging", case.ids[1]
    kill_when([sys.executable, "-m", "fixtures.stage_child", case.name, str(inputs), str(out), hang, str(marker)],
              marker)
    root = case.root(out)
    first = ledger(case, out, case.ids[0])
    assert first["status"] == "succeeded"
    assert not ledger_path(root, case.name, hang).exists() and staging_path(root, case.name, hang).is_dir()
    report = case.run(inputs, out)
    assert ledger(case, out, case.ids[0]) == first  # made before the kill: not made again
    assert all(ledger(case, out, i)["status"] == "succeeded" for i in case.ids)
    assert not staging_path(root, case.name, hang).exists() and not report.redone
    clean = tmp_path / "clean"
    case.run(inputs, clean)
    assert case.snapshot(out) == case.snapshot(clean)


def test_an_unknown_id_is_one_error_before_anything_is_prepared(case, tmp_path, monkeypatch):
    case, inputs = case
    prepared = []
    monkeypatch.setattr(case.stage_class, "prepare", lambda self, *args: prepared.append(args))
    out = tmp_path / "out"
    with pytest.raises(UserError, match="unknown example id"):
        case.run(inputs, out, ids=[case.ids[0], "no-such-id"])
    assert prepared == []
    written = [p for p in out.rglob("*") if p.is_file() and p.suffix != ".lock"] if out.exists() else []
    assert written == [], "an unknown id wrote into the output folder (more than the locks it held)"


def plain(value):
    """A comparable copy of ``value``: plain data by value (containers through), any other object by identity
    (a pure ``key()`` rebinds nothing and writes into no dict, list or set it holds)."""
    if isinstance(value, (str, int, float, bool, bytes, type(None), Path)):
        return value
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return (type(value).__name__, *map(plain, value))
    if isinstance(value, (set, frozenset)):
        return frozenset(map(plain, value))
    return ("object", id(value))


def test_key_is_pure(case, tmp_path, monkeypatch):
    case, inputs = case
    real, seen = case.stage_class.key, {}

    def key(stage, item_id, data):
        before = (plain(vars(stage)), copy.deepcopy(data))
        first, second = real(stage, item_id, data), real(stage, item_id, data)
        seen[item_id] = (first == second, before == (plain(vars(stage)), data))
        return first

    monkeypatch.setattr(case.stage_class, "key", key)
    case.run(inputs, tmp_path / "out")
    assert seen == {i: (True, True) for i in case.ids}, "(the same key twice, nothing written) per item"
