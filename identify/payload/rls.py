"""On-line payload estimation: recursive least squares on what the arm model leaves over.

Khosla's on-line strategy: with the arm's own parameters known, a payload rigidly held by
the last link only adds to that link's ten parameters, so (eq. 18)

.. math:: \\tau - M(q, \\dot q, \\ddot q)\\,\\phi_{arm} = M_{:,N}(q, \\dot q, \\ddot q)\\,\\phi_p

with ``M_{:,N}`` the regressor columns of link N (every joint's row) and ``phi_p`` the
payload's ``m, m s, I`` about the last link's frame. Each sample gives N equations; the
equations of each ``BLOCK_S`` (10 ms) of the arm's time are folded in together, in
information form (:meth:`PayloadRLS._fold_information`).

- **The record's own clock.** Position, velocity and acceleration are the degree-4
  least-squares polynomial through the records within ``HALF_WINDOW_S`` (50 ms) of each
  record, on their time stamps (:func:`identify.differentiation.local_polynomial`): a window of fixed *time*, so the
  filter's bias does not grow with the sample period (the 5-point filter applied twice
  spanned 80 ms at 10 ms and biased the mass by 1 %). The torque is filtered alike. Each
  equation is made once every record of its window has come (50 ms late), the same however
  the records are batched. A step ``GAP_RATIO`` times the typical one is a gap (the
  derivatives restart); the typical step moving by ``RATE_CHANGE_RATIO`` is a rate change,
  counted in ``rate_changes_``; jitter is neither. No configured period enters.
- **Honest covariance.** RLS takes its equations as independent; records 1 ms apart are
  not. Each joint's innovations' correlation time ``tau`` is measured from their
  autocorrelation (``correlation_time_``), and each equation counts for its share
  ``dt / tau`` of their mean: the effective sample size of a correlated series. The
  covariance is then that of the independent samples the motion gave, at any record rate,
  and the chi-square test below counts its degrees of freedom the same way.
- **Information form.** Each joint's equations since the last restart are summed apart
  and weighed by that joint's noise as known now (:meth:`PayloadRLS._fold_information`):
  every equation alike, however the noise was learned meanwhile.
- **Forgetting** is a factor per 2 ms of the arm's time (``forgetting ** (dt / 2 ms)``)
  on the equations, never on the prior, and applies only while the arm moves: at rest the
  equations carry no new information about most directions and forgetting would inflate
  the covariance (wind-up). The covariance never grows past its prior.
- **Gross errors and payload changes.** Before an update each equation's normalized
  innovation squared is tested: beyond ``GROSS_NIS`` (5 sigma rms) it is not taken (a
  stalled first cycle, a glitch). A change of payload shows as the innovations of the last
  ``change_window_s`` averaging over ``change_threshold`` times the level of the second
  before: the covariance is reset to the prior and the estimate moves to the new payload
  at once. Innovations that stay a few times their noise after an attach (an effect the
  model lacks that grows with the load) are noise to learn, not a new payload each time.
- **Noise** of each joint's equation is tracked from the innovations (time constant
  ``noise_time_constant_s`` of the arm's time, outliers clipped at 3 sigma), starting from
  the identification's per-joint sigma.
- **Physically possible estimates.** What is published is the projection of the estimate
  onto the payloads that can exist (mass >= 0 and the pseudo-inertia
  ``[[tr(I)/2 1 - I, m s], [m s^T, m]]`` positive semidefinite; Wensing et al. 2017), in the
  metric of the estimate's covariance: directions the data pin down move least. The
  unconstrained estimate is kept beside it. Each projection is a compiled barrier method
  (:mod:`identify.kernels.projection`), the same live and on replay.
- **Converged** means: the mass (and, with a mass, the centre of mass) excited, their
  standard deviations below ``MASS_STD_KG + MASS_STD_REL m`` and ``COM_STD_M``, and the
  whitened innovations of the last ``CONSISTENCY_WINDOW_S`` no larger than their covariance
  allows (a chi-square test at 0.1 %).
- **Reference mode** (:class:`ReferenceRun`): with a run of the same trajectory without the
  payload, each sample's residual has the unloaded run's residual at the same position
  taken off, so that arm-model and friction errors cancel.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from armid.schema.json_text import json_safe

from ..differentiation import HALF_WINDOW_S
from ..robot import inertial_from_parameters
from ..spatial import Array
from .arm import ArmModel, ReferenceRun, arm_model_from_identification, identification_document
from .band import MIN_BATCHES, Batches, batch_means_covariance, torque_constant_covariance
from .filter import StreamFilter
from .projection import project_feasible, project_feasible_many, pseudo_inertia

__all__ = ["ArmModel", "PayloadRLS", "ReferenceRun", "arm_model_from_identification", "identification_document",
           "project_feasible", "project_feasible_many", "pseudo_inertia"]
"""The estimator's public names; the arm model, the stream's filter and the projection onto
possible payloads live in the other modules of ``identify/payload/``, the derivatives on the
records' stamps in :mod:`identify.differentiation`."""

