"""Uncertainty and paired comparisons over per-example scores (paper section 4 and appendix C).

Numpy only at import (scipy inside the power functions). All functions are seeded with
``numpy.random.default_rng(seed)`` and are deterministic: the same inputs and seed give the same
intervals. Several samples per example: ``samples`` and ``power``, described in docs/statistics.md.
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
from rigidbench.stats.power import (
    PairedVarianceComponents,
    PowerRow,
    examples_needed,
    minimum_detectable_difference,
    paired_test_power,
    paired_variance_components,
    power_table,
)
from rigidbench.stats.samples import (
    BestOfK,
    SampleSummary,
    hierarchical_bootstrap_ci,
    paired_difference_matrix_samples,
    paired_difference_samples,
    per_example_means,
    probability_of_improvement_matrix_samples,
    probability_of_improvement_samples,
    summarize_samples,
)

__all__ = [
    "BestOfK",
    "PairedVarianceComponents",
    "PairwiseMatrix",
    "PowerRow",
    "SampleSummary",
    "bootstrap_ci",
    "correlation_across_models",
    "examples_needed",
    "hierarchical_bootstrap_ci",
    "improvement_indicators",
    "minimum_detectable_difference",
    "paired_difference",
    "paired_difference_matrix",
    "paired_difference_matrix_samples",
    "paired_difference_samples",
    "paired_test_power",
    "paired_variance_components",
    "per_example_means",
    "power_table",
    "probability_of_improvement",
    "probability_of_improvement_matrix",
    "probability_of_improvement_matrix_samples",
    "probability_of_improvement_samples",
    "summarize_samples",
]
