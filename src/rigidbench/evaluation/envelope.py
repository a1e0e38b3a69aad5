"""The physical envelope folder (made by ``rigidbench envelope``) read for ``evaluate --envelope ENV``, and the
"envelope" block of results.json computed from a run's records against it.

An envelope folder holds ``envelope.json`` ({"config", "twins", "geometry_only", "scale", "examples": {id:
{"status": "ok" | "no envelope", "reason", "twins"}}, optionally "dataset"}), ``predictions/`` (the twins)
and ``run/``, an evaluate run folder of the twins scored against the reference: one record per (example,
twin) ``run/examples/<id>.json`` (twin 0) or ``<id>.s<k>.json`` (``folders.sample_item``). The statistics
are ``rigidbench.stats.envelope``'s; formulas in docs/statistics.md.
"""

from __future__ import annotations

import logging
import math
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ..errors import UserError
from ..folders import RunFolder, sample_item
from ..jsonio import DamagedJSON, load_json, read_json
from ..metrics import METRICS
from ..readouts.records import record_problem
from ..stats.envelope import EnvelopeScores, score_against_envelope, summarize, summarize_by, width_table

log = logging.getLogger(__name__)

ENVELOPE_FILE = "envelope.json"
RUN_DIR = "run"
STATUSES = ("ok", "no envelope")
#: The measurements a geometry-only envelope covers (no path-traced RGB: the appearance group is not measured).
GEOMETRY_GROUP = "motion"
#: The identity fields that must agree between the envelope's set and the run's (``groundtruth.bundle``'s
#: ``dataset_identity``; whether an MD5 was checked may differ).
IDENTITY_FIELDS = ("dataset", "version", "md5", "preset")

REMAKE = "make it again with `rigidbench envelope`"


@dataclass(frozen=True)
class Envelope:
    """An envelope folder, read. ``twins``: example id -> measurement -> (n,) float64 twin scores in twin
    order (NaN: not measured); ``tasks``/``partitions``: example id -> its task/partition (from the twin
    records); ``no_envelope``: example id -> why it has none (envelope.json's reason, or no readable twin
    record); ``examples``: every example id envelope.json names; ``metrics``: the measurements the envelope
    measures, in registry order (the motion group only when ``geometry_only``); ``dataset``: the identity
    of the set it was made for (envelope.json's, else its run's results.json's), None when unknown;
    ``skipped``: twin records left out as damaged (path: why)."""

    source: Path
    n_twins: int
    geometry_only: bool
    scale: float | None
    config: dict
    examples: tuple[str, ...]
    metrics: tuple[str, ...]
    twins: dict[str, dict[str, np.ndarray]]
    tasks: dict[str, str]
    partitions: dict[str, str]
    no_envelope: dict[str, str]
    dataset: dict | None = None
    skipped: dict[str, str] = field(default_factory=dict)
    floor: dict[str, dict[str, float]] = field(default_factory=dict)  # id -> measurement -> the reference's own value


def _load_document(path: Path, what: str) -> dict:
    try:
        return load_json(path, dict)
    except FileNotFoundError:
        raise UserError(f"{path}: not found, so {path.parent} is not a complete envelope folder ({what}); "
                        f"{REMAKE}") from None
    except (OSError, ValueError) as exc:
        reason = str(exc) if isinstance(exc, DamagedJSON) else f"{path}: unreadable ({type(exc).__name__})"
        raise UserError(f"{reason}; {REMAKE}") from None


def _field_problem(doc: dict) -> str | None:
    """Why envelope.json's content cannot be used, or None."""
    n = doc.get("twins")
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        return "its 'twins' is not a positive whole number"
    if not isinstance(doc.get("geometry_only"), bool):
        return "its 'geometry_only' is not true or false"
    scale = doc.get("scale")
    if scale is not None and (isinstance(scale, bool) or not isinstance(scale, (int, float))):
        return "its 'scale' is not a number"
    if not isinstance(doc.get("config", {}), dict):
        return "its 'config' is not a JSON object"
    examples = doc.get("examples")
    if not isinstance(examples, dict) or not examples:
        return "its 'examples' is absent, empty or not a JSON object"
    for sample_id, entry in examples.items():
        if not isinstance(entry, dict) or entry.get("status") not in STATUSES:
            return f"example {sample_id}: its 'status' is not one of {', '.join(repr(s) for s in STATUSES)}"
        if entry.get("reason") is not None and not isinstance(entry["reason"], str):
            return f"example {sample_id}: its 'reason' is not text"
    if doc.get("dataset") is not None and not isinstance(doc["dataset"], dict):
        return "its 'dataset' is not a JSON object"
    return None


