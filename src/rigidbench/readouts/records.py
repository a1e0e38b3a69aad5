"""Readouts in a run folder: per-example records, the ``readouts`` block of results.json, and
``rigidbench readouts RUN``.

- ``out/examples/<id>.readouts.json``: every readout of the example in full (values, reasons,
  per-actor fits, flag evidence, thresholds), written by ``example_readouts`` from the evaluator;
- the example's score record gets a compact ``readouts`` entry (``summary``);
- ``results.json`` ``readouts``: per readout with a distribution (speed, gravity, g s^-2,
  restitution) the median, quartiles, finite and total counts, and per flag the number raised, the
  number where it is defined and their ratio; overall, per task and per partition (one run is one model).

Reading a run folder back (``load_run_readouts``, ``record_problem``) never stops at one damaged file: a
truncated, empty, non-UTF-8, foreign or directory per-example file is left out with a warning naming it
and what to do, and counted; a damaged ``results.json`` is one error naming it.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from rigidbench.atomic import write_text
from rigidbench.errors import UserError
from rigidbench.folders import READOUTS_SUFFIX, RunFolder, sample_item, split_sample_item
from rigidbench.jsonio import DamagedJSON, load_json, read_json
from rigidbench.readouts import compute_readouts, context_from_sample
from rigidbench.readouts.flags import FLAGS, THRESHOLDS

log = logging.getLogger(__name__)

#: what to do about a damaged or missing per-example readouts file (the evaluate stage's intactness check
#: finds it and scores its example again)
RESCORE = "rerun `rigidbench evaluate` with the same --out to score {} again"
LEFT_OUT = f"its example is left out; {RESCORE.format('it')}"

#: the scalars summarised by median and IQR: name in the compact summary -> (readout, key)
DISTRIBUTIONS = {"speed": ("speed", "value"), "gravity": ("gravity", "value"),
                 "gravity_per_speed2": ("gravity", "per_speed2"), "restitution": ("restitution", "value")}


def to_jsonable(x):
    """NaN and inf -> None, numpy scalars and arrays -> Python numbers and lists, recursively."""
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    return x


def summary(readouts: dict) -> dict:
    """The compact per-example entry: the distribution scalars (None when undefined) and the flags."""
    out = {}
    for key, (name, field) in DISTRIBUTIONS.items():
        v = readouts.get(name, {}).get(field)
        out[key] = float(v) if v is not None and math.isfinite(float(v)) else None
    flags = readouts.get("flags", {}).get("example", {})
    out["flags"] = {k: (None if v is None else bool(v)) for k, v in flags.items()}
    return out


def example_readouts(sample, inputs, scores: dict, out_dir: str | Path, item: str | None = None) -> dict:
    """Compute every readout of one evaluated example from its MetricInputs, write
    out_dir/examples/<item>.readouts.json (``item``: the sample's name, ``folders.sample_item``; default the
    example id) and return the compact summary for its score record; ``scores``
    name -> MetricResult (IdDrift feeds the identity flag). ``out_dir`` is a run folder or a staging folder
    laid out like one (the evaluate stage's, committed into the run folder by the stage driver)."""
    iddrift = scores.get("iddrift")
    ctx = context_from_sample(sample, inputs, None if iddrift is None else iddrift.value)
    readouts = compute_readouts(ctx)
    path = RunFolder(out_dir).readouts(item or sample.sample_id)
    write_text(path, json.dumps(to_jsonable({"id": sample.sample_id, "task": sample.task,
                                             "partition": sample.partition, "readouts": readouts}), indent=1))
    return summary(readouts)


#: what reading a readouts file's content may raise when a field has another type or is absent
_CONTENT_ERRORS = (KeyError, TypeError, AttributeError, ValueError)


def read_example_readouts(path: Path, then: str = LEFT_OUT) -> dict | None:
    """The readouts file of one example when it can be used: a JSON object with its ``id`` and ``readouts``
    that ``summary`` reads. None when there is none, or (with a warning naming the file, why and ``then``,
    what happens and what to do) when it is damaged: truncated, empty, not UTF-8, a directory, another
    document."""
    doc = read_json(path, then, expect=dict)
    if doc is None:
        return None
    try:
        if not isinstance(doc["id"], str):
            raise TypeError(f"'id' is {type(doc['id']).__name__}, not text")
        summary(doc["readouts"])
    except _CONTENT_ERRORS as exc:
        log.warning("%s: not a readouts file (%s: %s); %s", path, type(exc).__name__, exc, then)
        return None
    return doc


def _record_summary(record: dict, out_dir: Path | None) -> dict | None:
    if isinstance(record.get("readouts"), dict):
        return record["readouts"]
    if out_dir is not None:  # a record reused from a run before readouts: read its file if there is one
        doc = read_example_readouts(RunFolder(out_dir).readouts(sample_item(record["id"], record.get("sample") or 0)))
        if doc is not None:
            return summary(doc["readouts"])
    return None


def _distribution(values: list) -> dict:
    arr = np.array([v for v in values if v is not None and math.isfinite(v)], np.float64)
    if not arr.size:
        return {"median": None, "q25": None, "q75": None, "iqr": None, "finite": 0, "n": len(values)}
    q25, med, q75 = (float(v) for v in np.percentile(arr, [25, 50, 75]))
    return {"median": med, "q25": q25, "q75": q75, "iqr": q75 - q25, "finite": int(arr.size), "n": len(values)}


def _block(summaries: list[dict]) -> dict:
    out = {key: _distribution([s.get(key) for s in summaries]) for key in DISTRIBUTIONS}

    rates = {}
    for flag in FLAGS:
        values = [s.get("flags", {}).get(flag) for s in summaries]
        defined = [v for v in values if v is not None]
        raised = sum(bool(v) for v in defined)
        rates[flag] = {"raised": raised, "defined": len(defined), "rate": raised / len(defined) if defined else None}
    out["flags"] = rates
    return out


def aggregate_readouts(records: list[dict], out_dir: str | Path | None = None) -> dict:
    """The results.json ``readouts`` block over score records (overall, by task, by partition)."""
    out_dir = Path(out_dir) if out_dir is not None else None
    pairs = [(r, _record_summary(r, out_dir)) for r in records]
    have = [(r, s) for r, s in pairs if s is not None]

    block = {"n": len(have), "missing": sorted(r["id"] for r, s in pairs if s is None),
             "overall": _block([s for _, s in have]), "by_task": {}, "by_partition": {},
             "flag_thresholds": THRESHOLDS, "fit": "frame0 (disparity scale and shift fitted on frame 0 only)"}
    for key, name in (("task", "by_task"), ("partition", "by_partition")):
        for value in sorted({r.get(key, "") for r, _ in have}):
            block[name][value] = _block([s for r, s in have if r.get(key, "") == value])
    return block


def record_problem(record: dict) -> str | None:
    """Why a score record (``examples/<id>.json``, a JSON object) cannot be used: a field evaluate writes and
    the report and results.json read is absent or of another type; None when it can be."""
    for key in ("id", "task", "partition"):
        if not isinstance(record.get(key), str):
            return f"its '{key}' is {'absent' if key not in record else 'not text'}"
    metrics = record.get("metrics")
    if not isinstance(metrics, dict):
        return f"its 'metrics' is {'absent' if metrics is None else 'not a JSON object'}"
    bad = [m for m, v in metrics.items()
           if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)))]
    if bad:
        return f"its metric '{bad[0]}' is not a number or null"
    if not isinstance(record.get("skipped", {}), dict):
        return "its 'skipped' is not a JSON object"
    return None


