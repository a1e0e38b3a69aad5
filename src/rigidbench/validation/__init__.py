"""Metric validation (``rigidbench validate-metrics``): the paper's controlled metric perturbations
(appendix "Controlled Metric Perturbations") and one failure-mode response curve per metric.

- ``ray``: ATE-3D along vs across the viewing ray (array-level perturbation of the gt world state);
- ``background``: BGDrift under coherent translation vs independent jitter (synthetic corners);
- ``identity``: IdDrift under identity swap vs gamma, with pixel L2 beside it;
- ``curves``: each metric under the failure mode meant to move it, scored with gt perception;
- ``output``: the table (CSV, Markdown) and the figure (PNG, PDF); ``run``: all of it (the command:
  ``commands.scoring``).
"""

from .run import validate_metrics

__all__ = ["validate_metrics"]
