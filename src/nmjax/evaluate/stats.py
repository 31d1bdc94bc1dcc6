"""The statistics every table reports: means with Student-t 95% confidence intervals over test
sequences (or clips)."""

from __future__ import annotations

import math

import numpy as np


def confidence_interval(values: np.ndarray | list[float], level: float = 0.95) -> float:
    """Half-width of the Student-t confidence interval of the mean (NaN for fewer than 2 values)."""
    from scipy import stats

    x = np.asarray([v for v in np.asarray(values, np.float64).ravel() if np.isfinite(v)])
    if len(x) < 2:
        return float("nan")
    sem = float(np.std(x, ddof=1)) / math.sqrt(len(x))
    return float(stats.t.ppf(0.5 + level / 2, len(x) - 1) * sem)


def summarize(values: list[float]) -> dict[str, float]:
    """{"mean", "ci95", "n"} of the finite values."""
    x = np.asarray([v for v in values if np.isfinite(v)], np.float64)
    mean = float(np.mean(x)) if len(x) else float("nan")
    return {"mean": mean, "ci95": confidence_interval(x), "n": int(len(x))}


def summarize_per_rate(per_sequence: dict[str, dict[int, dict[str, float]]]) -> dict:
    """The summary over sequences (`summarize`) of every method at every sampling rate.

    Args:
      per_sequence: {method: {SR: {sequence: score}}}.

    Returns:
      {method: {str(SR): {"mean", "ci95", "n", "per_sequence"}}}.
    """
    return {
        method: {
            str(rate): {**summarize(list(scores.values())), "per_sequence": scores}
            for rate, scores in by_rate.items()
        }
        for method, by_rate in per_sequence.items()
    }
