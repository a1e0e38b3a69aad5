"""Readouts in a run folder: per-example records, the ``readouts`` block of results.json, and
``rigidbench readouts RUN``.

- ``out/examples/<id>.readouts.json``: every readout of the example in full (values, reasons,
  per-actor fits, flag evidence, thresholds), written by ``example_readouts`` from the evaluator;
- the example's score record gets a compact ``readouts`` entry (``summary``);
- ``results.json`` ``readouts``: per readout with a distribution (speed, gravity, g s^-2,
  restitution) the median, quartiles, finite and total counts, and per flag the number raised, the
  number where it is defined and their ratio; overall, per task and per partition (one run is one model).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from rigidbench.atomic import write_text
from rigidbench.errors import UserError
from rigidbench.folders import READOUTS_SUFFIX, RunFolder
from rigidbench.readouts import compute_readouts, context_from_sample
from rigidbench.readouts.flags import FLAGS, THRESHOLDS

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


def example_readouts(sample, inputs, scores: dict, out_dir: str | Path) -> dict:
    """Compute every readout of one evaluated example from its MetricInputs, write
    out_dir/examples/<id>.readouts.json and return the compact summary for its score record; ``scores``
    name -> MetricResult (IdDrift feeds the identity flag). ``out_dir`` is a run folder or a staging folder
    laid out like one (the evaluate stage's, committed into the run folder by the stage driver)."""
    iddrift = scores.get("iddrift")
    ctx = context_from_sample(sample, inputs, None if iddrift is None else iddrift.value)
    readouts = compute_readouts(ctx)
    path = RunFolder(out_dir).readouts(sample.sample_id)
    write_text(path, json.dumps(to_jsonable({"id": sample.sample_id, "task": sample.task,
                                             "partition": sample.partition, "readouts": readouts}), indent=1))
    return summary(readouts)


def _record_summary(record: dict, out_dir: Path | None) -> dict | None:
    if isinstance(record.get("readouts"), dict):
        return record["readouts"]
    if out_dir is not None:  # a record reused from a run before readouts: read its file if there is one
        path = RunFolder(out_dir).readouts(record["id"])
        if path.exists():
            return summary(json.loads(path.read_text())["readouts"])
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


def load_run_readouts(run_dir: str | Path) -> tuple[str, dict, list[dict]]:
    """(model, readouts block, per-example readout files) of a run folder; the block is recomputed from the
    per-example files when results.json has none (a run scored before readouts existed)."""
    folder = RunFolder(run_dir)
    results = json.loads(folder.results.read_text()) if folder.results.exists() else {}
    examples = [json.loads(p.read_text()) for p in sorted(folder.examples_dir.glob(f"*{READOUTS_SUFFIX}"))]
    block = results.get("readouts")
    if block is None:
        records = [{"id": e["id"], "task": e.get("task", ""), "partition": e.get("partition", ""),
                    "readouts": summary(e["readouts"])} for e in examples]
        block = aggregate_readouts(records)
    return results.get("model", folder.path.name), block, examples


def _fmt(d: dict) -> str:
    if not d or d.get("median") is None:
        return "-"
    return f"{d['median']:.3g} [{d['q25']:.3g}, {d['q75']:.3g}] ({d['finite']}/{d['n']})"


def format_block(model: str, block: dict) -> list[str]:
    """Lines that print one run's readouts: distributions overall and per task, then flag rates."""
    lines = [f"{model}: readouts of {block.get('n', 0)} examples (median [q25, q75] (finite/n)); "
             f"world fit: {block.get('fit', 'frame0')}"]
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


def cmd_readouts(args, ctx=None) -> int:
    """CLI: rigidbench readouts RUN [RUN ...] [--examples]: print each run's readouts."""
    for run in args.runs:
        run = Path(run)
        if not RunFolder(run).examples_dir.is_dir():
            raise UserError(f"{run}: not a run folder (no examples/); run `rigidbench evaluate` first")
        model, block, examples = load_run_readouts(run)
        for line in format_block(model, block):
            print(line)
        if getattr(args, "examples", False):
            for e in examples:
                s = summary(e["readouts"])
                raised = [k for k, v in s["flags"].items() if v]
                vals = ", ".join(f"{k} {('-' if s[k] is None else format(s[k], '.3g'))}" for k in DISTRIBUTIONS)
                print(f"    {e['id']} ({e['task']}): {vals}; flags: {', '.join(raised) or 'none'}")
    return 0