def _twin_problem(path: Path, doc: Any) -> str | None:
    """Why a twin record cannot be used, or None."""
    if not isinstance(doc, dict):
        return "not a JSON object"
    problem = record_problem(doc)
    if problem is not None:
        return problem
    k = doc.get("sample", 0)
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        return "its 'sample' is not a whole number >= 0"
    if path.stem != sample_item(doc["id"], k):
        return f"it holds twin {k} of example {doc['id']}, whose file is {sample_item(doc['id'], k)}.json"
    return None


def read_envelope(env_dir: str | Path) -> Envelope:
    """The envelope folder ``env_dir`` (ENV/envelope.json and the twins' records in ENV/run/examples/), read.
    A missing or damaged envelope.json, or a missing run/examples/, is a UserError naming the file and saying
    to make the envelope again; one damaged twin record is left out with a warning (``Envelope.skipped``)."""
    env_dir = Path(env_dir)
    if not env_dir.is_dir():
        raise UserError(f"{env_dir}: no such envelope folder; make one with `rigidbench envelope`")
    doc = _load_document(env_dir / ENVELOPE_FILE, "it describes the twins")
    problem = _field_problem(doc)
    if problem is not None:
        raise UserError(f"{env_dir / ENVELOPE_FILE}: {problem}; {REMAKE}")
    run = RunFolder(env_dir / RUN_DIR)
    if not run.examples_dir.is_dir():
        raise UserError(f"{run.examples_dir}: not found (the twins' scores against the reference); {REMAKE}")
    declared = doc["examples"]
    values: dict[str, dict[int, dict]] = defaultdict(dict)
    tasks: dict[str, str] = {}
    partitions: dict[str, str] = {}
    skipped: dict[str, str] = {}
    for path in run.records():  # <id>.json and <id>.s<k>.json
        record = read_json(path, "this twin is left out of the envelope", expect=dict)
        if record is None:
            skipped[str(path)] = "unreadable"
            continue
        problem = _twin_problem(path, record)
        if problem is None and record["id"] not in declared:
            problem = f"example {record['id']} is not in {ENVELOPE_FILE}"
        if problem is not None:
            log.warning("%s: %s; this twin is left out of the envelope (%s)", path, problem, REMAKE)
            skipped[str(path)] = problem
            continue
        values[record["id"]][int(record.get("sample", 0))] = record["metrics"]
        tasks[record["id"]], partitions[record["id"]] = record["task"], record["partition"]
    geometry_only = doc["geometry_only"]
    candidates = [m for m in METRICS if not geometry_only or METRICS[m].group == GEOMETRY_GROUP]
    twins: dict[str, dict[str, np.ndarray]] = {}
    no_envelope: dict[str, str] = {}
    for sample_id in sorted(declared):
        entry = declared[sample_id]
        if entry["status"] != "ok":
            no_envelope[sample_id] = entry.get("reason") or "no envelope (no reason recorded)"
        elif not values.get(sample_id):
            no_envelope[sample_id] = f"no readable twin record in {run.examples_dir}; {REMAKE}"
        else:
            by_twin = values[sample_id]
            twins[sample_id] = {m: np.array([_number(by_twin[k].get(m)) for k in sorted(by_twin)]) for m in candidates}
    metrics = tuple(m for m in candidates if any(np.isfinite(t[m]).any() for t in twins.values()))
    dataset = doc.get("dataset")
    if dataset is None:  # the twins' run records the set it scored against
        dataset = (read_json(run.results, "the envelope's set is not checked against the run's", expect=dict)
                   or {}).get("dataset")
    return Envelope(source=env_dir, n_twins=doc["twins"], geometry_only=geometry_only,
                    scale=None if doc.get("scale") is None else float(doc["scale"]), config=doc.get("config", {}),
                    examples=tuple(sorted(declared)), metrics=metrics,
                    twins={i: {m: t[m] for m in metrics} for i, t in twins.items()}, tasks=tasks,
                    partitions=partitions, no_envelope=no_envelope,
                    dataset=dataset if isinstance(dataset, dict) else None, skipped=skipped,
                    floor={i: {m: float(v) for m, v in declared[i]["floor"].items() if isinstance(v, (int, float))}
                           for i in twins if isinstance(declared[i].get("floor"), dict)})


def _number(value: Any) -> float:
    return float(value) if value is not None else math.nan


def _identities(identity: dict) -> set[tuple]:
    """The sets an identity (``dataset_identity`` or ``set_identity``) names, as comparable tuples."""
    return {tuple(ident.get(k) for k in IDENTITY_FIELDS) for ident in identity.get("sets") or [identity]
            if isinstance(ident, dict) and ident.get("dataset") not in ("unknown", "mixed")}


