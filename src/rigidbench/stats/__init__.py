"""Uncertainty and paired comparisons over per-example scores (paper section 4 and appendix C).

Numpy only at import. All functions are seeded with ``numpy.random.default_rng(seed)`` and are
deterministic: the same inputs and seed give the same intervals.
"""

from rigidbench.stats.bootstrap import bootstrap_ci, paired_difference
from rigidbench.stats.correlation import correlation_across_models
from rigidbench.stats.paired import (
    PairwiseMatrix,
    improvement_indicators,
    paired_difference_matrix,
    probability_of_improvement,
    probability_of_improvement_matrix,
)

__all__ = [
    "PairwiseMatrix",
    "bootstrap_ci",
    "correlation_across_models",
    "improvement_indicators",
    "paired_difference",
    "paired_difference_matrix",
    "probability_of_improvement",
    "probability_of_improvement_matrix",
]
