"""Power of a paired comparison between two models with K samples per example (docs/statistics.md).

Model for one measurement: model A's sample k on example e scores ``y_A,ek = mu_A + a_e + eps_A,ek``,
likewise for B. The per-example difference of sample means over K samples of each model is

    d_e = m_A,e - m_B,e,    Var(d_e) = tau^2(K) = sigma_D^2 + (sigma_wA^2 + sigma_wB^2) / K

where sigma_D^2 (``between``) is the between-example variance of the true per-example difference
and sigma_w^2 (``within_a``, ``within_b``) each model's within-example sample variance. The test
is the paired t-test of mean(d_e) = 0 over E examples, two-sided at level alpha. Its power at a true
difference delta is, with t_c = t_{1-alpha/2, E-1},

    power = P(|T| > t_c),   T ~ noncentral t(df = E - 1, nc = delta * sqrt(E) / tau(K)).

The smallest detectable difference solves power = target for nc and returns nc * tau(K) / sqrt(E);
for large E this is (z_{1-alpha/2} + z_{power}) * tau(K) / sqrt(E), about 2.80 * tau / sqrt(E)
at alpha 0.05 and power 0.8. The examples needed for a difference delta are the smallest E >= 2
whose power reaches the target; a user then needs E * K samples per model.

scipy is imported inside the functions that need it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from rigidbench.stats.samples import check_pair, per_example_means, within_example_std


@dataclass(frozen=True)
class PairedVarianceComponents:
    """Variance components of the per-example difference of two models on one measurement.

    between: sigma_D^2 (clipped at 0); within_a, within_b: pooled within-example sample variances
    (NaN for a model with no example of >= 2 finite samples, which leaves `between` NaN too);
    measured_variance: var(d_e), ddof=1, at the measured samples per example; measured_samples:
    (K_a, K_b) when every matched example had that many finite samples, else None.
    """

    between: float
    within_a: float
    within_b: float
    n_examples: int
    measured_variance: float
    measured_samples: tuple[int, int] | None

    def difference_variance(self, samples_per_example: int) -> float:
        """Returns tau^2(K) = between + (within_a + within_b) / K; var(d_e) itself at the measured K; else NaN."""
        k = int(samples_per_example)
        if k < 1:
            raise ValueError(f"samples_per_example must be at least 1, got {samples_per_example!r}")
        if math.isfinite(self.between) and math.isfinite(self.within_a) and math.isfinite(self.within_b):
            return self.between + (self.within_a + self.within_b) / k
        if self.measured_samples == (k, k):
            return self.measured_variance
        return float("nan")


def paired_variance_components(a, b) -> PairedVarianceComponents:
    """a: (E, K_a), b: (E, K_b) float scores of two models. Returns PairedVarianceComponents (method of moments).

    Over the E_m examples where both models have a finite sample:
    between = var(d_e) - within_a * mean_e(1 / K_a,e) - within_b * mean_e(1 / K_b,e), clipped at 0,
    where K_a,e counts the finite samples of example e; unbiased before clipping.
    """
    a_arr, b_arr = check_pair(a, b)
    if a_arr.ndim != 2:
        raise ValueError(f"paired_variance_components takes one measurement with shapes (E, K), got {a_arr.shape}")
    d = per_example_means(a_arr) - per_example_means(b_arr)
    matched = np.isfinite(d)
    n = int(matched.sum())
    ka = np.isfinite(a_arr[matched]).sum(axis=1)
    kb = np.isfinite(b_arr[matched]).sum(axis=1)
    var_d = float(np.var(d[matched], ddof=1)) if n >= 2 else float("nan")
    within_a = within_example_std(a_arr[matched]) ** 2
    within_b = within_example_std(b_arr[matched]) ** 2
    between = var_d - within_a * np.mean(1.0 / ka) - within_b * np.mean(1.0 / kb) if n >= 2 else float("nan")
    constant = n > 0 and np.all(ka == ka[0]) and np.all(kb == kb[0])
    return PairedVarianceComponents(
        between=float(max(between, 0.0)) if math.isfinite(between) else float("nan"),
        within_a=float(within_a),
        within_b=float(within_b),
        n_examples=n,
        measured_variance=var_d,
        measured_samples=(int(ka[0]), int(kb[0])) if constant else None,
    )


def _check_test(n_examples: int, alpha: float, power: float | None = None) -> None:
    if int(n_examples) != n_examples or n_examples < 2:
        raise ValueError(f"n_examples must be an integer of at least 2, got {n_examples!r}")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie strictly between 0 and 1, got {alpha!r}")
    if power is not None and not alpha < power < 1.0:
        raise ValueError(f"power must lie strictly between alpha ({alpha}) and 1, got {power!r}")


def paired_test_power(difference: float, difference_variance: float, n_examples: int, alpha: float = 0.05) -> float:
    """Returns the power of the two-sided paired t-test at level alpha for a true mean difference, over n_examples."""
    from scipy import stats as sps

    _check_test(n_examples, alpha)
    if not (math.isfinite(difference) and math.isfinite(difference_variance)) or difference_variance < 0:
        return float("nan")
    if difference_variance == 0:
        return 1.0 if difference != 0 else float(alpha)
    df = int(n_examples) - 1
    nc = abs(difference) * math.sqrt(n_examples / difference_variance)
    t_c = sps.t.ppf(1.0 - alpha / 2.0, df)
    # The far tail is below 1e-12 wherever scipy's nct.cdf returns NaN (large nc); count it as 0.
    far = float(sps.nct.cdf(-t_c, df, nc))
    return float(sps.nct.sf(t_c, df, nc)) + (far if math.isfinite(far) else 0.0)


def minimum_detectable_difference(
    difference_variance: float, n_examples: int = 100, alpha: float = 0.05, power: float = 0.8
) -> float:
    """Returns the smallest |mean difference| the paired t-test detects with probability `power` (NaN if variance unknown)."""
    from scipy import optimize

    _check_test(n_examples, alpha, power)
    if not math.isfinite(difference_variance) or difference_variance < 0:
        return float("nan")
    if difference_variance == 0:
        return 0.0
    unit = math.sqrt(difference_variance / n_examples)  # nc = delta / unit

    def shortfall(nc: float) -> float:
        return paired_test_power(nc * unit, difference_variance, n_examples, alpha) - power

    upper = 4.0
    while shortfall(upper) < 0:
        upper *= 2.0
    nc = optimize.brentq(shortfall, 0.0, upper, xtol=1e-12)
    return float(nc * unit)


#: More examples than any benchmark could hold: ``examples_needed`` answers None (out of reach) beyond it.
MAX_EXAMPLES = 10**7


def examples_needed(
    difference: float, difference_variance: float, alpha: float = 0.05, power: float = 0.8
) -> int | None:
    """Returns the smallest E >= 2 whose paired t-test detects `difference` with probability `power`; None if never
    or only beyond MAX_EXAMPLES (e.g. a difference that is a rounding error of the scores' spread)."""
    from scipy import stats as sps

    _check_test(2, alpha, power)
    if not (math.isfinite(difference) and math.isfinite(difference_variance)) or difference == 0:
        return None
    if difference_variance == 0:
        return 2
    z = sps.norm.ppf(1.0 - alpha / 2.0) + sps.norm.ppf(power)
    approx = (z * z) * difference_variance / (difference * difference)
    if not approx <= MAX_EXAMPLES:
        return None
    n = max(2, math.ceil(approx))
    while paired_test_power(difference, difference_variance, n, alpha) < power:
        n += 1
    while n > 2 and paired_test_power(difference, difference_variance, n - 1, alpha) >= power:
        n -= 1
    return n


@dataclass(frozen=True)
class PowerRow:
    """One row of the power table: a measurement at K samples per example per model."""

    measurement: str
    samples_per_example: int
    difference_variance: float
    n_examples: int
    min_detectable_difference: float
    difference: float
    examples_needed: int | None
    samples_needed: int | None


def power_table(
    components: Mapping[str, PairedVarianceComponents],
    n_examples: int = 100,
    samples_per_example: Iterable[int] = (1, 2, 4, 8),
    differences: Mapping[str, float] | None = None,
    alpha: float = 0.05,
    power: float = 0.8,
) -> list[PowerRow]:
    """components: measurement -> variance components. Returns one PowerRow per (measurement, K).

    min_detectable_difference is for `n_examples` examples x K samples; where `differences` gives a
    difference for the measurement, examples_needed and samples_needed (= examples_needed * K, per
    model) say what detecting it takes; otherwise they are None and difference is NaN.
    """
    rows = []
    for name, comp in components.items():
        diff = float("nan") if differences is None or name not in differences else float(differences[name])
        for k in samples_per_example:
            var = comp.difference_variance(k)
            need = examples_needed(diff, var, alpha, power) if math.isfinite(diff) else None
            rows.append(
                PowerRow(
                    measurement=name,
                    samples_per_example=int(k),
                    difference_variance=var,
                    n_examples=int(n_examples),
                    min_detectable_difference=minimum_detectable_difference(var, n_examples, alpha, power),
                    difference=diff,
                    examples_needed=need,
                    samples_needed=None if need is None else need * int(k),
                )
            )
    return rows


__all__ = [
    "PairedVarianceComponents",
    "PowerRow",
    "examples_needed",
    "minimum_detectable_difference",
    "paired_test_power",
    "paired_variance_components",
    "power_table",
]