def rewrite_hint(run_dir: Path, path: Path) -> str:
    """What to do about a damaged run-level file of a run folder (results.json, run.json): evaluate with the same
    --out writes it again from the kept examples (a folder in its place must be moved aside first)."""
    aside = f"move the folder {path} aside, then " if path.is_dir() else ""
    return (f"{aside}rerun `rigidbench evaluate` with --out {run_dir}: it keeps every scored example and writes "
            f"{path.name} again")


def _run_results(folder: RunFolder) -> dict:
    """results.json of a run folder ({} when there is none); a damaged one is a UserError naming it and what to
    do (its readouts block is what the command prints)."""
    rewrite = rewrite_hint(folder.path, folder.results)
    try:
        results = load_json(folder.results, expect=dict)
    except FileNotFoundError:
        return {}
    except DamagedJSON as exc:
        raise UserError(f"{exc}; {rewrite}") from None
    block = results.get("readouts")
    if block is not None and not (isinstance(block, dict) and isinstance(block.get("overall"), dict)):
        raise UserError(f"{folder.results}: its 'readouts' is not a readouts block; {rewrite}")
    return results


def load_run_readouts(run_dir: str | Path) -> tuple[str, dict, list[dict]]:
    """(model, readouts block, per-example readout files) of a run folder; the block is recomputed from the
    per-example files when results.json has none (a run scored before readouts existed). The block's
    ``unreadable`` gives each scored example whose readouts file is missing or damaged, and why: it is left
    out of the per-example files (a warning names each damaged file). With several samples per example there is
    one file per sample, its ``sample`` index set."""
    folder = RunFolder(run_dir)
    results = _run_results(folder)
    failed = results.get("failed") if isinstance(results.get("failed"), dict) else {}
    # examples/<id>.json (and each sample's <id>.s<k>.json) of the examples scored; every sample is one generation
    scored = {p.stem for p in folder.records() if split_sample_item(p.stem)[0] not in failed}
    with_file = {p.name[:-len(READOUTS_SUFFIX)] for p in folder.examples_dir.glob(f"*{READOUTS_SUFFIX}")}
    examples, unreadable = [], {}
    for sample_id in sorted(scored | with_file):
        path = folder.readouts(sample_id)
        doc = read_example_readouts(path)
        if doc is not None:
            examples.append({**doc, "sample": doc.get("sample", split_sample_item(sample_id)[1])})
        else:
            unreadable[sample_id] = f"{path.relative_to(folder.path)} " + ("damaged" if path.exists() or
                                                                          path.is_symlink() else "missing")
    block = results.get("readouts")
    if block is None:
        records = [{"id": e["id"], "task": e.get("task", ""), "partition": e.get("partition", ""),
                    "readouts": summary(e["readouts"])} for e in examples]
        block = aggregate_readouts(records)
    return str(results.get("model") or folder.path.name), {**block, "unreadable": unreadable}, examples


