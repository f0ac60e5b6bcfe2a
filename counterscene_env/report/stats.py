"""The statistics of reports and comparisons: a value with its 95 % interval, for rates and
means over episodes, and paired differences between two runs on the same episodes.

- A **rate** (episode flags 0/1: CR, ego-adversary CR, HBR) gets the Wilson score interval
  (``metrics.wilson_interval``), good at rates near 0 and at small n.
- A **mean** (ADE, FDE, ORR, the horizon groups) gets a percentile bootstrap interval over
  episodes: :data:`BOOTSTRAP` resamples from a fixed seed, so a report is reproducible. It is
  somewhat narrow below about 20 episodes; one episode has no spread to resample, so its
  mean has no interval (NaN ends, printed as such) rather than a zero-width one.
- A **paired difference** (run B minus run A over the episodes both ran). For a rate the
  decision is McNemar's exact test (a binomial test on the episodes where the two runs
  disagree), and the interval is built on that test: the Clopper-Pearson interval of B's
  share of the disagreeing episodes, times the Clopper-Pearson interval of their share of
  all pairs (:func:`paired_rate`), so it excludes 0 exactly when the test passes. (Until 3 Dec 2026
  it was a paired bootstrap, which could exclude 0 beside a test that did not pass: 5 of 20
  against 0 of 20 gave [-45, -10] points with p = 0.0625.) For a mean the interval is a
  paired bootstrap and the decision whether it excludes 0. A difference that does not pass
  is "inside the noise".

NaN values (nothing to measure in an episode) are left out and counted out of ``n``; so are
infinite ones (a mean of them means nothing).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from counterscene_env.metrics import wilson_interval

#: Bootstrap resamples of every interval.
BOOTSTRAP = 2000
#: Seed of the bootstrap resampling (fixed: the same run gives the same report).
BOOTSTRAP_SEED = 0
#: Significance level of the paired tests (two-sided).
ALPHA = 0.05
#: The fewest pairs whose bootstrap interval may call a mean difference outside the noise:
#: the bootstrap of a handful of pairs has a handful of values (two pairs that differ alike
#: give the interval [d, d]), so it cannot tell a difference from chance.
MIN_BOOTSTRAP_PAIRS = 10

RATE_METHOD = "Wilson score"
MEAN_METHOD = f"percentile bootstrap ({BOOTSTRAP} resamples)"


@dataclass(frozen=True)
class Estimate:
    """A value over episodes with its 95 % interval.

    Attributes:
        value: the point value (NaN: nothing to measure).
        low, high: the interval's ends, in the value's unit.
        n: episodes that contributed (NaN episodes left out).
        method: how the interval was made (:data:`RATE_METHOD` or :data:`MEAN_METHOD`).
    """

    value: float
    low: float
    high: float
    n: int
    method: str

    def to_dict(self) -> dict:
        return asdict(self)


def rate(flags: Sequence[float]) -> Estimate:
    """The rate of 0/1 episode flags (NaN left out) with its Wilson interval."""
    x = _finite(flags)
    k = int(np.count_nonzero(x))
    lo, hi = wilson_interval(k, x.size)
    return Estimate(k / x.size if x.size else math.nan, lo, hi, int(x.size), RATE_METHOD)


def mean(values: Sequence[float]) -> Estimate:
    """The mean of per-episode values (NaN left out) with a percentile bootstrap interval."""
    x = _finite(values)
    if x.size < 2:  # nothing, or one episode: no interval (module docstring)
        return Estimate(
            float(x.mean()) if x.size else math.nan, math.nan, math.nan, int(x.size), MEAN_METHOD
        )
    boot = x[_resamples(x.size)].mean(1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return Estimate(float(x.mean()), float(lo), float(hi), int(x.size), MEAN_METHOD)


def group_mean(values: np.ndarray) -> Estimate:
    """A horizon group's value with a bootstrap interval: ``values`` is ``[E, S]``, one row
    per episode and one column per second of the group (NaN: not measured); the value is
    the mean over seconds of each second's NaN-aware mean over episodes, exactly the paper's
    group (``metrics.aggregate``), and each resample of episodes recomputes it."""
    values = np.asarray(values, dtype=np.float64)
    n = int((~np.isnan(values)).any(1).sum())
    value = _group_of(values[None])[0]
    if n < 2:  # nothing, or one episode: no interval (module docstring)
        return Estimate(float(value) if n else math.nan, math.nan, math.nan, n, MEAN_METHOD)
    boot = _group_of(values[_resamples(len(values))])
    lo, hi = np.nanpercentile(boot, [2.5, 97.5]) if np.isfinite(boot).any() else (np.nan,) * 2
    return Estimate(float(value), float(lo), float(hi), n, MEAN_METHOD)


def _group_of(samples: np.ndarray) -> np.ndarray:
    """``[R, E, S]`` -> ``[R]``: per resample, the mean over seconds of the episode means,
    NaN-aware at both levels (NaN where nothing is measured)."""
    ok = ~np.isnan(samples)
    count = ok.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_second = np.where(ok, samples, 0.0).sum(1) / count  # [R, S], NaN where count 0
    have = ~np.isnan(per_second)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(have, per_second, 0.0).sum(1) / have.sum(1)


@dataclass(frozen=True)
class Paired:
    """Run B minus run A over the episodes both ran.

    Attributes:
        difference: the mean paired difference (a rate difference for 0/1 flags).
        low, high: its 95 % interval (rates: built on McNemar's test, :func:`paired_rate`;
            means: a paired bootstrap).
        n: pairs with a value in both runs.
        p_value: McNemar's exact p-value for rates, None for means.
        a_only, b_only: for rates, pairs flagged in A only and in B only (the discordant
            pairs McNemar's test reads); None for means.
        significant: the difference is outside the noise (rates: p < :data:`ALPHA`; means:
            the interval excludes 0 and there are at least :data:`MIN_BOOTSTRAP_PAIRS`).
        test: the decision rule, in words.
    """

    difference: float
    low: float
    high: float
    n: int
    p_value: float | None
    a_only: int | None
    b_only: int | None
    significant: bool
    test: str

    def to_dict(self) -> dict:
        return asdict(self)


def paired_rate(a: Sequence[float], b: Sequence[float]) -> Paired:
    """Paired difference of two runs' 0/1 flags on the same episodes (``a[i]``, ``b[i]``:
    episode i in runs A and B), with McNemar's exact test."""
    x, y = _pairs(a, b)
    a_only = int(np.count_nonzero((x > 0) & (y == 0)))
    b_only = int(np.count_nonzero((x == 0) & (y > 0)))
    p = mcnemar_exact(a_only, b_only)
    n, discordant = int(x.size), a_only + b_only
    if n == 0:
        lo = hi = diff = math.nan
    else:
        # Delta = psi (2 pi - 1): psi the share of pairs that disagree, pi the share of those
        # that B flags. Given the disagreeing pairs, B's count is binomial(N, pi), the law the
        # test reads, so pi's Clopper-Pearson interval excludes 1/2 exactly when p < ALPHA.
        # psi's own interval widens the ends (never crossing 0: psi's lower end is above 0
        # once a pair disagrees), so that a few disagreements do not fix the difference's
        # size; with none, pi is unknown and Delta lies within +-psi's upper end.
        psi_lo, psi_hi = clopper_pearson(discordant, n)
        pi_lo, pi_hi = clopper_pearson(b_only, discordant) if discordant else (0.0, 1.0)
        diff = (b_only - a_only) / n
        e_lo, e_hi = 2 * pi_lo - 1, 2 * pi_hi - 1  # the range of 2 pi - 1
        lo = e_lo * (psi_hi if e_lo < 0 else psi_lo)  # the smallest psi (2 pi - 1)
        hi = e_hi * (psi_hi if e_hi > 0 else psi_lo)  # the largest
    return Paired(diff, lo, hi, n, p, a_only, b_only, p < ALPHA, "McNemar exact, p < 0.05")


