"""``rigidbench envelope``: the physical envelope of a reference set, made by driver stages.

For every selected example with a scene spec, N physical twins (``predictors.twins``: the reference
re-simulated with its initial state and materials drawn within ``configs/envelope.yaml`` x scale) are
predicted into ``ENV/predictions/`` as N samples of the ``twin`` predictor (``predict --samples N``; sample
k seeded by ``sample_seed``) and scored against the reference into ``ENV/run/`` with ``gt`` perception,
under the same protocol and code as any model (``evaluate``). ``ENV/envelope.json`` then says what was made:
the configuration and scale, whether the twins were path traced, the set's identity, and per example
"ok" or "no envelope" with the reason (no scene spec and no re-simulation that reproduces the published
trajectory, or too few twins scored). ``evaluate --envelope ENV`` scores a model against it
(``evaluation.envelope``).

Both stages are the driver's: a rerun makes only what is missing or changed, a killed run resumes, and
``--ids``/``--limit``/``--shard`` choose examples as everywhere. A run with ``--shard`` makes and scores its part of
the twins but writes no envelope.json (run once more without it). A run on some examples keeps the other examples
of an envelope.json made with the same settings (twins, scale, seed, configuration, geometry-only) and replaces one
made with others; fewer twins than an existing envelope holds is refused (the extra twins' scores would stay in
``ENV/run``).

Imported (published) examples ship no scene spec. Each is rebuilt from its published metadata and
re-simulated at zero perturbation (``datasets.resimulate``); one that reproduces the published trajectory
within the stated tolerance gets geometry-only twins of the rebuilt spec (its RGB cannot be re-rendered:
our meshes stand in for the published assets); one that does not gets "no envelope" with the measured drift.
Twins of an imported example are scored against the PUBLISHED reference, so their scores include the
reconstruction's own error: envelope.json records per such example its "reconstruction", the re-simulation's
error against the published trajectory. Every example, imported or rendered, also gets one twin at scale 0
(``ENV/reconstruction/``, predicted and scored by the same two stages): its scores are the example's "floor", the
value each measurement gives a perfect prediction, below which the envelope's worse-side bound never goes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from ..context import RunContext
from ..datasets.resimulate import resimulate_published
from ..driver import RunOptions, Selection, StageReport
from ..errors import UserError
from ..evaluation.envelope import ENVELOPE_FILE, RUN_DIR, padded, read_envelope
from ..executors import Shard
from ..folders import SPEC_FILE, RunFolder, sample_item
from ..groundtruth.bundle import bundle_dirs, is_imported, resolve_split_dir, set_identity
from ..jsonio import read_json, write_json
from ..perception.features import FeatureNets
from ..predictors import PredictContext
from ..scene_spec.envelope import load_envelope
from ..stages.evaluate import evaluate
from ..stages.predict import predict
from ..stats.envelope import twin_quantiles, width_table

log = logging.getLogger(__name__)

PREDICTIONS_DIR = "predictions"
RESIM_DIR = "resimulation"  # the rebuilt specs of imported examples and their re-simulation check
RECONSTRUCTION_DIR = "reconstruction"  # every example: a twin at scale 0 and its scores (the floor)
DEFAULT_TWINS = 8
MIN_SCORED_TWINS = 2  # fewer twins scored: the example has no envelope (``stats.envelope.MIN_TWINS``)
#: What must agree for a run on some examples to keep the other examples of an existing envelope.json.
SAME_ENVELOPE = ("config", "twins", "geometry_only", "scale", "seed")
#: The re-simulation errors an imported example's "reconstruction" entry repeats (``datasets.resimulate.Drift``).
DRIFT_FIELDS = ("window_frames", "max_m", "max_px", "max_deg", "clip_max_m", "clip_max_px", "worst_actor")


@dataclass(frozen=True)
class EnvelopeFacts:
    """What ``make_envelope`` made: the stages' reports (the twins predicted and scored; for imported examples
    the scale-0 twin predicted and scored, None when there were none), envelope.json's per-example statuses of
    this run's examples, the width table per task (median over examples of q95 - q05 per measurement), the
    re-simulation table of imported examples (None when there were none) and whether envelope.json was written
    (not with a shard)."""

    predicted: StageReport | None
    scored: StageReport | None
    examples: dict[str, dict[str, Any]]
    widths: dict[str, dict[str, float | None]]
    resimulation: dict | None
    reconstructed: StageReport | None = None
    floor_scored: StageReport | None = None
    written: bool = True

    @property
    def reports(self) -> list[StageReport]:
        """The stage reports of this run, in the order they ran."""
        return [r for r in (self.predicted, self.scored, self.reconstructed, self.floor_scored) if r is not None]


def _selected_examples(split_dir: Path, selection: Selection) -> list[str]:
    """The examples the selection chooses from the split (the driver's rule; unknown ids fail here, early)."""
    whole = replace(selection, shard=Shard())  # a shard splits the stages' items (twins), not the examples
    return whole.apply([p.name for p in bundle_dirs(split_dir)], str(split_dir))


def _imported_check(split_dir: Path, ids: list[str], env_dir: Path, ctx: RunContext) -> tuple[dict, dict | None]:
    """Re-simulate the imported examples without a scene spec (``datasets.resimulate``): {id: status entry,
    with its re-simulation error where it was re-simulated} for each, and the table as JSON (None when there
    are none)."""
    imported = [i for i in ids if not (split_dir / i / SPEC_FILE).is_file() and is_imported(split_dir / i)]
    if not imported:
        return {}, None
    table = resimulate_published(split_dir, ctx.registry, ids=imported, out_dir=env_dir / RESIM_DIR)
    statuses = {}
    for row in table.rows:
        entry = {"status": row.envelope, "reason": row.reason, "imported": True}
        if row.drift is not None:
            drift = row.to_dict()["drift"]
            entry["reconstruction"] = {"resimulation": {k: drift[k] for k in DRIFT_FIELDS}}
        statuses[row.sample_id] = entry
    return statuses, table.to_dict()


def _previous(env_dir: Path, doc: dict) -> dict[str, dict]:
    """The examples of an existing envelope.json made with the same settings as ``doc`` (kept beside this run's),
    or {}; a UserError when it holds more twins per example than ``doc`` asks for."""
    old = read_json(env_dir / ENVELOPE_FILE, "it is written again", expect=dict)
    if not old:
        return {}
    if isinstance(old.get("twins"), int) and old["twins"] > doc["twins"]:
        raise UserError(f"{env_dir / ENVELOPE_FILE}: made with {old['twins']} twins per example; --twins "
                        f"{doc['twins']} would leave the other twins' scores in {env_dir / RUN_DIR}. Pass --twins "
                        f"{old['twins']} (or more), or make the envelope in a new --out folder")
    if any(old.get(k) != doc[k] for k in SAME_ENVELOPE) or not isinstance(old.get("examples"), dict):
        return {}
    return old["examples"]


def _done(report: StageReport | None, example: str, n: int) -> int:
    """How many of the ``n`` samples of ``example`` the stage has committed (ran now or up to date)."""
    if report is None:
        return 0
    done = set(report.succeeded)
    return sum(sample_item(example, k) in done for k in range(n))


def _zero_twin_scores(run_dir: Path, example: str) -> dict[str, float | None] | None:
    """The measurements of the scale-0 twin of ``example`` scored in ``run_dir`` (None when it was not scored)."""
    record = read_json(RunFolder(run_dir).examples_dir / f"{example}.json", "its reconstruction floor is not shown",
                       expect=dict)
    metrics = (record or {}).get("metrics")
    return {m: v for m, v in metrics.items() if v is not None} if isinstance(metrics, dict) else None


def _twins(split_dir: Path, folder: Path, ids: list[str], options: dict, samples: int, seed: int, run: RunOptions,
           ctx: RunContext) -> tuple[StageReport | None, StageReport | None]:
    """Predict ``samples`` twins (predictor options ``options``) of each example ``ids`` into
    ``folder/predictions`` and score them against the reference with gt perception into ``folder/run``; the two
    stages' reports (None, None when there are no examples)."""
    if not ids:
        return None, None
    chosen = replace(run, selection=replace(run.selection, ids=tuple(ids), limit=None))
    twin_ctx = PredictContext(ctx, severity=1.0, seed=seed, options=options)
    predicted = predict("twin", split_dir, folder / PREDICTIONS_DIR, twin_ctx, run=chosen, samples=samples)
    nets = FeatureNets(skipped={m: "geometry-only twins: no RGB" for m in ("lpips", "iddrift")}) \
        if options["geometry_only"] else None
    scored = evaluate(folder / PREDICTIONS_DIR, split_dir, folder / RUN_DIR, perception="gt", run=chosen, nets=nets,
                      model="twins")
    return predicted, scored


def make_envelope(data: str | Path, out_dir: str | Path, *, twins: int = DEFAULT_TWINS, scale: float = 1.0,
                  geometry_only: bool = True, config: str | Path | None = None, seed: int = 0,
                  run: RunOptions = RunOptions(), ctx: RunContext | None = None) -> EnvelopeFacts:
    """Make (or bring up to date) the envelope folder ``out_dir`` of the reference split ``data``; see the
    module docstring. ``twins``: twins per example (>= 2); ``scale``: multiplies every deviation of the
    configuration (``config``, default the packaged ``envelope.yaml``); ``geometry_only``: twins from the
    simulator and the data passes only (the geometric measurements), else path traced like the reference
    (every measurement); ``seed``: the base seed of the twins' draws."""
    if int(twins) < MIN_SCORED_TWINS:
        raise UserError(f"--twins {twins}: an envelope needs at least {MIN_SCORED_TWINS} twins per example")
    if not scale >= 0:
        raise UserError(f"--scale {scale}: must be a number >= 0 (1: the configured envelope)")
    ctx = ctx or RunContext()
    envelope_config = load_envelope(config, ctx.config_dirs)  # a bad file fails here, before anything runs
    split_dir = resolve_split_dir(data)
    env_dir = Path(out_dir)
    doc: dict[str, Any] = {"config": envelope_config.to_dict(), "twins": int(twins),
                           "geometry_only": bool(geometry_only), "scale": float(scale), "seed": int(seed)}
    previous = _previous(env_dir, doc)
    ids = _selected_examples(split_dir, run.selection)
    statuses, resim = _imported_check(split_dir, ids, env_dir, ctx)
    with_spec = [i for i in ids if (split_dir / i / SPEC_FILE).is_file()]
    rebuilt = [i for i, s in statuses.items() if s["status"] == "ok"]
    if not geometry_only:
        for i in rebuilt:
            statuses[i].update(status="no envelope", reason="imported: its twins are geometry-only (its RGB cannot be "
                                                            "re-rendered); make the envelope without --full")
        rebuilt = []
    for i in ids:
        if i not in statuses and i not in with_spec:
            statuses[i] = {"status": "no envelope", "reason": "no scene spec (not rendered with `rigidbench render`) "
                                                            "and not an imported example"}
    options: dict[str, Any] = {"scale": float(scale), "geometry_only": bool(geometry_only)}
    if config is not None:
        options["envelope"] = str(Path(config).resolve())
    if rebuilt:
        options["spec_dir"] = str((env_dir / RESIM_DIR).resolve())
    targets = [i for i in ids if i in with_spec or i in rebuilt]
    predicted, scored = _twins(split_dir, env_dir, targets, options, int(twins), int(seed), run, ctx)
    # the floor: one twin at scale 0 of each example (the reference itself re-made; for an imported example, its
    # reconstruction), scored like the others: what each measurement gives a perfect prediction
    reconstructed, floor_scored = _twins(split_dir, env_dir / RECONSTRUCTION_DIR, targets, {**options, "scale": 0.0},
                                         1, int(seed), run, ctx)
    for i in targets:
        done = _done(scored, i, int(twins))
        entry = statuses.setdefault(i, {})
        if done >= MIN_SCORED_TWINS:
            entry.update(status="ok", reason=None, twins=done)
        else:
            entry.update(status="no envelope", twins=done,
                         reason=f"only {done} of {twins} twins were predicted and scored (see "
                                f"{env_dir / PREDICTIONS_DIR / 'generation.json'} and "
                                f"{env_dir / RUN_DIR / 'results.json'})")
    for i in targets:
        statuses[i]["floor"] = _zero_twin_scores(env_dir / RECONSTRUCTION_DIR / RUN_DIR, i)
    for i in rebuilt:
        statuses[i]["reconstruction"]["zero_twin"] = statuses[i]["floor"]
    examples = {**previous, **statuses}
    doc["dataset"] = set_identity([split_dir / i for i in examples if (split_dir / i).is_dir()])
    doc["examples"] = dict(sorted(examples.items()))
    if resim is not None:
        doc["resimulation"] = resim
    if run.selection.shard.count > 1:
        log.info("a shard: envelope.json is written by a run without --shard")
        return EnvelopeFacts(predicted, scored, statuses, {}, resim, reconstructed, floor_scored, written=False)
    RunFolder(env_dir / RUN_DIR).examples_dir.mkdir(parents=True, exist_ok=True)  # (no twin scored: still readable)
    write_json(env_dir / ENVELOPE_FILE, doc, indent=2, allow_nan=False)
    return EnvelopeFacts(predicted, scored, dict(sorted(statuses.items())), envelope_widths(env_dir), resim,
                         reconstructed, floor_scored)


def envelope_widths(env_dir: Path) -> dict[str, dict[str, float | None]]:
    """Per task, the median over its examples of the twins' q95 - q05, per measurement (``stats.envelope``)."""
    envelope = read_envelope(env_dir)
    ids = sorted(envelope.twins)
    if not ids:
        return {}
    bands = {}
    for metric in envelope.metrics:
        q05, _, q95, _ = twin_quantiles(padded([envelope.twins[i][metric] for i in ids]))
        bands[metric] = (q05, q95)
    return width_table(bands, [envelope.tasks.get(i, "?") for i in ids])
