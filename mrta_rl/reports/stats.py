"""Statistics over seeds: mean and 95 % t interval; IQM, probability of improvement, profiles.

Seeds are few, so intervals use the t quantile (``t_{0.975, 4} = 2.776``), not 1.96.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats as scipy_stats

CONFIDENCE = 0.95  # two-sided level of every interval in the reports


def t_quantile(df: int, confidence: float = CONFIDENCE) -> float:
    """Two-sided critical value ``t`` with ``P(|T| <= t) = confidence`` for ``df`` degrees."""
    if int(df) != df or df < 1:
        raise ValueError(f"degrees of freedom must be an integer >= 1, got {df!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    return float(scipy_stats.t.ppf(0.5 + confidence / 2, int(df)))


@dataclass(frozen=True)
class MeanCI:
    """Mean over seeds with its 95 % t interval (half-width ``ci95``, NaN below two values)."""

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

    @property
    def half(self) -> float:
        """Half-width drawn as a band or an error bar: 0 where the interval is undefined."""
        return 0.0 if math.isnan(self.ci95) else self.ci95

    def format(self, digits: int = 1) -> str:
        """``"74.3 ± 2.1"``; ``"74.3"`` for a single seed; ``"–"`` without any value."""
        spread = f" ± {self.ci95:.{digits}f}" if self.n >= 2 else ""
        return f"{self.mean:.{digits}f}{spread}" if self.n else "–"


def mean_ci(values: Iterable[float | None]) -> MeanCI:
    """Mean and 95 % t interval of the values, ignoring None and NaN (undefined metrics)."""
    kept = [float(v) for v in values if v is not None and not math.isnan(float(v))]
    n = len(kept)
    if n == 0:
        return MeanCI(0, math.nan, math.nan, math.nan)
    mean = math.fsum(kept) / n
    if n == 1:
        return MeanCI(1, mean, math.nan, math.nan)
    std = math.sqrt(math.fsum((v - mean) ** 2 for v in kept) / (n - 1))
    return MeanCI(n, mean, t_quantile(n - 1) * std / math.sqrt(n), std)


# --- as the field reports them (Agarwal et al. 2021; rliable): scipy's bootstrap with one
# sample per task is rliable's stratified bootstrap. rliable is no dependency: its ``arch``
# fails to import under pandas 3.

BOOTSTRAP_REPS = 2000  # bootstrap resamples of every interval
BOOTSTRAP_SEED = 0  # fixed, so a report is reproducible
# each task's runs resampled alone (scipy's unpaired samples), vectorized statistics
STRATIFIED = {"confidence_level": CONFIDENCE, "method": "percentile", "paired": False}
STRATIFIED |= {"vectorized": True}
IQM_CUT = 0.25  # interquartile mean: drop the lowest and highest 25 % of the runs


@dataclass(frozen=True)
class Estimate:
    """A point estimate with its 95 % stratified bootstrap (percentile) interval over ``n`` runs."""

    value: float
    low: float
    high: float
    n: int

    def format(self, digits: int = 2) -> str:
        """``"0.97 [0.95, 0.99]"``; just the value without an interval; ``"–"`` without data."""
        if self.n == 0 or math.isnan(self.value):
            return "–"
        if math.isnan(self.low):
            return f"{self.value:.{digits}f}"
        return f"{self.value:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"


def _tasks(scores_by_task: Iterable[Iterable[float]]) -> list[Any]:
    tasks = [np.asarray([float(v) for v in task], dtype=float) for task in scores_by_task]
    tasks = [t[~np.isnan(t)] for t in tasks]
    return [t for t in tasks if t.size]


def _interquartile_mean(*tasks: Any, axis: int = -1) -> Any:
    """IQM of the runs of all tasks pooled (rliable ``aggregate_iqm``), vectorized on ``axis``."""
    return scipy_stats.trim_mean(np.concatenate(tasks, axis=axis), IQM_CUT, axis=axis)


def _bootstrap(
    samples: Sequence[Any], statistic: Callable[..., Any], value: Any, reps: int, seed: int
) -> tuple[Any, Any]:
    """Stratified percentile bootstrap interval of ``statistic`` (each sample resampled alone)."""
    if any(s.size < 2 for s in samples):  # no spread to resample within a task
        nan = np.full(np.shape(value), np.nan)
        return nan, nan
    if all(np.ptp(s) == 0 for s in samples) and len({float(s[0]) for s in samples}) == 1:
        return value, value  # every run has the same score: the interval is that point
    rng = np.random.default_rng(seed)
    result = scipy_stats.bootstrap(
        tuple(samples), statistic, n_resamples=reps, rng=rng, **STRATIFIED
    )
    return result.confidence_interval.low, result.confidence_interval.high


def _estimate(samples: list[Any], statistic: Callable[..., Any], reps: int, seed: int) -> Estimate:
    """``statistic`` of the samples and its bootstrap interval, over all their runs."""
    if not samples:
        return Estimate(math.nan, math.nan, math.nan, 0)
    value = float(statistic(*samples))
    low, high = _bootstrap(samples, statistic, value, reps, seed)
    return Estimate(value, float(low), float(high), sum(s.size for s in samples))


def iqm_ci(
    scores_by_task: Iterable[Iterable[float]],
    reps: int = BOOTSTRAP_REPS,
    seed: int = BOOTSTRAP_SEED,
) -> Estimate:
    """Interquartile mean of the runs with its 95 % stratified bootstrap interval."""
    return _estimate(_tasks(scores_by_task), _interquartile_mean, reps, seed)


def _improvement(*samples: Any, axis: int = -1) -> Any:
    """Mean over tasks of P(X > Y) + P(X = Y) / 2; samples are the X tasks then the Y tasks."""
    half = len(samples) // 2
    per_task = []
    for x, y in zip(samples[:half], samples[half:], strict=True):
        x, y = np.moveaxis(x, axis, -1), np.moveaxis(y, axis, -1)
        greater = (x[..., :, None] > y[..., None, :]).mean(axis=(-2, -1))
        equal = (x[..., :, None] == y[..., None, :]).mean(axis=(-2, -1))
        per_task.append(greater + 0.5 * equal)  # Mann-Whitney U / (n m) of the task
    return np.mean(per_task, axis=0)


def probability_of_improvement(
    x_by_task: Sequence[Iterable[float]],
    y_by_task: Sequence[Iterable[float]],
    reps: int = BOOTSTRAP_REPS,
    seed: int = BOOTSTRAP_SEED,
) -> Estimate:
    """P(X > Y): the chance that a run of X beats a run of Y on a task, averaged over tasks.

    Ties count one half (rliable's Mann-Whitney U divided by ``n * m``).
    """
    if len(x_by_task) != len(y_by_task):
        raise ValueError(f"X has {len(x_by_task)} tasks but Y has {len(y_by_task)}")
    pairs = [(_tasks([x]), _tasks([y])) for x, y in zip(x_by_task, y_by_task, strict=True)]
    pairs = [(x[0], y[0]) for x, y in pairs if x and y]
    samples = [x for x, _ in pairs] + [y for _, y in pairs]  # the X tasks, then the Y tasks
    return _estimate(samples, _improvement, reps, seed)


@dataclass(frozen=True)
class Profile:
    """Performance profile: fraction of runs scoring above each threshold ``tau``."""

    tau: Any
    fraction: Any
    low: Any
    high: Any


def performance_profile(
    scores_by_task: Iterable[Iterable[float]],
    tau: Sequence[float],
    reps: int = BOOTSTRAP_REPS,
    seed: int = BOOTSTRAP_SEED,
) -> Profile:
    """Run-score distribution (rliable ``create_performance_profile``) with a bootstrap band."""
    taus = np.asarray(tau, dtype=float)
    tasks = _tasks(scores_by_task)
    if not tasks:
        nan = np.full(taus.shape, np.nan)
        return Profile(taus, nan, nan, nan)

    def fraction(*samples: Any, axis: int = -1) -> Any:
        # [..., tau]: per task the share of runs above tau, then the mean over tasks
        per_task = [
            (np.moveaxis(s, axis, -1)[..., None, :] > taus[:, None]).mean(axis=-1) for s in samples
        ]
        # scipy's bootstrap wants the statistic's own axis first, the resamples last
        return np.moveaxis(np.mean(per_task, axis=0), -1, 0)

    value = fraction(*tasks)
    low, high = _bootstrap(tasks, fraction, value, reps, seed)
    return Profile(taus, value, np.asarray(low, dtype=float), np.asarray(high, dtype=float))