def paired_mean(a: Sequence[float], b: Sequence[float]) -> Paired:
    """Paired difference of two runs' per-episode values on the same episodes, with a
    paired bootstrap interval; significant when it excludes 0."""
    x, y = _pairs(a, b)
    diff, lo, hi = _paired_bootstrap(y - x)
    significant = x.size >= MIN_BOOTSTRAP_PAIRS and (lo > 0 or hi < 0)
    return Paired(
        diff,
        lo,
        hi,
        int(x.size),
        None,
        None,
        None,
        bool(significant),
        f"paired bootstrap excludes 0, over at least {MIN_BOOTSTRAP_PAIRS} pairs",
    )


def mcnemar_exact(a_only: int, b_only: int) -> float:
    """Two-sided exact McNemar p-value: under "no difference" each discordant pair is A's
    or B's with probability 1/2, so the smaller count is binomial(a_only + b_only, 1/2).
    1.0 when there is no discordant pair."""
    n = a_only + b_only
    if n == 0:
        return 1.0
    return min(1.0, 2.0 * binomial_cdf(min(a_only, b_only), n, 0.5))


def binomial_cdf(k: int, n: int, p: float) -> float:
    """``P(X <= k)`` for ``X ~ binomial(n, p)``, summed in log space (exact for any n: the
    plain ``comb(n, i) / 2**n`` overflows past about 1,000 trials)."""
    if k < 0:
        return 0.0
    if k >= n or p <= 0.0:
        return 1.0
    if p >= 1.0:
        return 0.0
    lp, lq, lnf = math.log(p), math.log1p(-p), math.lgamma(n + 1)
    terms = [lnf - math.lgamma(i + 1) - math.lgamma(n - i + 1) + i * lp + (n - i) * lq
             for i in range(k + 1)]  # fmt: skip
    top = max(terms)
    return min(1.0, math.exp(top) * math.fsum(math.exp(t - top) for t in terms))


