"""Statistics of evaluation cells: success rates with Wilson score intervals, recovery times."""

from __future__ import annotations

import math
from typing import Sequence

# The two-sided 95 % quantile of the standard normal distribution.
Z95 = 1.959963984540054


def wilson_interval(successes: int, trials: int, z: float = Z95) -> tuple[float, float]:
  """Wilson score interval of a binomial proportion.

  Unlike the normal approximation p ± z√(p(1−p)/n), it stays inside [0, 1] and does not collapse
  to a point at 0 % or 100 % — the rates the paper's tables are full of.
  """
  if trials <= 0:
    raise ValueError(f"trials {trials!r} must be >= 1")
  if not 0 <= successes <= trials:
    raise ValueError(f"successes {successes!r} must be within 0..{trials}")
  n, p = float(trials), successes / trials
  z2 = z * z
  centre = (p + z2 / (2 * n)) / (1 + z2 / n)
  half = z / (1 + z2 / n) * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
  low, high = centre - half, centre + half
  # Exact bounds at the ends (the formula gives them up to rounding).
  return (0.0 if successes == 0 else max(low, 0.0), 1.0 if successes == trials else min(high, 1.0))


def mean_std(values: Sequence[float]) -> tuple[float | None, float | None]:
  """Mean and sample standard deviation (n − 1; 0 for one value); (None, None) when empty."""
  n = len(values)
  if n == 0:
    return None, None
  mean = math.fsum(values) / n
  if n == 1:
    return mean, 0.0
  var = math.fsum((v - mean) ** 2 for v in values) / (n - 1)
  return mean, math.sqrt(var)
