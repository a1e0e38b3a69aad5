"""Why a run cannot be submitted, one line per problem (empty: it can).

A submission is a run of ``rigidbench evaluate`` that a reader may put beside the paper's table:

- on a published set: the run's reference set (results.json ``dataset``) is one a dataset description names
  (name, version and MD5 of a ``configs/datasets/*.yaml``, packaged or in a ``--config`` directory), and its
  MD5 was verified when it was downloaded or imported;
- every example of that set scored: as many as the description's ``examples`` (``EVAL_SIZE``, 100, for a
  description without one), none failed, all in this run;
- under protocol ``rigidbench-v1`` with the first-frame check on and no clip shorter than the reference span;
- with neural perception (``gt`` reads the answer from the reference) and no measurement skipped (for network
  weights that were missing);
- with a complete card (``submissions.card``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

from ..datasets.describe import DatasetDescription, list_datasets
from ..errors import ConfigError
from ..evaluation.aggregation import EVAL_SIZE
from ..evaluation.protocol import DEFAULT_PROTOCOL
from .card import card_problems
from .provenance import RunFiles

PERCEPTION = "neural"


def published_set(identity: dict, config_dirs: Iterable[str | Path] = ()) -> DatasetDescription | None:
    """The dataset description whose name, version and MD5 are those of the reference set ``identity`` (a
    results.json ``dataset``), or None (a rendered set, a mix, an unknown set)."""
    if not identity or "sets" in identity or not identity.get("md5"):
        return None
    try:
        known = list_datasets(config_dirs).values()
    except ConfigError:
        return None
    md5 = str(identity.get("md5")).lower()
    return next((d for d in known if d.name == identity.get("dataset") and d.version == str(identity.get("version"))
                 and d.md5 == md5), None)


def _set_name(identity: dict) -> str:
    if "sets" in identity:
        return f"a mix of {len(identity['sets'])} reference sets"
    if identity.get("dataset") == "rendered":
        preset = f", preset {identity['preset']}" if identity.get("preset") else ""
        return f"a rendered set ({identity.get('version')}{preset})"
    return " ".join(str(identity[k]) for k in ("dataset", "version") if identity.get(k)) or "an unnamed set"


def _few(ids: list[str], n: int = 5) -> str:
    return ", ".join(ids[:n]) + (f" and {len(ids) - n} more" if len(ids) > n else "")


def run_problems(files: RunFiles, config_dirs: Iterable[str | Path] = ()) -> list[str]:
    """One line per reason the run ``files`` is not a submission (the card aside)."""
    where = str(files.path)
    results = files.results
    identity = results.get("dataset") or {}
    problems = []
    described = published_set(identity, config_dirs)
    if described is None:
        problems.append(f"{where}: not the published set: the run is on {_set_name(identity)}; score the published "
                        "set (`rigidbench download`, then `rigidbench evaluate --perception neural`)")
    elif identity.get("verified") is not True:
        problems.append(f"{where}: an unverified set: the MD5 of {_set_name(identity)} was not checked "
                        f"({identity.get('verification') or 'no record of a check'}); import its .tar.gz or parts, "
                        "or download it, to check it, then evaluate again")
    protocol = results.get("protocol") or {}
    name = protocol.get("name") if isinstance(protocol, dict) else protocol
    if name != DEFAULT_PROTOCOL:
        problems.append(f"{where}: another protocol: the run was scored under {name or 'no recorded protocol'}, not "
                        f"{DEFAULT_PROTOCOL}; evaluate again without --protocol")
    elif protocol.get("first_frame_check") is False:
        problems.append(f"{where}: another protocol: the first-frame check was turned off; evaluate again without "
                        "--no-first-frame-check")
    expected = (described.examples if described is not None and described.examples else EVAL_SIZE)
    scored = sorted(files.records)
    failed = sorted(results.get("failed") or {})
    if len(scored) < expected or failed:
        label = f"{described.name} {described.version}" if described is not None else "the published set"
        missing = f"; failed: {_few(failed)}" if failed else ""
        problems.append(f"{where}: missing examples: {len(scored)} of the {expected} examples of {label} were "
                        f"scored{missing}; evaluate every example of the set")
    short = (results.get("coverage") or {}).get("short") or []
    if short:
        problems.append(f"{where}: clips shorter than the reference span were scored (--allow-short): {_few(short)}; "
                        "generate the whole span")
    perception = results.get("perception")
    if perception != PERCEPTION:
        problems.append(f"{where}: {perception} perception: the measurements read the reference's own "
                        f"{'ground truth' if perception == 'gt' else perception + ' outputs'}, not the video; "
                        f"evaluate again with --perception {PERCEPTION}")
    per_example = ((results.get("samples") or {}).get("samples_per_example") or {}).get("max") or 1
    if per_example > 1:  # the bundle and the board hold one record per example: sample records are not carried yet
        problems.append(f"{where}: several samples per example (up to {per_example}): a submission holds one "
                        "generation per example; evaluate a predictions folder with one video per example "
                        "(<id>.mp4, no <id>.s<k>.mp4) and submit that run")
    skipped = results.get("skipped_metrics") or {}
    if skipped:
        problems.append(f"{where}: measurements skipped: " + "; ".join(f"{m} ({why})" for m, why in skipped.items())
                        + "; fetch the weights (`rigidbench weights --download`) and evaluate again")
    return problems


def submission_problems(files: RunFiles, card: dict, card_path: str, config_dirs: Iterable[str | Path] = ()
                        ) -> list[str]:
    """Every reason the run ``files`` with ``card`` cannot be submitted: the run's, then the card's."""
    return run_problems(files, config_dirs) + card_problems(card, card_path)
