"""When is an improvement of the fit real?  Thresholds for bounded parameters and discrepancy.

Two things make a better fit meaningless:

1. **Noise plus an extra parameter.**  With white noise of std σ per coordinate, adding k
   parameters lowers the squared error by σ²·χ²-distributed amounts even when the effect is
   absent.  Parameters whose "no effect" value sits on a bound (drag ≥ 0, μ ≥ 0, η ≥ 0, a
   finite yield stress) make the null distribution a mixture ("chi-bar-squared": Self & Liang
   1987; each bounded parameter is at its bound half of the time), so a fixed ΔBIC or χ²_k
   threshold is wrong there.  :func:`lr_threshold` gives the level-α threshold of that
   mixture, Bonferroni-corrected for the number of candidates (and regions) tried.
2. **A base model that is close but not identical** leaves a structured residual far above
   the noise; any extra parameter nibbles at it, and its gain is then "significant" against
   noise alone.  :func:`share_of_excess` measures the gain against the structured error the
   reference model leaves (its squared error minus the noise floor); a missing effect
   explains a large share of it, a stand-in a small one.

The diagnosis calls an effect significant when both tests pass and fitting it on the early
frames does not make the prediction of the held-out later frames worse.
"""

from __future__ import annotations

import math

from scipy.special import chdtrc  # the χ² survival function (scipy.stats.chi2.sf calls it; importing scipy.stats costs ~1 s)
from scipy.optimize import brentq

ALPHA = 1e-3
"""Family-wise false-alarm level of the noise test (per diagnosis round, Bonferroni-split)."""
MIN_SHARE = 0.6
"""Smallest share of the reference model's structured (above-noise) squared error an effect must remove.
A missing effect at moderate strength removes most of it: ≥ 0.95 in every test case, 0.75 for MPM-made
damping diagnosed by the spring-mass model.  Stand-ins for a base model that is merely close to the truth
removed up to 0.54 in our cross-solver trials without a hidden effect (a softer region next to the clamp
of an MPM-made clamped bar: the two solvers hold a clamp differently)."""
HOLDOUT_FRACTION = 0.7
"""Effects are refitted on this early fraction of the duration and scored on the rest."""
NOISE_FLOOR_UNCERTAINTY = 0.5
"""An excess squared error below this fraction of the noise floor's is not resolved: the noise σ is
estimated from the tracks (uncertain by several per cent, real noise is never quite white) and a
base model that is close but not identical leaves about that much; an effect must remove a share
of at least this much to count."""


def chibar_tail(c: float, interior: int, bounded: int) -> float:
    """P(Λ > c) under the null for ``interior`` unbounded and ``bounded`` boundary parameters.

    Λ ~ Σ_j C(b, j) 2^-b χ²_{interior + j} (independent, locally orthogonal parameters).
    """
    if c <= 0:
        return 1.0
    total = 0.0
    for j in range(bounded + 1):
        w = math.comb(bounded, j) / 2.0 ** bounded
        dof = interior + j
        total += w * (float(chdtrc(dof, c)) if dof > 0 else 0.0)
    return total


def lr_threshold(interior: int, bounded: int, alpha: float = ALPHA, tests: int = 1) -> float:
    """Threshold on Λ = ΔSSE/σ² with false-alarm probability ``alpha / tests``."""
    a = alpha / max(int(tests), 1)
    if interior + bounded == 0:
        return math.inf
    hi = 10.0
    while chibar_tail(hi, interior, bounded) > a:
        hi *= 2.0
    return float(brentq(lambda c: chibar_tail(c, interior, bounded) - a, 1e-9, hi, xtol=1e-6))


def likelihood_ratio(sse_ref: float, sse_new: float, sigma: float) -> float:
    """Λ = (SSE_ref − SSE_new) / σ² (σ per coordinate, metres)."""
    return (sse_ref - sse_new) / max(sigma * sigma, 1e-300)


def noise_floor_sse(observed_samples: int, sigma: float) -> float:
    """Expected squared error (m²) of a perfect model: 3 coordinates × samples × σ²."""
    return 3.0 * observed_samples * sigma * sigma


def share_of_excess(sse_ref: float, sse_new: float, observed_samples: int, sigma: float) -> float:
    """(SSE_ref − SSE_new) / (SSE_ref − noise floor): the part of the above-noise error removed (can exceed 1)."""
    excess = sse_ref - noise_floor_sse(observed_samples, sigma)
    # an excess below NOISE_FLOOR_UNCERTAINTY of the noise floor is not resolved: it counts as that much
    floor = NOISE_FLOOR_UNCERTAINTY * noise_floor_sse(observed_samples, sigma)
    return (sse_ref - sse_new) / max(excess, floor, 1e-300)
