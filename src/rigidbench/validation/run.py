"""``rigidbench validate-metrics``: run the controlled perturbations and the per-metric response curves
and write the table (CSV, Markdown), a summary (JSON) and the figure (PNG, PDF)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Callable

import numpy as np

from ..atomic import write_text
from ..groundtruth.bundle import Sample, bundle_dirs, refuse_imported, resolve_split_dir
from ..metrics import METRICS
from ..perception.features import FeatureNets, load_feature_nets
from ..predictors import PREDICTORS
from .background import MOTIONS, motion_sweep
from .curves import RENDERED_MODES, curve_plan, mode_sweep
from .identity import CHANGES, collect_patches, swap_vs_gamma
from .output import (Row, curve_rows, display, mean_se, select, skipped_rows, write_csv, write_figure,
                     write_markdown)
from .ray import DIRECTIONS, ray_sweep, scene_from_sample, slope_through_origin
from .readouts import readout_rows, readout_summary_lines, write_readout_csv, write_readout_figure

log = logging.getLogger(__name__)

PREFERRED_TASKS = ("free_fall", "ramp_collision")  # the paper's ATE-3D examples
MAX_OFFSET_M = 0.5
MAX_BG_DISPLACEMENT_PX = 40.0
TABLE_STEM = "metric_validation"


def choose_examples(data_dir: Path, n_examples: int) -> list:
    """Up to n_examples reference Samples from data_dir, split evenly between free fall and ramp
    collision where the data has them, the rest filled from other tasks in id order."""
    samples = [Sample(p) for p in bundle_dirs(resolve_split_dir(data_dir))]
    if not samples:
        raise ValueError(f"{data_dir}: no rendered examples; render some with "
                         "`rigidbench render --split eval --quality preview --limit 10 --data ...`")
    by_task = {task: [s for s in samples if s.task == task] for task in PREFERRED_TASKS}
    chosen: list = []
    quota = [n_examples - n_examples // 2, n_examples // 2]
    for task, want in zip(PREFERRED_TASKS, quota):
        chosen += by_task[task][:want]
    for task in PREFERRED_TASKS:  # one preferred task short: the other fills in
        chosen += [s for s in by_task[task] if s not in chosen][:n_examples - len(chosen)]
    chosen += [s for s in samples if s not in chosen][:n_examples - len(chosen)]
    return sorted(chosen, key=lambda s: s.sample_id)


def ray_rows(samples: list, n_levels: int) -> tuple[list[Row], dict[str, float]]:
    """ATE-3D / 2D ATE / IoU along vs across the viewing ray, offsets 0..0.5 m."""
    offsets = np.linspace(0.0, MAX_OFFSET_M, n_levels)
    sweep = ray_sweep([scene_from_sample(s) for s in samples], offsets)
    rows = [r for d in DIRECTIONS for m in ("ate3d", "ate", "iou")
            for r in curve_rows("ate3d_ray", m, d, "", offsets, "m", sweep[f"{d}/{m}"])]
    mean = {k: np.nanmean(v, axis=1) for k, v in sweep.items()}
    numbers = {"ate3d_slope_along_per_m": slope_through_origin(offsets, mean["along/ate3d"]),
               "ate3d_slope_across_per_m": slope_through_origin(offsets, mean["across/ate3d"]),
               "ate_max_along": float(np.nanmax(np.abs(mean["along/ate"]))),
               "ate_slope_across_per_m": slope_through_origin(offsets, mean["across/ate"])}
    numbers["ate3d_slope_ratio_along_over_across"] = (numbers["ate3d_slope_along_per_m"]
                                                      / numbers["ate3d_slope_across_per_m"])
    return rows, numbers


def background_rows(n_levels: int, trials: int, seed: int) -> tuple[list[Row], dict[str, float]]:
    """BGDrift and raw displacement under translation vs jitter, 0..40 px."""
    magnitudes = np.linspace(0.0, MAX_BG_DISPLACEMENT_PX, n_levels)
    sweep = motion_sweep(magnitudes, trials, seed)
    rows = [r for c in MOTIONS for m in ("bgdrift", "displacement")
            for r in curve_rows("bgdrift_motion", m, c, "", magnitudes, "px", sweep[f"{c}/{m}"])]
    numbers = {f"bgdrift_{c}_at_{MAX_BG_DISPLACEMENT_PX:g}px": float(np.nanmean(sweep[f"{c}/bgdrift"][-1]))
               for c in MOTIONS}
    return rows, numbers


def identity_rows(samples: list, n_levels: int, trials: int, n_patches: int, seed: int,
                  feature_fn: Callable | None, skip_reason: str) -> tuple[list[Row], dict[str, float], str]:
    """IdDrift (when feature_fn is given) and pixel L2 under swap vs gamma, q = 0..1."""
    severities = np.linspace(0.0, 1.0, n_levels)
    patches, donors, note = collect_patches(samples, n_patches, np.random.default_rng(seed))
    sweep = swap_vs_gamma(patches, donors, severities, trials, seed, feature_fn)
    rows: list[Row] = []
    numbers: dict[str, float] = {"patches": float(len(patches))}
    for metric in ("iddrift", "pixel_l2"):
        for change in CHANGES:
            key = f"{change}/{metric}"
            if key in sweep:
                rows += curve_rows("iddrift_swap", metric, change, "", severities, "q", sweep[key], note)
            else:
                rows += skipped_rows("iddrift_swap", metric, change, "", severities, "q", skip_reason)
        if f"swap/{metric}" in sweep:
            rise = {c: float(np.nanmean(sweep[f"{c}/{metric}"][-1]) - np.nanmean(sweep[f"{c}/{metric}"][0]))
                    for c in CHANGES}
            numbers[f"{metric}_rise_swap"] = rise["swap"]
            numbers[f"{metric}_rise_gamma"] = rise["gamma"]
            numbers[f"{metric}_swap_over_gamma"] = rise["swap"] / rise["gamma"] if rise["gamma"] else float("nan")
    return rows, numbers, note


def curve_section(samples: list, n_levels: int, nets, with_rendered: bool, progress: bool
                  ) -> tuple[list[Row], list[dict], dict[str, str]]:
    """One curve per metric (and the control curves) from the failure-mode suite with gt perception."""
    severities = np.linspace(0.0, 1.0, n_levels)
    plan = curve_plan(set(PREDICTORS), with_rendered)
    skipped = {m: nets.skipped.get(m, "its feature network was not given")
               for m, net in (("lpips", nets.lpips), ("iddrift", nets.identity)) if net is None}
    # A mode only needed for skipped measurements is not run (the rendered ones take minutes).
    modes = list(dict.fromkeys(mode for metric, mode, _ in plan if metric not in skipped))
    sweep, failures = mode_sweep(samples, modes, severities, nets, progress)
    rows: list[Row] = []
    curves: list[dict] = []
    planned = {metric for metric, _, _ in plan}
    for metric, mode, role in plan:
        note = "" if mode not in RENDERED_MODES else "re-rendered with Blender"
        if metric in skipped:
            reason = skipped[metric]
            rows += skipped_rows("metric_curve", metric, role, mode, severities, "severity", reason)
            curves.append({"metric": metric, "mode": mode, "role": role, "note": f"skipped: {reason}"})
            continue
        if mode in failures:
            note = (note + "; " if note else "") + f"failed on some examples: {failures[mode]}"
        rows += curve_rows("metric_curve", metric, role, mode, severities, "severity", sweep[mode][metric], note)
        curves.append({"metric": metric, "mode": mode, "role": role, "note": note})
    for metric in sorted(set(METRICS) - planned):
        skipped[metric] = "no usable failure mode registered"
    all_modes = [Row("failure_mode", metric, "", mode, float(s), "severity", *mean_se(sweep[mode][metric][i]))
                 for mode in modes for metric in sweep[mode] for i, s in enumerate(severities)]
    return rows + all_modes, curves, skipped


def curve_summary(rows: list[Row]) -> list[str]:
    """One line per main curve: value at severity 0 and at the highest severity."""
    lines = []
    for metric in METRICS:
        mine = select(rows, experiment="metric_curve", metric=metric, condition="main")
        finite = [r for r in mine if r.n > 0]
        if len(finite) >= 2:
            lines.append(f"{display(metric)} under {finite[0].mode}: {finite[0].mean:.4g} at severity "
                         f"{finite[0].severity:g} -> {finite[-1].mean:.4g} at {finite[-1].severity:g}")
    return lines


def validate_metrics(data_dir: str | Path, out_dir: str | Path, *, examples: int = 10, severities: int = 6,
                     seed: int = 0, with_rendered: bool = False, nets=None, feature_fn: Callable | None = None,
                     trials: int = 20, bg_trials: int = 10, n_patches: int = 10, progress: bool = True) -> Path:
    """Run the metric validation on up to `examples` reference examples of data_dir with `severities`
    levels per sweep; `nets` defaults to perception.features.load_feature_nets(), `feature_fn` (B,3,224,224) ->
    (B,D) replaces its identity network. Writes metric_validation.{csv,md,png,pdf} and summary.json
    into out_dir and returns out_dir."""
    if severities < 2:
        raise ValueError(f"need at least 2 severity levels (0 and the strongest), got {severities}")
    data_dir, out_dir = Path(data_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    samples = choose_examples(data_dir, examples)
    if with_rendered:
        refuse_imported([s.path for s in samples], "validate-metrics --with-rendered re-renders the scene")
    log.info("validating metrics on %d examples: %s", len(samples),
             ", ".join(f"{s.sample_id} ({s.task})" for s in samples))
    if nets is None:
        nets = load_feature_nets()
    if feature_fn is not None:
        nets = FeatureNets(lpips=nets.lpips, identity=feature_fn,
                           skipped={k: v for k, v in nets.skipped.items() if k != "iddrift"}, device=nets.device)
    id_reason = nets.skipped.get("iddrift", "no identity feature network was given")

    log.info("[1/5] ATE-3D along vs across the viewing ray")
    rows, numbers = ray_rows(samples, severities)
    log.info("[2/5] BGDrift: coherent translation vs independent jitter")
    bg, bg_numbers = background_rows(severities, bg_trials, seed)
    log.info("[3/5] IdDrift: identity swap vs gamma%s", "" if nets.identity else f" (IdDrift skipped: {id_reason})")
    idr, id_numbers, donor_note = identity_rows(samples, severities, trials, n_patches, seed, nets.identity, id_reason)
    log.info("[4/5] one response curve per metric (failure modes, gt perception)")
    curve, curves, skipped = curve_section(samples, severities, nets, with_rendered, progress)
    log.info("[5/5] physics readouts under the failure modes that set them (gt perception)")
    readouts, readout_failures = readout_rows(samples, np.linspace(0.0, 1.0, severities), with_rendered, nets,
                                              progress)
    write_readout_csv(readouts, out_dir / "readout_curves.csv")
    figure = write_readout_figure(readouts, out_dir / "readout_curves.png")
    rows = rows + bg + idr + curve
    if nets.identity is None:
        skipped.setdefault("iddrift", id_reason)
    numbers.update(bg_numbers)
    numbers.update(id_numbers)
    summary = {"examples": [f"{s.sample_id} ({s.task})" for s in samples], "severities": severities,
               "seed": seed, "with_rendered": with_rendered, "numbers": numbers, "curves": curves,
               "skipped": skipped, "identity_donors": donor_note,
               "lines": summary_lines(numbers, skipped, donor_note) + curve_summary(rows)
               + readout_summary_lines(readouts),
               "readouts": {"rows": len(readouts), "failures": readout_failures,
                            "figure": figure.name if figure is not None else None}}
    write_csv(rows, out_dir / f"{TABLE_STEM}.csv")
    write_markdown(rows, summary, out_dir / f"{TABLE_STEM}.md")
    write_figure(rows, skipped, out_dir / TABLE_STEM)
    write_text(out_dir / "summary.json", json.dumps(_json_safe(summary), indent=2))
    return out_dir


def summary_lines(numbers: dict[str, float], skipped: dict[str, str], donor_note: str) -> list[str]:
    """Human-readable headline numbers of the three controlled perturbations."""
    n = numbers
    lines = [f"ATE-3D slope along the ray {n['ate3d_slope_along_per_m']:.4g} per m, across it "
             f"{n['ate3d_slope_across_per_m']:.4g} per m (ratio {n['ate3d_slope_ratio_along_over_across']:.3f}); "
             f"2D ATE along the ray at most {n['ate_max_along']:.2g}, across it "
             f"{n['ate_slope_across_per_m']:.4g} per m",
             f"BGDrift at {MAX_BG_DISPLACEMENT_PX:g} px mean displacement: translation "
             f"{n[f'bgdrift_translation_at_{MAX_BG_DISPLACEMENT_PX:g}px']:.4g}, jitter "
             f"{n[f'bgdrift_jitter_at_{MAX_BG_DISPLACEMENT_PX:g}px']:.4g}"]
    if "iddrift_swap_over_gamma" in n:
        lines.append(f"IdDrift rise at q = 1: swap {n['iddrift_rise_swap']:.4g}, gamma {n['iddrift_rise_gamma']:.4g} "
                     f"(ratio {n['iddrift_swap_over_gamma']:.3g}); pixel L2 ratio {n['pixel_l2_swap_over_gamma']:.3g} "
                     f"({int(n['patches'])} patches; {donor_note})")
    else:
        lines.append(f"IdDrift swap vs gamma skipped ({skipped.get('iddrift', 'no feature network')}); pixel L2 rise "
                     f"at q = 1: swap {n['pixel_l2_rise_swap']:.4g}, gamma {n['pixel_l2_rise_gamma']:.4g} (ratio "
                     f"{n['pixel_l2_swap_over_gamma']:.3g}; {int(n['patches'])} patches; {donor_note})")
    return lines


def _json_safe(x):
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