def check_envelope(envelope: Envelope, run_ids: Iterable[str], identity: dict | None) -> None:
    """UserError when ``envelope`` was made for another set than the run's examples ``run_ids`` of set
    ``identity`` (``groundtruth.bundle.set_identity``): none of the run's examples is in it, or the sets'
    identities (name, version, MD5, preset) differ. Examples of the run outside it are allowed (counted later)."""
    run_ids = sorted(run_ids)
    if run_ids and not set(run_ids) & set(envelope.examples):
        shown = ", ".join(run_ids[:3]) + (" ..." if len(run_ids) > 3 else "")
        raise UserError(f"{envelope.source}: an envelope for other examples (none of the run's {len(run_ids)} "
                        f"examples, {shown}, is in its {ENVELOPE_FILE}); make one for this set with "
                        "`rigidbench envelope`")
    if identity and envelope.dataset:
        ours, theirs = _identities(identity), _identities(envelope.dataset)
        if ours and theirs and not ours <= theirs:
            def name(ids: set[tuple]) -> str:
                return "; ".join(" ".join(f"{k} {v}" for k, v in zip(IDENTITY_FIELDS, t) if v is not None)
                                 or "of no recorded name" for t in sorted(ids, key=str))

            raise UserError(f"{envelope.source}: made for the set {name(theirs)}, but the run's reference set is "
                            f"{name(ours)}; make an envelope for this set with `rigidbench envelope`")


def _none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def padded(rows: Sequence[np.ndarray]) -> np.ndarray:
    """Rows of varying length -> (len(rows), longest) float64, NaN-padded."""
    out = np.full((len(rows), max((len(r) for r in rows), default=0) or 1), np.nan)
    for i, row in enumerate(rows):
        out[i, :len(row)] = row
    return out


def envelope_block(envelope: Envelope, records: list[dict]) -> dict:
    """results.json's "envelope" block for a run's score records (one per example and sample; a record without
    "sample" is sample 0) against ``envelope``: per measurement the share of examples inside the envelope, the
    mean excess and their number overall, per task and per partition; per example the twins' quantiles and
    the model's position, excess and inside (with each sample's position); per task the envelope's median
    width; and the run's examples without an envelope, with why."""
    samples: dict[str, dict[int, dict]] = defaultdict(dict)
    labels: dict[str, tuple[str, str]] = {}
    for r in records:
        samples[r["id"]][int(r.get("sample", 0))] = r.get("metrics") or {}
        labels[r["id"]] = (r["task"], r["partition"])
    ids = sorted(i for i in samples if i in envelope.twins)
    missing = {i: envelope.no_envelope.get(i, f"not in {envelope.source / ENVELOPE_FILE}")
               for i in sorted(samples) if i not in envelope.twins}
    tasks = [labels[i][0] for i in ids]
    parts = [labels[i][1] for i in ids]
    per_example: dict[str, dict] = {i: {} for i in ids}
    overall: dict[str, dict] = {}
    by_task: dict[str, dict] = defaultdict(dict)
    by_partition: dict[str, dict] = defaultdict(dict)
    bands: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for metric in envelope.metrics:
        twins = padded([envelope.twins[i][metric] for i in ids])
        model = padded([np.array([_number(samples[i][k].get(metric)) for k in sorted(samples[i])]) for i in ids])
        floor = np.array([envelope.floor.get(i, {}).get(metric, np.nan) for i in ids], np.float64)
        scores = score_against_envelope(twins, model, METRICS[metric].higher_is_better, floor)
        overall[metric] = summarize(scores)
        for groups, table in ((tasks, by_task), (parts, by_partition)):
            for group, summary in summarize_by(scores, groups).items():
                table[group][metric] = summary
        bands[metric] = (scores.q05, scores.q95)
        for e, sample_id in enumerate(ids):
            if scores.has_envelope[e]:
                per_example[sample_id][metric] = _example_entry(scores, e, len(samples[sample_id]))
    return {"source": str(envelope.source), "twins": envelope.n_twins, "geometry_only": envelope.geometry_only,
            "scale": envelope.scale, "metrics": list(envelope.metrics), "overall": overall,
            "by_task": dict(by_task), "by_partition": dict(by_partition), "per_example": per_example,
            "widths": width_table(bands, tasks), "n_no_envelope": len(missing), "no_envelope": missing}


def _example_entry(scores: EnvelopeScores, e: int, k: int) -> dict:
    inside = scores.inside[e]
    return {"q05": _none(scores.q05[e]), "median": _none(scores.median[e]), "q95": _none(scores.q95[e]),
            "bound": _none(scores.bound[e]),
            "twins": int(scores.twins[e]), "value": _none(scores.value[e]), "position": _none(scores.position[e]),
            "excess": _none(scores.excess[e]), "inside": None if math.isnan(inside) else bool(inside),
            "sample_positions": [_none(p) for p in scores.sample_positions[e, :k]]}
