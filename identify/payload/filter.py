"""The record's own clock: position, velocity and acceleration of a stream on its time stamps.

The payload estimator's derivatives (:mod:`identify.payload`): the degree-4 least-squares
polynomial through every record within ``HALF_WINDOW_S`` of each one, a window of fixed
*time* on the records' own stamps (:func:`identify.differentiation.local_polynomial`), causal
on a stream here (:class:`StreamFilter`: each record's
equations once its window has come, the same however the records are batched; gaps restart
the derivatives, rate changes are counted).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..differentiation import HALF_WINDOW_S, local_polynomial
from ..spatial import Array

GAP_RATIO, RATE_MEDIAN, RATE_CHANGE_RATIO = 3.0, 9, 1.5
"""A step 3 times the median of the 9 before it is a gap (the derivatives restart); the
median of 9 steps moving by 1.5 times is a rate change (counted)."""


def _rolling_median(steps: Array, k: int) -> Array:
    """The median of each run of ``k`` consecutive steps (len(steps) - k + 1 values)."""
    return np.median(np.lib.stride_tricks.sliding_window_view(steps, k), axis=1)


def _within(a: float, b: float, ratio: float) -> bool:
    """Whether two steps are the same rate: neither is ``ratio`` times the other."""
    return bool(a <= ratio * b and b <= ratio * a)


@dataclass
class StreamFilter:
    """Causal :func:`local_polynomial` of a stream: records (t, positions, torques) in, in
    batches of any size; out, each record's smoothed position and torque with its velocity
    and acceleration, once every record within ``half_window_s`` after it has come (the
    equations lag the stream by the half window). The same records give the same equations
    however they are batched.

    A step longer than ``GAP_RATIO`` times the typical step (the median of the
    ``RATE_MEDIAN`` steps before it) or longer than the half window is a gap: the derivatives
    start again after it. A rate change (the typical step moving by ``RATE_CHANGE_RATIO``)
    is counted in ``rate_changes`` and needs nothing else: the windows are spans of time.
    The typical step is read from windows whose two halves agree on the rate, so a window
    across the change counts no rate of its own. Jitter moves single steps, not their
    median or mean, so jittery stamps are neither.
    """

    half_window_s: float = HALF_WINDOW_S
    t: Array = field(default_factory=lambda: np.zeros(0))
    x: Array = field(default_factory=lambda: np.zeros((0, 0)))
    seg_start: float | None = None
    last_centre: float = -np.inf
    last_t: float | None = None
    steps: Array = field(default_factory=lambda: np.zeros(0))  # the last RATE_MEDIAN steps, across restarts
    typical: float | None = None  # the typical step when the rate was last counted
    rate_changes: int = 0
    gaps: int = 0

    def reset(self) -> None:
        self.t = np.zeros(0)
        self.x = np.zeros((0, 0))
        self.seg_start = None
        self.last_centre = -np.inf

    def _steps(self, t: Array) -> Array:
        """Which records follow a gap; counts rate changes."""
        first = np.array([np.nan if self.last_t is None else self.last_t])
        step = np.diff(np.concatenate([first, t]))
        finite = np.isfinite(step)
        hist = np.concatenate([self.steps, step[finite]])
        pos = self.steps.size + np.cumsum(finite) - 1  # index of each record's step in hist
        gap = finite & (step > self.half_window_s)
        if hist.size >= RATE_MEDIAN:
            med = _rolling_median(hist, RATE_MEDIAN)  # med[i]: steps i .. i + RATE_MEDIAN - 1
            have = finite & (pos >= RATE_MEDIAN)
            before = np.full(t.size, np.inf)
            before[have] = med[pos[have] - RATE_MEDIAN]
            gap |= step > GAP_RATIO * before
            self._count_rate_changes(hist, med, max(0, self.steps.size - RATE_MEDIAN + 1))
        self.steps = hist[-RATE_MEDIAN:]
        self.last_t = float(t[-1])
        return gap

    def _count_rate_changes(self, hist: Array, med: Array, first: int) -> None:
        """The typical step of each window of ``RATE_MEDIAN`` steps from ``first`` on is their
        mean (a jittered stamp moves two steps by opposite amounts: the mean keeps the rate
        where a median of 9 jittered steps drifts by half), read only where the two halves of
        the window agree on the rate (a window across a change, 2 ms then 10 ms, has a mean of
        neither) and no step in it is a gap."""
        half = (RATE_MEDIAN + 1) // 2
        sums = np.concatenate([[0.0], np.cumsum(hist)])
        mean = (sums[RATE_MEDIAN:] - sums[:-RATE_MEDIAN]) / RATE_MEDIAN
        halves = (sums[half:] - sums[:-half]) / half  # a window's first half: halves[i], its last: halves[i + RATE_MEDIAN - half]
        longest = np.max(np.lib.stride_tricks.sliding_window_view(hist, RATE_MEDIAN), axis=1)
        for i in range(first, mean.size):
            if longest[i] > GAP_RATIO * med[i] or not _within(halves[i], halves[i + RATE_MEDIAN - half], RATE_CHANGE_RATIO):
                continue
            m = float(mean[i])
            if self.typical is None:
                self.typical = m
            elif not _within(m, self.typical, RATE_CHANGE_RATIO):
                self.rate_changes += 1
                self.typical = m

    def push(self, t: Array, q: Array, tau: Array) -> tuple[Array, Array, Array, Array, Array, Array, Array]:
        """Returns ``(t, q, qd, qdd, tau, done_at, step)`` of the equations this batch completes,
        ``done_at`` the index in the batch of the record that completed each and ``step`` the
        time since the record before it (the span each equation stands for: the records' own,
        whatever came before the stream's start or a restart)."""
        nj = q.shape[1]
        x = np.hstack([q, tau])
        parts = []
        if t.size:
            gap = self._steps(t)
            cuts = np.concatenate([[0], np.flatnonzero(gap), [t.size]])
            for a, b in zip(cuts[:-1], cuts[1:]):
                if b > a:
                    if gap[a]:
                        self.gaps += 1
                        self.reset()
                    parts.append(self._segment(t[a:b], x[a:b], int(a)))
        parts = [p for p in parts if p[0].size]
        if not parts:
            z = np.zeros((0, nj))
            return np.zeros(0), z, z, z, z, np.zeros(0, int), np.zeros(0)
        tt, x0, x1, x2, done, step = (np.concatenate([p[i] for p in parts]) for i in range(6))
        return tt, x0[:, :nj], x1[:, :nj], x2[:, :nj], x0[:, nj:], done, step

    def _segment(self, t: Array, x: Array, first: int) -> tuple[Array, Array, Array, Array, Array, Array]:
        if self.seg_start is None:
            self.seg_start = float(t[0])
        bt = np.concatenate([self.t, t])
        bx = x if self.x.shape[0] == 0 else np.vstack([self.x, x])
        hw = self.half_window_s
        # the next centres whose windows are complete: every record up to t_c + hw has come
        c0 = int(np.searchsorted(bt, self.last_centre, "right"))
        c1 = int(np.searchsorted(bt, bt[-1] - hw, "right"))
        res = (np.zeros(0), np.zeros((0, bx.shape[1])), np.zeros((0, bx.shape[1])), np.zeros((0, bx.shape[1])), np.zeros(0, int), np.zeros(0))
        if c1 > c0:
            centres = np.arange(c0, c1)
            self.last_centre = float(bt[c1 - 1])
            x0, x1, x2, ok = local_polynomial(bt, bx, centres, hw, span=(self.seg_start, np.inf),  # complete: c1 says so
                                              origin=self.seg_start)
            if ok.any():
                tc = bt[centres][ok]
                done = first + np.minimum(np.searchsorted(t, tc + hw, "left"), t.size - 1)
                res = (tc, x0[ok], x1[ok], x2[ok], done, tc - bt[centres - 1][ok])  # ok: two records before each centre
        # keep what the windows of the centres still to come need
        nxt = int(np.searchsorted(bt, self.last_centre, "right"))
        t_next = bt[nxt] if nxt < bt.size else bt[-1]
        keep = max(0, int(np.searchsorted(bt, t_next - hw, "left")) - 2)  # 2 more: the windows' edges are decided on relative times
        self.t, self.x = bt[keep:], bx[keep:]
        return res
