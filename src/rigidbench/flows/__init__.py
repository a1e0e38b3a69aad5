"""Several stages in a row, not stages themselves: ``demo`` (render one example per task, predict with the
reference and failure modes, evaluate, report: ``make demo``) and ``audit`` (several video models over one
reference split: predict, preflight, evaluate each, then one report)."""
