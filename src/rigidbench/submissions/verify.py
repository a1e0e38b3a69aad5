"""Checking a submission: its numbers recomputed from its per-example records, and (with its videos) a seeded
subset of its examples scored again.

``aggregate_problems(sub)`` recomputes every aggregate of results.json with the code ``rigidbench evaluate``
writes them with (``evaluation.aggregation``, ``readouts.records.aggregate_readouts``): the mean, standard
deviation and counts of each measurement overall, per task and per partition, the coverage block, the readouts
block, the example count, the skipped measurements, the notes and whether the run is official. Each number that
differs is one line. The card's ``provenance.records`` digests must be those of the bundled records.

Re-scoring (``commands.submitting.rescore``, which runs the evaluate stage, a layer above this one):
``check_rescore_set`` checks the reference set given is the run's, ``rescore_ids(sub, n, seed)`` draws the examples
among those whose video the bundle holds, and ``rescore_differences`` compares each re-scored measurement with the
record: equal within ``RESCORE_REL_TOL`` of the larger magnitude, or ``RESCORE_ABS_TOL`` (both stated in every line
that reports a difference and in docs/submitting.md).
"""

from __future__ import annotations

import math
import random
from pathlib import Path
from typing import Any

from ..evaluation.aggregation import EVAL_SIZE, aggregate, coverage_summary
from ..groundtruth.bundle import bundle_dirs, resolve_split_dir, set_identity, unverified_reason
from ..readouts.records import aggregate_readouts, summary
from .bundle import Submission, SubmissionError

#: numbers recomputed from the same records must agree to rounding (JSON keeps doubles exactly)
AGGREGATE_REL_TOL = 1e-9
#: a re-scored measurement may differ from the submitted one by this much (relative to the larger magnitude) or
#: RESCORE_ABS_TOL: neural perception on another GPU or library version moves masks and tracks slightly
RESCORE_REL_TOL = 0.02
RESCORE_ABS_TOL = 1e-6


def _close(a: Any, b: Any, rel: float, abs_: float = 1e-12) -> bool:
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        if not (math.isfinite(a) and math.isfinite(b)):
            return a == b
        return math.isclose(a, b, rel_tol=rel, abs_tol=abs_)
    return a == b


def differences(expected: Any, actual: Any, path: str) -> list[tuple[str, Any, Any]]:
    """(dotted path, expected, actual) of each leaf where ``actual`` differs from ``expected`` (a key missing
    from either side counts; numbers compare within ``AGGREGATE_REL_TOL``)."""
    if isinstance(expected, dict) and isinstance(actual, dict):
        out = []
        for key in list(expected) + [k for k in actual if k not in expected]:
            sub = f"{path}.{key}" if path else str(key)
            if key not in actual:
                out.append((sub, expected[key], "absent"))
            elif key not in expected:
                out.append((sub, "absent", actual[key]))
            else:
                out += differences(expected[key], actual[key], sub)
        return out
    if isinstance(expected, list) and isinstance(actual, list) and len(expected) == len(actual):
        return [d for k, (e, a) in enumerate(zip(expected, actual)) for d in differences(e, a, f"{path}[{k}]")]
    return [] if _close(expected, actual, AGGREGATE_REL_TOL) else [(path, expected, actual)]


def _records(sub: Submission) -> list[dict]:
    """The records in id order, each with its compact readouts (from its readouts file when the record has none,
    as evaluate does for a record from before readouts)."""
    out = []
    for sample_id in sorted(sub.records):
        record = sub.records[sample_id]
        if not isinstance(record.get("readouts"), dict) and sample_id in sub.readouts:
            record = {**record, "readouts": summary(sub.readouts[sample_id].get("readouts") or {})}
        out.append(record)
    return out


def expected_results(sub: Submission) -> dict:
    """results.json's aggregates as the records give them (evaluate's own aggregation code)."""
    records = _records(sub)
    metrics = list(sub.results.get("metrics") or [])
    skipped = sorted({m for r in records for m in r.get("skipped", {})})
    coverage = coverage_summary(records)
    results = sub.results
    official = (results.get("n_reference") == EVAL_SIZE and len(records) == results.get("n_reference")
                and not results.get("failed") and not skipped and not coverage["short"]
                and unverified_reason(results.get("dataset") or {}) is None)
    expected = {"n_examples": len(records), "official": official, "coverage": coverage,
                "skipped_metrics": skipped, **aggregate(records, metrics),
                "readouts": aggregate_readouts(records)}
    notes = {r["id"]: r["notes"] for r in records if r.get("notes")}
    if notes or "notes" in results:
        expected["notes"] = notes
    return expected


