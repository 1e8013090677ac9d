"""Mean and 95 % confidence interval over seeds (Student t), without SciPy.

A report aggregates one number per training seed (e.g. the evaluation CTR of T1_H of each of the
five seeds of CQL on System-I). The interval is the usual two-sided t interval of the mean,
``mean ± t_{0.975, n-1} * s / sqrt(n)`` with ``s`` the sample standard deviation (``ddof=1``):
seeds are few (the paper uses one run, we use five), so the normal quantile 1.96 would be too
narrow (``t_{0.975, 4} = 2.776``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

CONFIDENCE = 0.95  # two-sided level of every interval in the reports


def _t_abs_cdf(t: float, df: int) -> float:
    """``P(|T| <= t)`` for Student's t with an integer ``df`` >= 1, in closed form.

    The finite series in ``theta = atan(t / sqrt(df))`` (Abramowitz & Stegun 26.7.3-4): exact for
    integer degrees of freedom, which is all a count of seeds can give.
    """
    theta = math.atan(t / math.sqrt(df))
    cos2 = math.cos(theta) ** 2
    if df % 2 == 1:  # odd df: 2/pi * (theta + sin cos (1 + 2/3 cos^2 + 2*4/(3*5) cos^4 + ...))
        series, term = 0.0, 1.0
        for k in range(1, (df - 1) // 2 + 1):
            series += term
            term *= cos2 * (2 * k) / (2 * k + 1)
        inner = math.sin(theta) * math.cos(theta) * series if df > 1 else 0.0
        return 2.0 / math.pi * (theta + inner)
    series, term = 0.0, 1.0  # even df: sin (1 + 1/2 cos^2 + 1*3/(2*4) cos^4 + ...)
    for k in range(1, df // 2 + 1):
        series += term
        term *= cos2 * (2 * k - 1) / (2 * k)
    return math.sin(theta) * series


def t_quantile(df: int, confidence: float = CONFIDENCE) -> float:
    """Two-sided critical value ``t`` with ``P(|T| <= t) = confidence`` for ``df`` degrees.

    Args:
        df: Degrees of freedom, an integer >= 1 (number of seeds - 1).
        confidence: Two-sided level in (0, 1).

    Returns:
        The critical value, to about 1e-12 (bisection on the exact CDF).

    Raises:
        ValueError: if ``df`` < 1 or ``confidence`` is not in (0, 1).
    """
    if int(df) != df or df < 1:
        raise ValueError(f"degrees of freedom must be an integer >= 1, got {df!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    low, high = 0.0, 1.0
    while _t_abs_cdf(high, int(df)) < confidence:  # bracket: the CDF is increasing in t
        high *= 2.0
    for _ in range(200):
        mid = 0.5 * (low + high)
        if _t_abs_cdf(mid, int(df)) < confidence:
            low = mid
        else:
            high = mid
        if high - low < 1e-12:
            break
    return 0.5 * (low + high)


@dataclass(frozen=True)
class MeanCI:
    """Mean over seeds with its 95 % t interval.

    Attributes:
        n: Number of values (seeds) that had a value.
        mean: Their mean; NaN if ``n == 0``.
        ci95: Half-width of the interval; NaN if ``n < 2`` (no spread to estimate).
        std: Sample standard deviation (``ddof=1``); NaN if ``n < 2``.
    """

    n: int
    mean: float
    ci95: float
    std: float

    @property
    def low(self) -> float:
        """Lower end of the interval (NaN if undefined)."""
        return self.mean - self.ci95

    @property
    def high(self) -> float:
        """Upper end of the interval (NaN if undefined)."""
        return self.mean + self.ci95

    def format(self, digits: int = 1) -> str:
        """``"74.3 ± 2.1"``; ``"74.3"`` for a single seed; ``"–"`` without any value."""
        if self.n == 0:
            return "–"
        if self.n < 2:
            return f"{self.mean:.{digits}f}"
        return f"{self.mean:.{digits}f} ± {self.ci95:.{digits}f}"


def mean_ci(values: Iterable[float | None]) -> MeanCI:
    """Mean and 95 % t interval of the values, ignoring None and NaN (undefined metrics).

    Args:
        values: One value per seed; None/NaN where the metric is undefined for that seed (e.g. a
            CTR of a task type none of whose tasks was decided).

    Returns:
        The aggregate.
    """
    kept = [float(v) for v in values if v is not None and not math.isnan(float(v))]
    n = len(kept)
    if n == 0:
        return MeanCI(0, math.nan, math.nan, math.nan)
    mean = math.fsum(kept) / n
    if n == 1:
        return MeanCI(1, mean, math.nan, math.nan)
    std = math.sqrt(math.fsum((v - mean) ** 2 for v in kept) / (n - 1))
    return MeanCI(n, mean, t_quantile(n - 1) * std / math.sqrt(n), std)