MIN_SPEED = 0.02
REVERSAL_MARGIN_S = 0.025
"""A joint's equation is left out while the joint would stop or reverse within this much of the
arm's time (``|qd| < |qdd| * REVERSAL_MARGIN_S``): ``sign(qd)`` is wrong there."""
CHANGE_CLEAR_S = HALF_WINDOW_S
"""The change test (:meth:`PayloadRLS._changed`) reads only equations whose derivative window
(+-``HALF_WINDOW_S``) is clear of a stop or reversal: a window that reaches one holds the
friction's step smeared across it. With the 25 ms of the estimate, an arm coming to rest at
the end of a run (joints stopping one after another) made a 30 ms jump of 20 times the noise,
read as a new payload 0.5 s before the end. The estimate keeps those equations: near a
reversal the acceleration is largest, and leaving them out raised the mass std by 45 %."""
PRIOR_STD = np.array([5.0, 0.5, 0.5, 0.5, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05])
"""Prior standard deviations of ``m, msx, msy, msz, Ixx..Izz`` (kg, kg m, kg m^2): a
payload of up to a few kg within half a metre of the flange."""
PARAMETER_NAMES = ("m", "msx", "msy", "msz", "Ixx", "Ixy", "Ixz", "Iyy", "Iyz", "Izz")
FORGETTING_STEP_S = 0.002
"""The forgetting factor is given per this much of the arm's time (0.998: a memory of 1 s)."""
BLOCK_S = 0.01
"""The equations of each 10 ms of the arm's time are folded in together."""
CHANGE_WINDOW_S = 0.05
"""A new payload shows as innovations too large over this much of the arm's time."""
NOISE_TIME_CONSTANT_S = 2.0
"""Each joint's noise is learned over this much of the arm's time."""
CHANGE_BASELINE_S = 1.0
"""... over this much of the arm's time before it (see :meth:`PayloadRLS._changed`)."""
GROSS_NIS = 25.0
"""Normalized innovation squared per equation beyond which an update is not taken (5 sigma rms)."""
MASS_STD_KG, MASS_STD_REL, COM_STD_M = 0.02, 0.02, 0.005
"""Converged needs std(mass) <= 0.02 kg + 2 % of the mass and std(centre of mass) <= 5 mm per axis."""
PUBLISH_ATOL = 1e-3
"""Tolerance of the projection of what is published (:func:`project_feasible`)."""
MIN_MASS_FOR_COM_KG = 0.1
"""Below this mass no centre of mass or inertia is reported (they are divided by the mass)."""
CONSISTENCY_WINDOW_S = 1.0
INITIAL_CORRELATION_S = HALF_WINDOW_S
"""The innovations' correlation time until it is measured: about the derivative window's."""
CORRELATION_MEMORY_S, CORRELATION_UPDATE_S, CORRELATION_MIN_S, CORRELATION_MAX_LAG_S = 3.0, 0.25, 1.0, 0.5
"""Correlation times are measured on the last 3 s of innovations (once there is 1 s), every
0.25 s of the arm's time, over lags up to 0.5 s."""