def _fmt(d: dict) -> str:
    if not d or d.get("median") is None:
        return "-"
    return f"{d['median']:.3g} [{d['q25']:.3g}, {d['q75']:.3g}] ({d['finite']}/{d['n']})"


def format_block(model: str, block: dict) -> list[str]:
    """Lines that print one run's readouts: distributions overall and per task, then flag rates."""
    unreadable = block.get("unreadable") or {}
    lines = [f"{model}: readouts of {block.get('n', 0)} examples (median [q25, q75] (finite/n)); "
             f"world fit: {block.get('fit', 'frame0')}"
             + (f"; {len(unreadable)} example(s) without a readable readouts file, left out of the per-example "
                "values" if unreadable else "")]
    header = f"  {'':<28}{'speed s':<28}{'gravity g m/s2':<28}{'g s^-2':<28}{'restitution e':<28}"
    lines.append(header)
    rows = [("overall", block["overall"])] + [(f"task {k}", v) for k, v in block.get("by_task", {}).items()] + \
           [(f"partition {k}", v) for k, v in block.get("by_partition", {}).items()]
    for label, b in rows:
        lines.append(f"  {label:<28}{_fmt(b.get('speed')):<28}{_fmt(b.get('gravity')):<28}"
                     f"{_fmt(b.get('gravity_per_speed2')):<28}{_fmt(b.get('restitution')):<28}")
    flags = block["overall"].get("flags", {})
    lines.append("  flags (raised/defined): " + ", ".join(
        f"{f} {v['raised']}/{v['defined']}" for f, v in flags.items()))
    if block.get("missing"):
        lines.append(f"  no readouts for {len(block['missing'])} examples (scored before readouts existed): "
                     f"rerun evaluate to add them")
    if unreadable:
        lines.append(f"  left out, {len(unreadable)} example(s): " + "; ".join(unreadable.values())
                     + f"; {RESCORE.format('them')}")
    return lines


def one_line(model: str, block: dict) -> str:
    """One line per model for the demo table: median s, g, g s^-2 and the flags raised."""
    o = block["overall"]

    def med(key):
        v = o.get(key, {}).get("median")
        return "n/a" if v is None else f"{v:.3g}"

    flags = [f"{f} {v['raised']}/{v['defined']}" for f, v in o.get("flags", {}).items() if v["raised"]]
    return (f"{model}: s^ {med('speed')}, g^ {med('gravity')} m/s^2 (g^ s^-2 {med('gravity_per_speed2')}), "
            f"e^ {med('restitution')}; flags: {', '.join(flags) if flags else 'none'}")


