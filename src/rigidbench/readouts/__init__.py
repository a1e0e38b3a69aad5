"""Physical readouts of a generated clip: what gravity, restitution and playback speed it implies, and
how it fails (issue 28). Beside the ten measurements, never inside them.

``READOUTS`` holds one ``ReadoutInfo`` per readout, registered like the metrics (one ``LazyRegistry``,
targets "module:attr" imported on first use): ``compute(ReadoutContext) -> dict`` with at least
``value`` (float, NaN when undefined) and ``reason`` (why it is undefined, else None), plus whatever
evidence it keeps. Adding a readout is one module with its compute function plus one
``READOUTS.add(ReadoutInfo(...))``. ``compute_readouts`` runs them all on one example; the evaluator
writes the result beside each example's scores (``readouts.records``), and ``results.json`` holds
their distributions (median and IQR) and flag rates. Fits, thresholds and failure cases: docs/physics.md.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from rigidbench.readouts.context import ReadoutContext, context_from_sample
from rigidbench.registry import LazyRegistry

__all__ = ["READOUTS", "ReadoutInfo", "ReadoutContext", "compute_readouts", "context_from_sample"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReadoutInfo:
    """Registry entry of one readout. target: "module:attr" of compute(ReadoutContext) -> dict; unit: of
    ``value``; truth: the value a physically right clip gives ("reference": the reference's own readout,
    a number, or "" when none); distribution: summarised by median and IQR in results.json."""

    name: str
    target: str
    display_name: str
    unit: str
    summary: str
    truth: str = ""
    distribution: bool = True
    aliases: tuple[str, ...] = ()

    def load(self):
        return READOUTS.load(self.name)


READOUTS: LazyRegistry[ReadoutInfo] = LazyRegistry("readout")

READOUTS.add(ReadoutInfo("world", "rigidbench.readouts.physics:readout_world", "world fit", "m",
                         "anchored world trajectories; RMS against the simulated ones (frame-0 and clip disparity fits)",
                         distribution=False))
READOUTS.add(ReadoutInfo("speed", "rigidbench.readouts.physics:readout_speed", "s\u0302", "x",
                         "playback speed s with p(t) ~ p_ref(s t + d), offset d, standard errors, error left", "1"))
READOUTS.add(ReadoutInfo("gravity", "rigidbench.readouts.physics:readout_gravity", "g\u0302", "m/s^2",
                         "parabola fit of the height over each free actor's ballistic window; also g s^-2",
                         "simulated"))
READOUTS.add(ReadoutInfo("restitution", "rigidbench.readouts.physics:readout_restitution", "e\u0302", "1",
                         "-v_after / v_before at the first contact of a free actor", "reference"))
READOUTS.add(ReadoutInfo("flags", "rigidbench.readouts.flags:readout_flags", "flags", "count",
                         "disappears, duplicates, frozen, through support/actor, identity, camera", distribution=False))


def compute_readouts(ctx: ReadoutContext, names=None) -> dict[str, dict]:
    """name -> readout record for every registered readout (or those in ``names``). A readout that raises
    an arithmetic or shape error is recorded as NaN with the error as its reason; it never stops the others."""
    out = {}
    for name in (tuple(READOUTS) if names is None else tuple(names)):
        try:
            out[name] = READOUTS.load(name)(ctx)
        except (ValueError, FloatingPointError, ZeroDivisionError, IndexError, np_linalg_error()) as exc:
            log.warning("readout %s failed: %s", name, exc)
            out[name] = {"value": math.nan, "reason": f"failed: {exc}"}
    return out


def np_linalg_error():
    import numpy as np

    return np.linalg.LinAlgError
