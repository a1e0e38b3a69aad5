"""Scoring a model's predictions against the reference bundles (paper, section 3.4 and appendix B); the
``evaluate`` stage that runs it over a folder is ``stages.evaluate``.

For every reference example the evaluator decodes ``pred_dir/<id>.<ext>``, resizes it to the
reference resolution, runs a perception backend on it (cached by content hash), aligns the video
and the perception outputs to the reference timestamps t_k = k/24, computes every registered
measurement and writes

- ``out/examples/<id>.json``: the scalars (null for non-finite), task, partition, input hash;
- ``out/examples/<id>.npz``: the per-frame arrays of each measurement;
- ``out/results.json``: mean, population standard deviation and finite count per metric,
  overall, per task and per partition, and whether the result is official;
- ``out/run.json``: model, data and prediction hashes, versions, backend, settings, timings,
  skipped measurements and failed examples with reasons.

A rerun skips examples whose inputs (video, world state, reference, backend, settings) are
unchanged and recomputes the others; an interrupted run resumes. One bad example is recorded
with its reason and never stops the others; a bug (any other exception) stops the run.

Modules: ``scoring`` (one example -> metrics), ``reference_side`` (what an example's samples share of its
reference), ``keys`` (input hashes), ``protocol`` (decoding and the JPEG round trip), ``aggregation``
(results.json numbers) and ``provenance`` (run.json); the loop is ``stages.evaluate``.
"""

from .aggregation import EVAL_SIZE, aggregate, summarise, why_not_official
from .keys import SCORE_VERSION, file_hash, reference_hash
from .scoring import metric_inputs, score_example, score_inputs, tracked_points_world

__all__ = ["EVAL_SIZE", "SCORE_VERSION", "aggregate", "file_hash", "metric_inputs", "reference_hash", "score_example",
           "score_inputs", "summarise", "tracked_points_world", "why_not_official"]
