"""The change test of identify/changes.py on sequences whose truth is known (numpy draws, no
identification): its prior is the one that made the data, its slope and t are least squares'
own, its false alarms stay within the designed family-wise rate, and a step or a drift is
found where it began with its sign.

The no-change fleets are drawn from the model the test is designed for (each quantity
scatters ``sqrt(lambda_q)`` times its std, ``lambda_q`` drawn per quantity) and from a harder
one (a wild run in every arm, the per-recording stds off by up to 3x).
"""

from __future__ import annotations

import numpy as np
import pytest

from armid.identify.changes import ALPHA, DRIFT, MIN_SEGMENT, STEP, family_wise, scan, scatter_prior


def _arm(rng: np.random.Generator, n: int = 10, q: int = 30, s0: float = 1.5, d0: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """Estimates of ``q`` unchanging quantities over ``n`` recordings: value 1-100, std per
    recording 0.5-2 % of it, scatter ``lambda_q`` drawn from the scaled inverse chi-square prior."""
    level = rng.uniform(1.0, 100.0, q)
    stds = level * rng.uniform(0.005, 0.02, (n, q))
    lam = s0**2 * d0 / rng.chisquare(d0, q)
    return level + stds * np.sqrt(lam) * rng.standard_normal((n, q)), stds


def test_the_prior_of_the_scatter_is_the_one_that_made_it() -> None:
    rng = np.random.default_rng(1)
    lam = 2.0 * 8.0 / rng.chisquare(8.0, 20000)
    estimates = lam * rng.chisquare(9.0, lam.size) / 9.0
    s02, d0, outlying = scatter_prior(estimates, np.full(lam.size, 9.0))
    print(f"\ns0^2 {s02:.3f} (made with 2.0), d0 {d0:.2f} (made with 8.0), {int(outlying.sum())} of {lam.size} left out")
    assert s02 == pytest.approx(2.0, rel=0.05) and d0 == pytest.approx(8.0, rel=0.2) and outlying.sum() <= 5
    same = rng.chisquare(9.0, 20000) / 9.0  # every quantity scatters alike: no spread beyond chance
    s02, d0, _ = scatter_prior(same, np.full(same.size, 9.0))
    assert s02 == pytest.approx(1.0, rel=0.05) and d0 > 100
    changed = np.append(estimates[:30], [400.0, 900.0])  # two quantities that moved: left out, the prior kept
    s02, d0, outlying = scatter_prior(changed, np.full(changed.size, 9.0))
    assert list(np.flatnonzero(outlying)) == [30, 31] and s02 == pytest.approx(2.0, rel=0.5) and d0 > 3


def test_the_fit_and_its_t_are_weighted_least_squares() -> None:
    """Each quantity's best candidate refitted by numpy's lstsq on the whitened design (all
    recordings, then each left out), with the scan's own prior: the same fitted values and the
    same weakest moderated t."""
    rng = np.random.default_rng(2)
    values, stds = _arm(rng, q=12)
    values[6:, 0] += 20 * stds[:, 0].mean()
    times = np.cumsum(rng.uniform(0.5, 1.5, values.shape[0]))
    result = scan(values, stds, times)
    assert result.kind[0] == STEP and result.first[0] == 6
    d0 = np.where(result.wanders, 0.0, result.prior_df)
    s02 = result.prior_variance
    for c in range(values.shape[1]):
        k = int(result.first[c])
        z = (np.arange(10) >= k).astype(float) if result.kind[c] == STEP else np.maximum(times - times[k - 1], 0.0)
        design = np.column_stack([np.ones(10), z]) / stds[:, c:c + 1]
        (a, b), *_ = np.linalg.lstsq(design, values[:, c] / stds[:, c], rcond=None)
        assert result.before[c] == pytest.approx(a, rel=1e-8) and result.after[c] == pytest.approx(a + b * z[-1], rel=1e-8)
        ts = []
        for j in range(10):
            keep = np.arange(10) != j
            (_, bj), rss, *_ = np.linalg.lstsq(design[keep], values[keep, c] / stds[keep, c], rcond=None)
            lam = (d0[c] * s02 + rss[0]) / (d0[c] + 7)
            ts.append(abs(bj) / np.sqrt(lam * np.linalg.inv(design[keep].T @ design[keep])[1, 1]))
        assert result.statistic[c] == pytest.approx(np.sign(b) * min(ts), rel=1e-7)


def _false_alarms(fleets: int, seed: int, wild: bool) -> int:
    """Fleets of 6 arms x 30 quantities x 10 recordings, nothing changing: how many report a change."""
    rng = np.random.default_rng(seed)
    alarms = 0
    for _ in range(fleets):
        scans = []
        for _ in range(6):
            values, stds = _arm(rng, s0=float(rng.uniform(0.8, 3.0)), d0=float(rng.uniform(4.0, 30.0)))
            if wild:
                values[rng.integers(10), rng.integers(30)] += 15 * stds.mean()  # a wild run
                stds = stds * rng.uniform(1 / 3, 3, stds.shape)  # the stds off, recording by recording
            scans.append(scan(values, stds, np.arange(10.0) + rng.uniform(0, 0.3, 10)))
        total = np.array([sum(int(s.candidates.sum()) for s in scans)])
        alarms += any((family_wise(s.p, total) < ALPHA).any() for s in scans)
    return alarms


@pytest.mark.parametrize("wild", [False, True], ids=["designed-model", "wild-runs-and-wrong-stds"])
def test_no_change_fleets_raise_few_false_alarms(wild: bool) -> None:
    fleets = 300
    alarms = _false_alarms(fleets, 3 + wild, wild)
    print(f"\n{alarms} of {fleets} no-change fleets reported a change (designed family-wise rate {ALPHA})")
    assert alarms <= 3 * ALPHA * fleets  # 9 of 300: expected at most 3 at the designed rate (Bonferroni is conservative)


def test_one_wild_run_is_not_a_change() -> None:
    rng = np.random.default_rng(5)
    for k in range(10):
        for size in (15, 50, 1000):
            values, stds = _arm(rng)
            values[k, 0] += size * stds[k, 0]
            result = scan(values, stds)
            assert family_wise(result.p[:1], result.candidates)[0] > ALPHA, f"a wild run ({size} std) at recording {k + 1} made a change"


def test_a_step_and_a_drift_are_found_where_they_began() -> None:
    rng = np.random.default_rng(6)
    values, stds = _arm(rng, s0=1.0, d0=20.0)
    values[5:, 3] -= 12 * stds[:, 3].mean()  # a step down from recording 6
    values[3:, 7] += 4 * stds[:, 7].mean() * np.arange(1, 8)  # a drift up from recording 4
    result = scan(values, stds, np.arange(10.0))
    adjusted = family_wise(result.p, result.candidates)
    found = set(np.flatnonzero(adjusted < ALPHA))
    assert found == {3, 7}, found
    assert (result.kind[3], result.first[3]) == (STEP, 5) and result.after[3] < result.before[3]
    assert result.kind[7] == DRIFT and abs(int(result.first[7]) - 3) <= 1 and result.after[7] > result.before[7]


def test_a_change_needs_recordings_on_either_side() -> None:
    rng = np.random.default_rng(7)
    values, stds = _arm(rng, n=2 * MIN_SEGMENT - 1)
    values[-1] += 100 * stds[-1]
    result = scan(values, stds)
    assert (result.candidates == 0).all() and (result.kind == 0).all()