def clopper_pearson(k: int, n: int, alpha: float = ALPHA) -> tuple[float, float]:
    """The exact (Clopper-Pearson) ``1 - alpha`` interval of a binomial share ``k / n``: the
    shares p at which neither tail of ``binomial(n, p)`` beyond ``k`` is below ``alpha / 2``
    (found by bisection to 1e-12)."""

    def solve(increasing) -> float:
        lo, hi = 0.0, 1.0
        while hi - lo > 1e-12:
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if increasing(mid) >= 0 else (mid, hi)
        return 0.5 * (lo + hi)

    low = 0.0 if k == 0 else solve(lambda p: 1.0 - binomial_cdf(k - 1, n, p) - alpha / 2)
    high = 1.0 if k >= n else solve(lambda p: alpha / 2 - binomial_cdf(k, n, p))
    return low, high


def _pairs(a: Sequence[float], b: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"paired values need two equal-length lists, got {x.shape} and {y.shape}")
    keep = np.isfinite(x) & np.isfinite(y)
    return x[keep], y[keep]


def _paired_bootstrap(d: np.ndarray) -> tuple[float, float, float]:
    """Mean of the paired differences ``d`` and its percentile bootstrap interval (none for
    fewer than two pairs, as for :func:`mean`)."""
    if d.size < 2:
        return (float(d.mean()) if d.size else math.nan), math.nan, math.nan
    boot = d[_resamples(d.size)].mean(1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return float(d.mean()), float(lo), float(hi)


def _resamples(n: int) -> np.ndarray:
    """``[BOOTSTRAP, n]`` indices drawn with replacement from a fixed seed."""
    return np.random.default_rng(BOOTSTRAP_SEED).integers(0, n, size=(BOOTSTRAP, n))


def _finite(values: Sequence[float]) -> np.ndarray:
    """Values as float64 with NaN (nothing measured) and inf left out."""
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    return x[np.isfinite(x)]
