"""Statistics over seeds: mean with a 95 % t-interval, improvement in percent, correlations."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats


@dataclass(frozen=True, slots=True)
class Estimate:
    """A mean over ``n`` values and the half-width of its 95 % confidence interval.

    The interval uses Student's t with n - 1 degrees of freedom (few seeds, unknown
    variance). ``ci95`` is None for fewer than two values, ``mean`` None for none.
    """

    mean: float | None
    ci95: float | None
    n: int

    def format(self, digits: int = 1, *, signed: bool = False) -> str:
        """``"161.2 ± 3.4"``, ``"+4.5 ± 2.0"``, or ``"-"`` without values."""
        if self.mean is None:
            return "-"
        sign = "+" if signed else ""
        text = f"{self.mean:{sign}.{digits}f}"
        return text if self.ci95 is None else f"{text} ± {self.ci95:.{digits}f}"


def mean_ci95(values: Sequence[float | None]) -> Estimate:
    """Mean and 95 % t-interval half-width of the values that are defined (not None/nan)."""
    kept = [float(v) for v in values if v is not None and math.isfinite(v)]
    n = len(kept)
    if n == 0:
        return Estimate(None, None, 0)
    mean = float(np.mean(kept))
    if n < 2:
        return Estimate(mean, None, n)
    sem = float(np.std(kept, ddof=1)) / math.sqrt(n)
    return Estimate(mean, float(stats.t.ppf(0.975, n - 1)) * sem, n)


def improvement_pct(base: float, new: float) -> float | None:
    """How much ``new`` exceeds ``base``, in percent of ``base``; None when base is 0."""
    if base == 0:
        return None
    return (new - base) / base * 100.0


def correlations(estimated: Sequence[float], true: Sequence[float]) -> tuple[float, float]:
    """(Pearson r, Spearman rho) of two equally long sequences; nan with < 3 pairs."""
    a = np.asarray(estimated, dtype=np.float64)
    b = np.asarray(true, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"{a.size} estimates but {b.size} true values")
    if a.size < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return float("nan"), float("nan")
    pearson = float(stats.pearsonr(a, b).statistic)
    spearman = float(stats.spearmanr(a, b).statistic)
    return pearson, spearman


def captured_fraction(policy: float, uncontrolled: float, oracle: float) -> float | None:
    """The share of the possible gain a policy reached: (policy − uncontrolled) /
    (oracle − uncontrolled); None when the oracle gains nothing over uncontrolled."""
    if oracle == uncontrolled:
        return None
    return (policy - uncontrolled) / (oracle - uncontrolled)


def json_safe(value: Any) -> Any:
    """JSON-safe: nan and inf become None (no interval for one seed, no rate for zero)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value
