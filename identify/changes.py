"""Changes in a sequence of estimates: a step or a drift, against each estimate's std and the
scatter the arm itself shows (issue 37). Arrays in, arrays out.

Each tracked quantity of an arm (:mod:`identify.tracked`) is a sequence ``x_i +- s_i`` over
its recordings ``i = 1..n`` in time order. Its estimates scatter from run to run more than
their standard deviations say (a new trajectory each day excites a little differently; the
model is never exact), by a factor that differs from quantity to quantity. The model is

.. math:: x_i = a + b \\, z_i + e_i, \\qquad e_i \\sim N(0, \\lambda_q s_i^2)

with ``z`` the candidate change: a **step** (``z_i = 1`` from recording ``k`` on, else 0) or
a **drift** (``z_i = t_i - t_{k-1}`` from ``k`` on: a ramp in time that starts after recording
``k - 1``), and no change ``b = 0``. The excess variance ``lambda_q`` is unknown; the quantities
of one arm share a scaled inverse chi-square prior for it, ``lambda_q ~ s0^2 d0 / chi2(d0)``,
whose ``s0^2`` and ``d0`` are estimated from all of the arm's quantities (Smyth 2004, 6.2:
the moments of ``log lambda_hat``). Each candidate's slope is then tested by the *moderated*
t statistic (Smyth 2004, eq. 3-4)

.. math:: \\tilde t = \\hat b / \\sqrt{\\tilde\\lambda \\, v_b}, \\qquad
          \\tilde\\lambda = \\frac{d_0 s_0^2 + RSS}{d_0 + n - 2}

with ``v_b`` the slope's variance per unit ``lambda`` (weights ``1/s_i^2``), which is Student t
with ``d0 + n - 2`` degrees of freedom when nothing changed: the quantity's own scatter,
pulled towards the arm's typical scatter by as much as the arm's quantities agree with each
other. A quantity whose estimates wander more than the others' keeps its own wide scatter.

A single wild run is common (a trajectory that excites a joint badly: one of the generated
fleet's unchanged arms has a run whose Coulomb friction is 20 sigma off the others). Least squares lets one point make a
step when it sits in a short segment, so each candidate is fitted ``n`` more times, leaving
each recording out in turn (a jackknife), and its statistic is the *weakest* of these
moderated t's, on ``d0 + n - 3`` degrees of freedom. It is never larger than the t of any one
leave-one-out fit, each of which is Student t when nothing changed: the p-value stays valid
(conservative), and no single recording can make a change.

The change's place is unknown (Hinkley 1970 for a step, 1971 for two-phase regression):
every recording ``k`` with at least :data:`MIN_SEGMENT` recordings before and after it is a
candidate, for either kind; the best candidate (largest ``|t|``) is the change. Its p-value
is multiplied by the number of candidates of every quantity of the fleet (Bonferroni over
places, kinds, quantities and arms: :func:`family_wise`), so the rate of a fleet run reporting
any change when none happened is at most ``alpha`` (:data:`ALPHA`) whatever the correlation
between candidates; neighbouring candidates are strongly correlated, so the true rate is lower
(Worsley 1982 gives the sharper bound).

References: G. K. Smyth (2004), Linear models and empirical Bayes methods for assessing
differential expression in microarray experiments, Stat. Appl. Genet. Mol. Biol. 3(1), art. 3;
D. V. Hinkley (1970), Inference about the change-point in a sequence of random variables,
Biometrika 57, 1-17; D. V. Hinkley (1971), Inference in two-phase regression, JASA 66, 736-743;
K. J. Worsley (1982), An improved Bonferroni inequality and applications, Biometrika 69, 297-302.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special, stats

from .spatial import Array

ALPHA = 0.01
"""Designed family-wise false-alarm rate: the chance that a fleet run in which nothing changed
reports any change at all, over every quantity of every arm."""

MIN_SEGMENT = 2
"""Recordings a change needs on either side of it: a change is reported once two recordings
show it (and, left out in turn, neither of them alone makes it)."""

OUTLYING = 0.01
"""A quantity whose scatter the arm's prior gives less than this chance (over all of the arm's
quantities) is left out of the prior (:func:`scatter_prior`)."""

STEP, DRIFT = 1, 2
KINDS = {0: "none", STEP: "step", DRIFT: "drift"}


@dataclass(frozen=True)
class Scan:
    """Per quantity (Q,): the best candidate change and its test. ``kind`` 0 (no candidate),
    :data:`STEP` or :data:`DRIFT`; ``first`` the first recording (0-based) the change affects;
    ``before``/``after`` the fitted value before the change and at the last recording (all
    recordings); ``statistic`` the weakest leave-one-out moderated t, ``p`` its two-sided
    p-value as one test, ``candidates`` the number of places and kinds tried (the
    multiplicity :func:`family_wise` charges)."""

    kind: Array
    first: Array
    before: Array
    after: Array
    statistic: Array
    p: Array
    candidates: Array
    scatter: Array  # lambda_hat: each quantity's scatter about its mean in units of its own variance (no change assumed)
    wanders: Array  # scatters beyond the arm's prior even with its change fitted out: tested on its own scatter
    prior_variance: float  # s0^2
    prior_df: float  # d0 (inf: every quantity scatters alike)


def _trigamma_inverse(y: float) -> float:
    """``x`` with ``trigamma(x) = y`` (Newton, as Smyth 2004's appendix)."""
    if y > 1e7:
        return 1.0 / np.sqrt(y)
    if y < 1e-6:
        return 1.0 / y
    x = 0.5 + 1.0 / y
    for _ in range(50):
        tri = float(special.polygamma(1, x))
        step = tri * (1.0 - tri / y) / float(special.polygamma(2, x))
        x += step
        if -step / x < 1e-8:
            break
    return x


def _moments(v: Array, d: Array) -> tuple[float, float]:
    """Smyth's (2004, 6.2) moment estimates of ``(s0^2, d0)`` from variances ``v`` on ``d`` degrees of freedom."""
    e = np.log(v) - special.digamma(d / 2) + np.log(d / 2)
    mean = float(e.mean())
    if v.size < 2:
        return float(np.exp(mean)), 0.0
    spread = float(np.mean((e - mean) ** 2) * v.size / (v.size - 1) - np.mean(special.polygamma(1, d / 2)))
    if spread <= 0:
        return float(np.exp(mean)), np.inf
    d0 = 2.0 * _trigamma_inverse(spread)
    return float(np.exp(mean + special.digamma(d0 / 2) - np.log(d0 / 2))), d0


def scatter_prior(variance: Array, df: Array) -> tuple[float, float, Array]:
    """``(s0^2, d0, outlying)``: the scaled inverse chi-square prior of the quantities' variances
    from their estimates ``variance`` (Q,) on ``df`` (Q,) degrees of freedom (Smyth 2004, 6.2:
    the mean and the excess spread of ``log variance`` beyond what its own chi-square spread
    explains; ``d0`` infinite when they spread no more than chance makes them), and the
    quantities left out of it (Q,): those whose variance the prior itself puts beyond
    :data:`OUTLYING` (Bonferroni over the quantities), refitted until none is. A quantity that
    changed has a large variance about its mean; let in, it would widen the prior and cost every
    other quantity of its arm its power (Phipson et al. 2016 make limma robust for the same
    reason). An outlying quantity is tested on its own scatter alone."""
    ok = np.isfinite(variance) & (variance > 0) & (df > 0)
    # the first fit on the lower 80 % (the changed ones sit at the top), then the prior's own test
    # decides, each time from scratch, until it stands
    keep = ok & (variance <= np.quantile(variance[ok], 0.8)) if ok.sum() >= 5 else ok.copy()
    s02, d0 = 1.0, 0.0
    for _ in range(10):
        if not keep.any():
            break
        s02, d0 = _moments(variance[keep], df[keep])
        ratio = np.where(ok, variance, 1.0) / s02
        upper = stats.chi2.sf(ratio * df, np.maximum(df, 1e-9)) if not np.isfinite(d0) else stats.f.sf(ratio, np.maximum(df, 1e-9), max(d0, 1e-9))
        again = ok & (upper >= OUTLYING / max(int(ok.sum()), 1))
        if d0 <= 0 or np.array_equal(again, keep):
            break
        keep = again
    return s02, d0, ok & ~keep


def _weights(stds: Array, valid: Array) -> Array:
    """``1/s^2`` where a value is; a missing or non-positive std takes its quantity's median
    (1 where a quantity has none: its scatter alone then sets its scale)."""
    s = np.where(valid & np.isfinite(stds) & (stds > 0), stds, np.nan)
    with np.errstate(all="ignore"):
        typical = np.nanmedian(np.where(np.isnan(s).all(axis=0, keepdims=True), 1.0, s), axis=0)
    s = np.where(np.isnan(s), typical, s)
    return np.where(valid, 1.0 / s**2, 0.0)


def _sums(x: Array, w: Array, z: Array) -> Array:
    """Per point (n, Q) its terms of the six weighted sums of ``x ~ a + b z``: 1, z, z^2, x, z x, x^2."""
    return np.stack([w, w * z, w * z * z, w * x, w * z * x, w * x * x])


def _solve(s: Array) -> tuple[Array, Array, Array, Array]:
    """Weighted least squares from the six sums ``s`` (6, ...): (a, b, RSS, var(b) per unit lambda)."""
    s0, s1, s2, sy, szy, syy = s
    det = s0 * s2 - s1**2
    with np.errstate(divide="ignore", invalid="ignore"):
        b = (s0 * szy - s1 * sy) / det
        a = (sy - b * s1) / s0
        vb = np.where(det > 1e-12 * np.maximum(s0 * s2, 1e-300), s0 / det, np.nan)
    rss = np.maximum(syy - a * sy - b * szy, 0.0)
    return a, b, rss, vb


def _moderated_t(b: Array, rss: Array, vb: Array, df: Array, s02: float, d0: Array) -> Array:
    """``b / sqrt(lambda~ v_b)`` with each quantity's residual variance pulled towards the arm's
    by its prior's ``d0`` (Q,; infinite: the arm's alone, 0: its own alone)."""
    with np.errstate(invalid="ignore"):
        pooled = np.where(np.isinf(d0), s02, (np.where(np.isinf(d0), 0.0, d0) * s02 + rss) / np.maximum(d0 + df, 1e-300))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(b / np.sqrt(pooled * vb))


def _candidates(n: int, times: Array) -> list[tuple[int, int, Array]]:
    """(kind, first recording, z (n,)) of every candidate change in ``n`` recordings."""
    out = []
    for k in range(MIN_SEGMENT, n - MIN_SEGMENT + 1):
        out.append((STEP, k, (np.arange(n) >= k).astype(float)))
        out.append((DRIFT, k, np.maximum(times - times[k - 1], 0.0)))
    return out


def _usable(valid: Array, k: int) -> Array:
    """Quantities (Q,) with :data:`MIN_SEGMENT` estimates before recording ``k`` and from it on."""
    return np.asarray((valid[:k].sum(0) >= MIN_SEGMENT) & (valid[k:].sum(0) >= MIN_SEGMENT))


def _wandering(x: Array, w: Array, valid: Array, candidates: list[tuple[int, int, Array]], s02: float, d0: float) -> Array:
    """Quantities (Q,) that scatter beyond the arm's prior even with their best change fitted
    out (the residual variance of the best candidate in the prior's upper :data:`OUTLYING`
    tail, Bonferroni over the quantities): tested on their own scatter alone, not pulled
    towards the arm's. A quantity that only changed is not one of them."""
    count = valid.sum(0)
    rss = np.full(x.shape[1], np.inf)
    for _, k, z in candidates:
        _, _, r, _ = _solve(_sums(x, w, z[:, None]).sum(1))
        rss = np.where(_usable(valid, k), np.minimum(rss, r), rss)
    df = (count - 2).astype(float)
    ratio = rss / np.maximum(df, 1.0) / s02
    with np.errstate(invalid="ignore"):
        upper = stats.chi2.sf(ratio * df, np.maximum(df, 1e-9)) if not np.isfinite(d0) else stats.f.sf(ratio, np.maximum(df, 1e-9), max(d0, 1e-9))
    tested = np.isfinite(rss) & (df > 0)
    return np.asarray(tested & (upper < OUTLYING / max(int(tested.sum()), 1)))


def scan(values: Array, stds: Array, times: Array | None = None) -> Scan:
    """The best step or drift of each quantity of one arm and its moderated t test.

    ``values``, ``stds``: (n, Q) estimates over the arm's ``n`` recordings in time order (NaN
    where a recording gave none); ``times`` (n,) the recordings' start times in any unit (a
    drift is a ramp in time); their index when not given or when they do not increase."""
    n, q = np.shape(values)
    times = np.arange(n, dtype=float) if times is None else np.asarray(times, float)
    if not (np.all(np.isfinite(times)) and np.all(np.diff(times) > 0)):
        times = np.arange(n, dtype=float)  # recordings stamped from 0: a drift is per recording
    x, w, valid, count, centre = _centred(values, stds)
    null_var = (w * x * x).sum(0) / np.maximum(count - 1, 1)
    s02, d0, _ = scatter_prior(np.where(count >= 2, null_var, np.nan), (count - 1).astype(float))
    candidates = _candidates(n, times - times[0])
    wanders = _wandering(x, w, valid, candidates, s02, d0)
    d0_q = np.where(wanders, 0.0, d0)
    out = {k: np.full(q, np.nan) for k in ("before", "after", "statistic")}
    kind, first, tried, best = np.zeros(q, int), np.full(q, -1), np.zeros(q, int), np.zeros(q)
    for kd, k, z in candidates:
        terms = _sums(x, w, z[:, None])
        a, b, _, _ = _solve(terms.sum(1))
        # leave each recording out in turn: the weakest of these is the candidate's statistic
        _, b_out, rss_out, vb_out = _solve(terms.sum(1, keepdims=True) - terms)
        t_out = _moderated_t(b_out, rss_out, vb_out, count - 3, s02, d0_q)
        t = np.sign(b) * np.where(np.isfinite(t_out), np.abs(t_out), 0.0).min(0)
        usable = _usable(valid, k) & np.isfinite(t)
        tried += usable
        better = usable & (np.abs(t) > best)
        best = np.where(better, np.abs(t), best)
        kind, first = np.where(better, kd, kind), np.where(better, k, first)
        out["statistic"] = np.where(better, t, out["statistic"])
        out["before"] = np.where(better, a + centre, out["before"])
        out["after"] = np.where(better, a + b * z[-1] + centre, out["after"])
    df_t = (count - 3) + np.where(np.isinf(d0_q), 1e12, d0_q)
    with np.errstate(invalid="ignore"):
        p = np.where(kind > 0, 2.0 * stats.t.sf(np.abs(out["statistic"]), np.maximum(df_t, 1e-9)), np.nan)
    return Scan(kind, first, out["before"], out["after"], out["statistic"], p, tried, np.where(count >= 2, null_var, np.nan),
                wanders, s02, d0)


def _centred(values: Array, stds: Array) -> tuple[Array, Array, Array, Array, Array]:
    """(x, w, valid, count, centre): each quantity's estimates less their weighted mean (0 where
    missing), the weights ``1/s^2``, which are there, how many, and that mean."""
    x_raw = np.asarray(values, float)
    valid = np.isfinite(x_raw)
    w = _weights(np.asarray(stds, float), valid)
    count = valid.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        centre = np.where(count > 0, (w * np.where(valid, x_raw, 0.0)).sum(0) / w.sum(0), 0.0)
    return np.where(valid, x_raw - centre, 0.0), w, valid, count, centre


def family_wise(p: Array, candidates: Array) -> Array:
    """Bonferroni: each best candidate's p-value times every candidate tried in the family
    (every quantity of every arm of the fleet run), capped at 1. A change is reported when
    this is below :data:`ALPHA`."""
    p = np.asarray(p, float)
    total = float(np.sum(candidates))
    return np.where(np.isfinite(p), np.minimum(1.0, p * max(total, 1.0)), np.nan)


def step_at(values: Array, stds: Array, first: int, prior_variance: float, prior_df: float, wanders: Array) -> tuple[Array, Array, Array]:
    """Each quantity's step at recording ``first`` (0-based), whether or not it changed there:
    ``(b, se, df)`` (Q,) the fitted step ``x_i = a + b z_i`` (``z`` the step's), its standard
    error on the moderated scatter ``sqrt(lambda~ v_b)`` (the module's docstring, with the
    arm's prior ``prior_variance``, ``prior_df`` and the quantities that ``wanders``, as
    :func:`scan` found them) and its degrees of freedom. NaN where a quantity has fewer than
    :data:`MIN_SEGMENT` estimates on either side."""
    x, w, valid, count, _ = _centred(values, stds)
    z = (np.arange(x.shape[0]) >= first).astype(float)
    _, b, rss, vb = _solve(_sums(x, w, z[:, None]).sum(1))
    d0 = np.where(np.asarray(wanders, bool), 0.0, prior_df)
    df = (count - 2).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        pooled = np.where(np.isinf(d0), prior_variance, (np.where(np.isinf(d0), 0.0, d0) * prior_variance + rss) / np.maximum(d0 + df, 1e-300))
        se = np.sqrt(pooled * vb)
    usable = _usable(valid, first) & np.isfinite(se)
    nan = np.full(b.shape, np.nan)
    return np.where(usable, b, nan), np.where(usable, se, nan), np.where(usable, df + d0, nan)