class PayloadRLS:
    """Recursive least squares on the payload's parameters (scikit-learn style).

    Hyperparameters only here; ``fit`` starts over, ``partial_fit`` goes on; learned state
    ends in ``_``. See the module docstring for the method. No sample period: every update
    uses the records' time stamps, and the equations of each ``block_s`` of the arm's time
    are folded in together (one 10 x 10 update per block, whatever the record rate).
    """

    def __init__(self, arm: ArmModel, *, forgetting: float = 0.998, moving_rad_s: float = 0.05, change_window_s: float = CHANGE_WINDOW_S,
                 change_threshold: float = 8.0, prior_std: Array | None = None, noise_time_constant_s: float = NOISE_TIME_CONSTANT_S,
                 reference: ReferenceRun | None = None, block_s: float = BLOCK_S) -> None:
        self.arm = arm
        self.forgetting = forgetting
        self.moving_rad_s = moving_rad_s
        self.change_window_s = change_window_s
        self.change_threshold = change_threshold
        self.prior_std = PRIOR_STD if prior_std is None else np.asarray(prior_std, float)
        self.noise_time_constant_s = noise_time_constant_s
        self.reference = reference
        self.block_s = block_s

    def _start(self) -> None:
        if not 0.0 < self.forgetting <= 1.0:
            raise ValueError(f"forgetting must be in (0, 1], got {self.forgetting}")
        nj = self.arm.robot.n_joints
        self.theta_ = np.zeros(10)
        self.P_ = np.diag(self.prior_std**2)
        self._anchor = np.zeros(10)  # the estimate at the last (re)start: the prior's centre
        self._joint_info = np.zeros((nj, 10, 10))  # per joint, the equations since, before 1/r (scaled parameters)
        self._joint_score = np.zeros((nj, 10))
        self._all_info = np.zeros((nj, 10, 10))  # the same sums, never faded: the run's final answer
        self._all_score = np.zeros((nj, 10))
        self._batches = Batches(nj)
        self.excited_s_ = 0.0  # moving time folded in since the last (re)start
        self.torque_constant_std_ = np.array([j.torque_constant_std for j in self.arm.robot.joints])
        self.filter_ = StreamFilter()
        self.noise_var_ = np.maximum(np.asarray(self.arm.joint_sigma, float), 1e-6) ** 2
        self.correlation_time_ = np.full(nj, INITIAL_CORRELATION_S)
        self._pending: dict[str, Array] | None = None
        self._folded = 0
        self._change: deque[tuple[float, float, float, int]] = deque()  # per block: (first time, last time, nis, dof)
        self._window: deque[tuple[float, float, float, int, int]] = deque()  # per block: (time, nis, dof, rejected, rows), weighted
        self._innovations: deque[tuple[Array, Array]] = deque()  # per block: (times, whitened innovations, NaN if unused)
        self._next_correlation_t: float | None = None
        self.n_updates_ = 0
        self.resets_ = 0
        self.rejected_ = 0
        self.time_s_ = float("nan")
        self.innovation_ = np.zeros(0)
        self._projected: tuple[Any, Array] | None = None

    @property
    def rate_changes_(self) -> int:
        return self.filter_.rate_changes

    def fit(self, t: Array, q: Array, tau: Array) -> PayloadRLS:
        self._start()
        return self.partial_fit(t, q, tau)

    def restart_filter(self) -> None:
        """Samples were skipped: the derivatives start again (the estimate is kept)."""
        if not hasattr(self, "theta_"):
            self._start()
        self.filter_.reset()
        if self.reference is not None:
            self.reference.restart()

    def warm(self) -> None:
        """Run every code path once on a copy (imports, first-call costs) before the arm moves."""
        robot = self.arm.robot
        clone = PayloadRLS(self.arm, forgetting=self.forgetting, prior_std=self.prior_std)
        t = np.arange(80) * 0.002
        q = 0.1 * np.sin(np.outer(t, np.arange(1, robot.n_joints + 1)))
        clone.fit(t, q, np.zeros_like(q)).estimate()
        project_feasible(-np.ones(10) * 0.01, np.eye(10))

    def partial_fit(self, t: Array, q: Array, tau: Array, checkpoints: Iterable[int] = (),
                    on_checkpoint: Callable[[int], None] | None = None) -> PayloadRLS:
        """Fold in consecutive samples: times (n,) in s, strictly increasing, positions and
        torques (n, N).

        ``on_checkpoint(k)`` is called once sample ``k`` of this batch has been folded in,
        for each ``k`` in ``checkpoints``: a stream publishes there, and a batch of any size
        gives the same estimates as one sample at a time.
        """
        if not hasattr(self, "theta_"):
            self._start()
        t, q, tau = np.atleast_1d(np.asarray(t, float)), np.atleast_2d(q), np.atleast_2d(tau)
        n = t.shape[0]
        if n == 0:
            return self
        prev = self.filter_.last_t
        order = np.diff(t if prev is None else np.concatenate([[prev], t]))
        bad = np.flatnonzero(~(order > 0))
        if bad.size:
            k = int(bad[0]) + (0 if prev is None else -1) + 1
            before = t[k - 1] if k >= 1 else prev
            raise ValueError(f"time {t[k]:.6g} s is not after the previous record's {before:.6g} s")
        ts, qs, qds, qdds, taus, done, steps = self.filter_.push(t, q, tau)
        base = 0 if self._pending is None else self._pending["t"].size  # rows before this batch's
        if ts.size:
            self._add_rows(ts, qs, qds, qdds, taus, steps)
        wanted = set(checkpoints)
        for k in sorted(k for k in wanted if 0 <= k < n - 1) + [n - 1]:
            self._fold_complete_blocks(base + int(np.searchsorted(done, k, "right")))
            if k in wanted and on_checkpoint is not None:
                on_checkpoint(k)
        if self._pending is not None and self._folded:
            self._pending = {key: v[self._folded :] for key, v in self._pending.items()}
            self._folded = 0
        return self

    def _add_rows(self, ts: Array, qs: Array, qds: Array, qdds: Array, taus: Array, dts: Array) -> None:
        """The equations of new rows, waiting for their block to be complete; ``dts``, the time
        each stands for (since the record before it)."""
        model, h_all = self.arm.torque_and_payload_columns(qs, qds, qdds)
        residual = taus - model
        # a joint's equation is left out while it is near rest or reversing: sign(qd) is
        # wrong there (as in identification), and one wrong Coulomb step looks like a new payload
        sliding = np.abs(qds) >= np.maximum(MIN_SPEED, np.abs(qdds) * REVERSAL_MARGIN_S)
        clear = np.abs(qds) >= np.maximum(MIN_SPEED, np.abs(qdds) * CHANGE_CLEAR_S)
        if self.reference is not None:
            for i in range(ts.size):
                ref, dist = self.reference.lookup(float(ts[i]), qs[i])
                residual[i] -= ref
                if dist > self.reference.tolerance_rad:
                    sliding[i] = False
        clear &= sliding
        moving = np.abs(qds).max(axis=1) > self.moving_rad_s
        rows = {"t": ts, "block": np.floor(ts / self.block_s), "h": h_all, "y": residual, "use": sliding, "clear": clear, "moving": moving, "dt": dts}
        if self._pending is None:
            self._pending = rows
        else:
            self._pending = {key: np.concatenate([self._pending[key], v]) for key, v in rows.items()}

    def _fold_complete_blocks(self, available: int) -> None:
        """Fold the blocks of the first ``available`` pending rows that a later row closes."""
        rows = self._pending
        if rows is None or available <= self._folded:
            return
        block = rows["block"]
        stop = int(np.searchsorted(block[:available], block[available - 1], "left"))
        if stop <= self._folded:
            return
        edges = np.flatnonzero(np.diff(block[self._folded : stop])) + self._folded + 1
        for a, b in zip([self._folded, *edges.tolist()], [*edges.tolist(), stop]):
            self._fold_block(a, b)
        self._folded = stop
        self.time_s_ = float(rows["t"][stop - 1])

    def _nis(self, h: Array, nu: Array, p: Array, r: Array) -> Array:
        """Normalized innovation squared of each row, ``nu^T (h P h^T + R)^-1 nu``."""
        s = (h @ p) @ h.transpose(0, 2, 1)
        s += np.eye(r.size) * r
        return np.einsum("mj,mj->m", nu, np.linalg.solve(s, nu[..., None])[..., 0])

    def _changed(self, ts: Array, nis: Array, dof: Array) -> bool:
        """Whether the payload changed in the last ``change_window_s`` (whole blocks): their
        innovations average over ``change_threshold`` times the level of the innovations of
        the ``CHANGE_BASELINE_S`` before (the median block's NIS per equation, at least 1).

        A change is a jump against what came before. An effect the model lacks that grows
        with the new payload (friction of a loaded gear, torque constants a few per cent
        off) keeps every innovation after an attach a few times its noise until the noise
        is learned; against the absolute level it read as a new payload again and again,
        each time throwing the estimate away (four resets in 1.3 s of one attach)."""
        now = float(ts[-1])
        self._change.append((float(ts[0]), now, float(nis.sum()), int(dof.sum())))
        while self._change[0][1] < now - self.change_window_s - CHANGE_BASELINE_S:
            self._change.popleft()
        window = [c for c in self._change if c[1] >= now - self.change_window_s]
        if now - window[0][0] < 0.8 * self.change_window_s:
            return False
        before = [c[2] / c[3] for c in self._change if c[1] < now - self.change_window_s and c[3] > 0]
        level = max(1.0, float(np.median(before))) if before else 1.0
        changed = sum(c[2] for c in window) > self.change_threshold * level * sum(c[3] for c in window)
        if changed:  # the change's own blocks are no baseline for the next one
            for _ in window:
                self._change.pop()
        return changed

    def _fold_block(self, a: int, b: int) -> None:
        rows = self._pending
        assert rows is not None
        use = rows["use"][a:b]
        dof = use.sum(axis=1)
        live = dof > 0
        if not live.any():
            return
        ts, dts, moving, h, y, clear = (rows[key][a:b] if live.all() else rows[key][a:b][live] for key in ("t", "dt", "moving", "h", "y", "clear"))
        if not live.all():
            use, dof = use[live], dof[live]
        h = h * use[..., None]
        theta, p, r = self.theta_, self.P_, self.noise_var_
        prior_var = self.prior_std**2
        nu = (y - h @ theta) * use
        nis = self._nis(h, nu, p, r)
        nis_clear = nis if np.array_equal(clear, use) else self._nis(h * clear[..., None], nu * clear, p, r)
        if self._changed(ts, nis_clear, clear.sum(axis=1)):
            p = np.diag(prior_var)  # start over from the prior, keep the estimate
            self._restart_information()
            self.resets_ += 1
            nis = self._nis(h, nu, p, r)
        gross = nis > GROSS_NIS * dof
        take = ~gross
        self.rejected_ += int(gross.sum())
        if take.any():
            moving_s = float(dts[take & moving].sum())
            theta, p = self._fold_information(h, y, use & take[:, None], dts, moving_s, r)
            # the noise this estimator sees: E[e^2] = r - (h P+ h^T) for the residual e after
            # the update (unbiased whatever P is); outliers clipped at 3 sigma
            post = nu - (h @ (theta - self.theta_)) * use
            seen = np.minimum(post**2 + ((h @ p) * h).sum(axis=2), 9.0 * r)
            counted = use & take[:, None]
            span = (dts[:, None] * counted).sum(axis=0)
            mean_seen = (seen * dts[:, None] * counted).sum(axis=0) / np.maximum(span, 1e-300)
            rate = np.minimum(1.0, span / self.noise_time_constant_s)
            r = np.where(span > 0, r + rate * (mean_seen - r), r)
            self.n_updates_ += int(take.sum())
            self.innovation_ = nu[take][-1][use[take][-1]]
        # the chi-square window: each row weighted by its share of the correlation time
        share = np.minimum(1.0, dts / float(np.mean(self.correlation_time_)))
        # gross errors count against consistency only where the model holds: a row whose windows
        # are clear of every stop and reversal (near one, the smeared friction step is expected)
        row_clear = clear.sum(axis=1) == dof
        self._window.append((float(ts[-1]), float((nis * share)[take].sum()), float((dof * share)[take].sum()),
                             int((gross & row_clear).sum()), int(row_clear.sum())))
        while self._window and self._window[0][0] < ts[-1] - CONSISTENCY_WINDOW_S:
            self._window.popleft()
        white = np.where(use & take[:, None], nu / np.sqrt(self.noise_var_), np.nan)
        self._innovations.append((ts, white))
        self.theta_, self.P_, self.noise_var_ = theta, p, r
        self._update_correlation_time(float(ts[-1]))

    def _restart_information(self) -> None:
        """A new payload: the equations so far are about the old one; the estimate stays as
        the prior's centre."""
        self._anchor = self.theta_.copy()
        self._joint_info[:] = 0.0
        self._joint_score[:] = 0.0
        self._all_info[:] = 0.0
        self._all_score[:] = 0.0
        self._batches.clear()
        self.excited_s_ = 0.0

    def _fold_information(self, h: Array, y: Array, use: Array, dts: Array, moving_s: float, r: Array) -> tuple[Array, Array]:
        """Exponentially weighted least squares in information form: the estimate and its
        covariance from the prior (centred on the estimate at the last restart) and each
        joint's equations since, each joint weighed by its noise as known now.

        Each equation counts for the share ``dt / tau`` of the innovations' correlation time
        it covers: 1 ms and 10 ms records of one motion carry the same information. Keeping
        each joint's sums apart and dividing by its noise and ``tau`` only here weighs every
        equation since the restart alike, which a recursive update cannot: folded with the
        noise of its own time, what came just after an attach (when the noise was the
        unloaded arm's) outweighed all that came later (when the model's errors had grown
        with the load). ``tau`` is one for all joints (their mean): it counts rows, and
        must not weigh joints against each other; per joint, a joint whose innovations
        are white got twenty times the weight of one whose are a model error, and torque
        constants a few per cent off between them moved the estimate. Together, against a
        reference run with those errors: 2 kg read 2.25 kg, its centre of mass 4 cm off,
        2 s after the attach; now 1.98 kg and 0.2 cm. Forgetting (``forgetting`` per 2 ms
        while the arm moves) fades the equations, never the prior: the covariance never
        grows past it (no wind-up)."""
        d = self.prior_std
        hs = h * d  # scaled parameters: x = theta / d, the prior the identity
        w = dts[:, None] * use  # divided by the correlation time at the solve
        if moving_s > 0:
            fade = self.forgetting ** (moving_s / FORGETTING_STEP_S)
            self._joint_info *= fade
            self._joint_score *= fade
        e0 = (y - h @ self._anchor) * use
        info, score = np.einsum("mjk,mjl,mj->jkl", hs, hs, w), np.einsum("mjk,mj->jk", hs, w * e0)
        self._joint_info += info
        self._joint_score += score
        self._all_info += info
        self._all_score += score
        self._batches.add(info, score, moving_s)
        self.excited_s_ += moving_s
        return self._solve(self._joint_info, self._joint_score, r)

    def _solve(self, joint_info: Array, joint_score: Array, r: Array) -> tuple[Array, Array]:
        """The estimate and its covariance from the prior and per-joint sums (scaled
        parameters), each joint weighed by its noise ``r`` and the correlation time."""
        d, w = self.prior_std, self._joint_weights(r)
        ps = np.linalg.inv(np.eye(10) + np.einsum("jkl,j->kl", joint_info, w))
        ps = 0.5 * (ps + ps.T)
        theta = self._anchor + d * (ps @ np.einsum("jk,j->k", joint_score, w))
        return theta, ps * np.outer(d, d)

    def _joint_weights(self, r: Array) -> Array:
        return np.asarray(1.0 / (r * float(np.mean(self.correlation_time_))))

    def _information(self, joint_info: Array) -> Array:
        """Each joint's information on the parameters themselves (its weighted sums unscaled)."""
        d = self.prior_std
        return np.asarray(joint_info * self._joint_weights(self.noise_var_)[:, None, None] / np.outer(d, d))

    def _update_correlation_time(self, now: float) -> None:
        """Each joint's integrated autocorrelation time of the innovations over the last
        ``CORRELATION_MEMORY_S`` (every ``CORRELATION_UPDATE_S`` of the arm's time).

        RLS takes its equations as independent; records 1 ms apart are not (the derivative
        window alone spans 100 ms, and a model error lasts as long as the pose). With
        correlation time ``tau``, n rows ``dt`` apart carry the information of ``n dt / tau``
        independent ones (the effective sample size of a correlated series), so each row is
        weighted ``dt / tau``: the covariance is the one of independent samples of the same
        motion, at any record rate. ``tau = dt (1 + 2 sum rho_k)``, the sum over the initial
        positive autocorrelations (about zero, not the mean: a persistent bias is a long
        correlation), up to lags of ``CORRELATION_MAX_LAG_S``.
        """
        while self._innovations and self._innovations[0][0][-1] < now - CORRELATION_MEMORY_S:
            self._innovations.popleft()
        if self._next_correlation_t is None:
            self._next_correlation_t = now + CORRELATION_UPDATE_S
        if now < self._next_correlation_t:
            return
        self._next_correlation_t = now + CORRELATION_UPDATE_S
        t = np.concatenate([b[0] for b in self._innovations])
        if t.size < 20 or t[-1] - t[0] < CORRELATION_MIN_S:
            return
        x = np.concatenate([b[1] for b in self._innovations])
        dt = float(np.median(np.diff(t)))
        m = np.isfinite(x)
        x0 = np.where(m, x, 0.0)
        n = t.size
        lags = min(n - 1, max(1, int(round(CORRELATION_MAX_LAG_S / dt))))
        nfft = 1 << int(np.ceil(np.log2(2 * n)))
        fx, fm = np.fft.rfft(x0, nfft, axis=0), np.fft.rfft(m.astype(float), nfft, axis=0)
        c = np.fft.irfft(np.abs(fx) ** 2, nfft, axis=0)[: lags + 1]
        pairs = np.fft.irfft(np.abs(fm) ** 2, nfft, axis=0)[: lags + 1]
        enough = pairs > 0.25 * np.maximum(pairs[0], 1.0)
        cov = np.where(enough, c / np.maximum(pairs, 1.0), 0.0)
        for j in range(x.shape[1]):
            if pairs[0, j] < 20 or cov[0, j] <= 0:
                continue
            rho = cov[1:, j] / cov[0, j]
            stop = np.flatnonzero(~(rho > 0))
            k = int(stop[0]) if stop.size else rho.size
            self.correlation_time_[j] = dt * (1.0 + 2.0 * float(rho[:k].sum()))

    # --- what the estimate means ---
    @property
    def std_(self) -> Array:
        return np.sqrt(np.maximum(np.diag(self.P_), 0.0))

    @property
    def excited_(self) -> Array:
        """Per parameter: the data have told more than the prior (std below half of it)."""
        return self.std_ < 0.5 * self.prior_std

    def consistency(self) -> dict[str, Any]:
        """Chi-square test of the whitened innovations over the last second of the arm's time.

        Each row's normalized innovation squared counts for its share ``dt / tau`` of the
        innovations' correlation time (see :meth:`_update_correlation_time`): the sum is
        tested against the 99.9 % point of chi-square with as many degrees of freedom as the
        rows' equations count independent ones. One-sided: innovations larger than their
        covariance allows (a model error, a wrong clock) fail it; smaller ones mean the
        stated std is cautious. More than 2 % gross errors in the window fail it too, counted on
        the rows whose derivative windows are clear of every stop and reversal (``CHANGE_CLEAR_S``)."""
        rows = sum(w[4] for w in self._window)
        rejected = sum(w[3] for w in self._window)
        dof = sum(w[2] for w in self._window)
        if dof < 5:
            return {"consistent": False, "nis_per_dof": None, "equations": dof, "rejected": rejected}
        nis = sum(w[1] for w in self._window)
        ok = bool(nis <= _chi2_upper(dof)) and rejected <= 0.02 * rows
        return {"consistent": ok, "nis_per_dof": nis / dof, "equations": dof, "rejected": rejected}

    def feasible_(self) -> Array:
        """The published parameters: :func:`project_feasible` of ``theta_`` (cached per update)."""
        return self._projection(self.n_updates_ + self.resets_ + self.rejected_, self.theta_, self.P_)

    def _projection(self, equations: int, theta: Array, cov: Array) -> Array:
        """:func:`project_feasible` of ``theta``, reused while no equation came since the last."""
        key = (equations, theta.tobytes())
        if self._projected is None or self._projected[0] != key:
            self._projected = (key, project_feasible(theta, cov, atol=PUBLISH_ATOL))
        return self._projected[1]

    def snapshot(self) -> dict[str, Any]:
        """What :meth:`document` needs of the estimator's state now (copies)."""
        if not hasattr(self, "theta_"):
            self._start()
        p_sys = torque_constant_covariance(self.P_, self._information(self._joint_info), self.theta_, self.torque_constant_std_)
        return {"theta": self.theta_.copy(), "P": self.P_.copy(), "P_sys": p_sys, "time": self.time_s_, "consistency": self.consistency(),
                "updates": self.n_updates_, "resets": self.resets_, "rejected": self.rejected_, "rate_changes": self.rate_changes_}

    def final_estimate(self) -> dict[str, Any]:
        """The run's one answer (a replay's last document, ``"final": true``): least squares on
        every equation since the last restart (the attach, or the start), none forgotten, so
        the estimate over the whole excited part rather than the last second's. Its
        covariance is the batch means' of :func:`batch_means_covariance` (seconds of motion
        apart: the model error that moves the estimate with the trajectory counts) once there
        are ``MIN_BATCHES`` and it gives the mass more variance than the model does, else the
        model's; the torque constants' term is added as for every estimate."""
        if not hasattr(self, "theta_"):
            self._start()
        r = self.noise_var_
        theta, p_model = self._solve(self._all_info, self._all_score, r)
        scores = self._batches.scores_at((theta - self._anchor) / self.prior_std, self._joint_weights(r))
        d = self.prior_std
        p_batches = batch_means_covariance(p_model / np.outer(d, d), scores) * np.outer(d, d) if scores.shape[0] >= MIN_BATCHES else None
        batched = p_batches is not None and p_batches[0, 0] > p_model[0, 0]  # the larger of the two on the mass
        p = p_batches if batched and p_batches is not None else p_model
        p_sys = torque_constant_covariance(p_model, self._information(self._all_info), theta, self.torque_constant_std_)
        snap = {"theta": theta, "P": p, "P_sys": p_sys, "time": self.time_s_, "consistency": self.consistency(), "updates": self.n_updates_,
                "resets": self.resets_, "rejected": self.rejected_, "rate_changes": self.rate_changes_}
        doc = self.document(snap, project_feasible(theta, p, atol=PUBLISH_ATOL))  # in the data's metric, as every estimate
        doc.update(final=True, excited_s=self.excited_s_, covariance="batch means" if batched else "model", batches=int(scores.shape[0]))
        return doc

    def estimate(self) -> dict[str, Any]:
        """Mass (kg), centre of mass (m) and inertia about it (kg m^2, xx xy xz yy yz zz) in
        the last link's frame, physically possible, with standard deviations (delta method for
        the centre of mass); ``null`` for what the motion so far does not determine."""
        if not hasattr(self, "theta_"):
            self._start()
        return self.document(self.snapshot(), self.feasible_())

    def estimates(self, snapshots: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """The documents of many snapshots, each projected on its own from the cold start (never
        from the last answer: see :func:`project_feasible`), so live and replay publish the same;
        a snapshot equal to the last one (no new equation) reuses its projection."""
        return [self.document(s, self._projection(s["updates"] + s["resets"] + s["rejected"], s["theta"], s["P"]))
                for s in snapshots]

    def document(self, snap: dict[str, Any], th: Array) -> dict[str, Any]:
        """The published document of a :meth:`snapshot` whose physically possible parameters are ``th``."""
        th_u, p_stat = snap["theta"], snap["P"]
        p = p_stat + snap["P_sys"]  # the band: the noise's and the torque constants'
        std_stat = np.sqrt(np.maximum(np.diag(p_stat), 0.0))
        std = np.sqrt(np.maximum(np.diag(p), 0.0))
        excited = std_stat < 0.5 * self.prior_std
        m = float(th[0])
        mass_known = bool(excited[0])
        com = com_std = inertia = com_stat = None
        if mass_known and m >= MIN_MASS_FOR_COM_KG:
            c = th[1:4] / m
            jac = np.zeros((3, 10))
            jac[:, 0] = -th[1:4] / m**2
            jac[:, 1:4] = np.eye(3) / m
            cs = np.sqrt(np.maximum(np.diag(jac @ p @ jac.T), 0.0))
            com_stat = np.sqrt(np.maximum(np.diag(jac @ p_stat @ jac.T), 0.0))
            com, com_std = c.tolist(), cs.tolist()
            inertia = list(inertial_from_parameters(th).inertia_kgm2)
        cons = snap["consistency"]
        # converged: the estimate has stopped moving (the data's part of the band is small);
        # the torque constants' part stays whatever the data
        mass_ok = mass_known and std_stat[0] <= MASS_STD_KG + MASS_STD_REL * m
        com_ok = m < MIN_MASS_FOR_COM_KG or (com_stat is not None and bool(excited[1:4].all()) and float(com_stat.max()) <= COM_STD_M)
        converged = bool(mass_ok and com_ok and cons["consistent"])
        if not mass_known:
            status = "not excited"
        elif converged:
            status = "converged"
        elif not cons["consistent"] and cons["nis_per_dof"] is not None:
            status = "inconsistent"
        else:
            status = "converging"
        doc = {"time": snap["time"], "mass": m if mass_known else None, "mass_std": float(std[0]), "mass_std_data": float(std_stat[0]),
               "mass_std_torque_constants": float(np.sqrt(max(snap["P_sys"][0, 0], 0.0))), "com": com, "com_std": com_std,
               "com_std_data": None if com_stat is None else com_stat.tolist(),
               "inertia": inertia, "inertia_std": std[4:].tolist(), "parameters": th.tolist(), "parameters_std": std.tolist(),
               "excited": excited.tolist(), "excited_parameters": [n for n, e in zip(PARAMETER_NAMES, excited) if e],
               "converged": converged, "status": status, "consistency": cons,
               "unconstrained": {"mass": float(th_u[0]), "parameters": th_u.tolist(), "feasible": bool(np.allclose(th, th_u))},
               "updates": snap["updates"], "resets": snap["resets"], "rejected": snap["rejected"], "rate_changes": snap["rate_changes"]}
        return json_safe(doc)


def _chi2_upper(k: float, z: float = 3.0902) -> float:
    """The 99.9 % point of chi-square with ``k`` degrees of freedom (Wilson-Hilferty; within
    1.2 % of scipy's for k >= 5, 0.1 % for k >= 50)."""
    a = 2.0 / (9.0 * k)
    return float(k * (1.0 - a + z * np.sqrt(a)) ** 3)