def _show(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.10g}"
    text = repr(value) if not isinstance(value, str) else value
    return text if len(text) <= 60 else text[:57] + "..."


def aggregate_problems(sub: Submission) -> list[str]:
    """One line per number of results.json that its per-example records do not give, and per record whose
    digest in the card's provenance is not its file's."""
    where = str(sub.path)
    problems = []
    records = _records(sub)
    record_metrics = {m for r in records for m in (r.get("metrics") or {})}
    if set(sub.results.get("metrics") or []) != record_metrics:
        problems.append(f"{where}: results.json: 'metrics' lists {sorted(sub.results.get('metrics') or [])}, the "
                        f"records hold {sorted(record_metrics)}")
    for key in ("perception", "protocol"):
        want = sub.results.get(key)
        want = want.get("name") if isinstance(want, dict) else want
        odd = {r["id"]: r[key] for r in records if r.get(key) is not None and r[key] != want}
        if odd:
            first = next(iter(odd))
            problems.append(f"{where}: results.json: '{key}' is {want}, the records of {', '.join(list(odd)[:5])} "
                            f"say otherwise ({first}: {odd[first]})")
    expected = expected_results(sub)
    actual = {k: sub.results.get(k, "absent") for k in expected}
    actual["skipped_metrics"] = sorted(sub.results.get("skipped_metrics") or {})
    for path, want, got in differences(expected, actual, ""):
        problems.append(f"{where}: results.json: {path} is {_show(got)}, the records give {_show(want)}")
    digests = sub.provenance.get("records") or {}
    for sample_id in sorted(set(digests) | set(sub.records)):
        if digests.get(sample_id) != sub.record_digest(sample_id):
            problems.append(f"{where}: card.yaml: provenance.records.{sample_id} is not the SHA-256 of "
                            f"examples/{sample_id}.json")
    return problems


# -- re-scoring ----------------------------------------------------------------------------------------------


def rescore_ids(sub: Submission, n: int, seed: int) -> list[str]:
    """``n`` ids drawn with ``seed`` from the examples whose video the bundle holds (sorted)."""
    with_video = sorted(i for i, p in sub.videos.items() if p is not None)
    if not with_video:
        raise SubmissionError(f"{sub.path}: holds no videos, so nothing can be scored again; bundle with "
                              "`rigidbench submit RUN --videos PREDICTIONS`")
    return sorted(random.Random(seed).sample(with_video, min(n, len(with_video))))


def rescore_differences(sub: Submission, rescored: dict[str, dict]) -> list[str]:
    """One line per measurement of each re-scored record (id -> the record evaluate wrote again) that differs
    from the submitted record beyond the tolerance (``RESCORE_REL_TOL``, ``RESCORE_ABS_TOL``, stated in the
    line); a defined value against an undefined one (null) always differs."""
    where = str(sub.path)
    problems = []
    for sample_id, record in sorted(rescored.items()):
        again = record.get("metrics") or {}
        for metric, value in (sub.records[sample_id].get("metrics") or {}).items():
            new = again.get(metric)
            same = (value is None and new is None) or (
                value is not None and new is not None
                and math.isclose(value, new, rel_tol=RESCORE_REL_TOL, abs_tol=RESCORE_ABS_TOL))
            if not same:
                problems.append(f"{where}: {sample_id}: {metric} is {_show(value)} in its record, {_show(new)} "
                                f"scored again (tolerance {RESCORE_REL_TOL:g} relative, {RESCORE_ABS_TOL:g} "
                                "absolute)")
    return problems


def check_rescore_set(sub: Submission, data: str | Path) -> Path:
    """The split folder of ``data`` when it holds the set the submission was scored on (name, version and MD5),
    else SubmissionError saying which set to pass."""
    split = resolve_split_dir(data)
    identity, recorded = set_identity(bundle_dirs(split)), sub.results.get("dataset") or {}
    keys = ("dataset", "version", "md5")
    if {k: identity.get(k) for k in keys} != {k: recorded.get(k) for k in keys}:
        raise SubmissionError(f"--data {data}: holds {_set(identity)}, not the set the submission was scored on "
                              f"({_set(recorded)}); pass that set's folder")
    missing = [i for i in sub.records if not (split / i).is_dir()]
    if missing:
        raise SubmissionError(f"--data {data}: has no example {missing[0]} of the submission; pass the whole set")
    return split


def _set(identity: dict) -> str:
    return " ".join(str(identity[k]) for k in ("dataset", "version") if identity.get(k)) or "an unnamed set"
