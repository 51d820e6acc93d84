"""The identified arm the payload estimator leaves out of the torque (:mod:`identify.payload`).

:class:`ArmModel` is the arm of an identification (``armid identify --json``, read back by
:func:`arm_model_from_identification`): its torque and the last link's regressor columns, the
payload's, by one backward pass of eqs. 16-17 in plain numpy. :class:`ReferenceRun` is the
unloaded run of the same trajectory, looked up by position, whose residual is taken off the
loaded run's (reference mode: arm-model and friction errors cancel).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..differentiation import HALF_WINDOW_S, MIN_WINDOW_POINTS, local_polynomial
from ..dynamics import forward_recursion, kinematic_matrix, pseudo_rotation, selection_vector
from ..effects import LinearEffect, LoadFriction, effect_columns
from ..robot import Robot
from ..spatial import Array


@dataclass(frozen=True)
class ArmModel:
    """The identified arm: ``tau = W(q, qd, qdd)[:, columns] @ beta`` (base parameters of an
    identification, with its effect columns); ``joint_sigma`` is each joint's noise."""

    robot: Robot
    effects: tuple[LinearEffect, ...]
    columns: Array
    beta: Array
    joint_sigma: Array

    def _phi(self) -> Array:
        n_std = 10 * self.robot.n_joints
        phi = np.zeros(n_std + sum(len(e.parameter_names) for e in self.effects))
        phi[np.asarray(self.columns, int)] = self.beta
        return phi

    def torque_and_payload_columns(self, q: Array, qd: Array, qdd: Array) -> tuple[Array, Array]:
        """The arm's modeled torque (n, N) and the payload's regressor ``M_{:,N}`` (n, N, 10).

        One backward pass of eq. (16), ``g_{i-1} = R_i g_i + K_{i-1} phi_{i-1}`` and
        ``tau_i = s_i^T g_i`` (eq. 17), carrying ``R_{i+1} ... R_N K_N`` beside it for the
        last link's columns. Plain numpy: the estimator has nothing to compile before the
        arm moves (a cold compile of the batched kernel takes tens of seconds).
        """
        robot = self.robot
        nj = robot.n_joints
        motions = forward_recursion(robot, q, qd, qdd)
        phi = self._phi()
        n = motions[0].w.shape[0]
        tau, cols = np.empty((n, nj)), np.empty((n, nj, 10))
        g, c = np.zeros((n, 6)), np.zeros((n, 6, 10))
        for i in range(nj - 1, -1, -1):
            k = kinematic_matrix(motions[i])
            if i == nj - 1:
                c = k
            else:
                r = pseudo_rotation(motions[i + 1], motions[i].rho)
                g = np.einsum("nab,nb->na", r, g)
                c = r @ c
            g = g + k @ phi[10 * i : 10 * i + 10]
            s = selection_vector(motions[i])
            tau[:, i] = g @ s
            cols[:, i] = np.einsum("a,nab->nb", s, c)
        if self.effects:
            q2, qd2, qdd2 = np.atleast_2d(q), np.atleast_2d(qd), np.atleast_2d(qdd)
            # a load-dependent friction's load is the arm's own rigid-body torque, just computed
            tau_rigid = tau.copy()
            tau += effect_columns(list(self.effects), q2, qd2, qdd2, load=tau_rigid) @ phi[10 * nj :]
            col = 10 * nj
            for e in self.effects:
                if isinstance(e, LoadFriction):
                    # the payload's torque goes through the same gear: fl |tau + tau_p| ~ fl |tau| + fl sign(tau) tau_p
                    cols[:, e.joint] *= (1.0 + phi[col] * np.sign(tau_rigid[:, e.joint]) * e.direction(qd2))[:, None]
                col += len(e.parameter_names)
        return tau, cols

    def torque(self, q: Array, qd: Array, qdd: Array) -> Array:
        return self.torque_and_payload_columns(q, qd, qdd)[0]


class ReferenceRun:
    """A run of the same trajectory without the payload, looked up by position.

    Its arm-model residual ``tau - M phi_arm`` (derivatives on its own time stamps) is
    taken off the loaded run's residual at the same point of the trajectory, so that what
    the arm model and friction get wrong cancels and the payload's torque remains. The
    point is found by position: the nearest reference sample within ``search_s`` of where
    the last match predicts (same speed), refined onto the segment to its neighbours. A
    sample further than ``tolerance_rad`` from the reference path gives no equation.
    """

    def __init__(self, arm: ArmModel, t: Array, q: Array, tau: Array, tolerance_rad: float = 0.05, search_s: float = 0.25) -> None:
        t, q, tau = np.asarray(t, float), np.asarray(q, float), np.asarray(tau, float)
        nj = q.shape[1]
        # the same filter as the loaded run's equations, torque included
        x0, x1, x2, ok = local_polynomial(t, np.hstack([q, tau]))
        if ok.sum() < 9:
            raise ValueError(f"the reference run has {t.size} samples: too few to differentiate "
                             f"(it takes {MIN_WINDOW_POINTS} records within {1000 * HALF_WINDOW_S:g} ms)")
        self.t, self.q = t[ok], x0[ok, :nj]
        self.residual = x0[ok, nj:] - arm.torque(x0[ok, :nj], x1[ok, :nj], x2[ok, :nj])
        self.step_s = float(np.median(np.diff(self.t)))
        self.tolerance_rad = tolerance_rad
        self.window = max(2, int(round(search_s / self.step_s)))
        self.cursor: int | None = None
        self.last_t = 0.0
        self.first_t: float | None = None
        self.misses = 0
        self.matched = 0

    def restart(self) -> None:
        self.cursor = None

    def lookup(self, t: float, q: Array) -> tuple[Array, float]:
        """The reference residual at the pose ``q`` of time ``t`` and its distance (rad)."""
        n = self.t.size
        if self.first_t is None:
            self.first_t = t
        if self.cursor is None:  # both runs start together; afterwards, follow the matches
            guess = int(np.searchsorted(self.t, self.t[0] + (t - self.first_t)))
        else:
            guess = self.cursor + int(round((t - self.last_t) / self.step_s))
        lo, hi = max(0, guess - self.window), min(n, guess + self.window + 1)
        if lo >= hi:
            lo, hi = max(0, n - 2 * self.window), n
        d2 = ((self.q[lo:hi] - q) ** 2).sum(axis=1)
        k = lo + int(np.argmin(d2))
        if d2[k - lo] > self.tolerance_rad**2 and self.misses > 50:  # lost: search the whole run
            d2_all = ((self.q - q) ** 2).sum(axis=1)
            k = int(np.argmin(d2_all))
        best, best_d, res = k, float(((self.q[k] - q) ** 2).sum()), self.residual[k]
        for a, b in ((k - 1, k), (k, k + 1)):
            if 0 <= a and b < n:
                seg = self.q[b] - self.q[a]
                den = float(seg @ seg)
                if den > 0:
                    s = min(1.0, max(0.0, float((q - self.q[a]) @ seg) / den))
                    d = float(((self.q[a] + s * seg - q) ** 2).sum())
                    if d < best_d:
                        best_d, res = d, (1 - s) * self.residual[a] + s * self.residual[b]
        self.cursor, self.last_t = best, t
        dist = float(np.sqrt(best_d))
        if dist > self.tolerance_rad:
            self.misses += 1
        else:
            self.misses = 0
            self.matched += 1
        return res, dist


def identification_document(arm: ArmModel, seed: int = 0) -> dict[str, Any]:
    """The fields of an ``armid identify --json`` document that
    :func:`arm_model_from_identification` reads, for an arm model on the robot's declared
    effects (an arm known otherwise, e.g. a simulator's, handed to ``armid estimate``)."""
    from ..identification import structural_base

    base = structural_base(arm.robot, list(arm.effects), seed)
    if not np.array_equal(np.asarray(base.independent), np.asarray(arm.columns)):
        raise ValueError("the arm model's columns are not the robot's structural base parameters")
    return {"robot": arm.robot.name,
            "base_parameters": [{"expression": x, "value": float(v)} for x, v in zip(base.expressions(), arm.beta)],
            "joint_noise_sigma": [float(x) for x in arm.joint_sigma],
            "effects": [{"effect": e.effect, "joint": e.joint + 1, **({"setting": dict(e.setting)} if e.setting else {})} for e in arm.effects]}


def arm_model_from_identification(robot: Robot, doc: dict[str, Any], seed: int = 0) -> ArmModel:
    """The arm model of an ``armid identify --json`` document, checked against the robot:
    the base parameters are rebuilt from the kinematics and must read as the document's."""
    from ..errors import IdentificationError
    from ..identification import declared_effects, structural_base

    effects = declared_effects(robot)
    base = structural_base(robot, effects, seed)
    exprs = base.expressions()
    got = [b["expression"] for b in doc.get("base_parameters", [])]
    if got != exprs:
        first = next((k for k, (a, b) in enumerate(zip(exprs, got)) if a != b), min(len(exprs), len(got)))
        raise IdentificationError(
            f"the identification's base parameters do not match {robot.name}'s model (declared effects included): "
            f"{len(got)} against {len(exprs)}; first difference at #{first + 1}: "
            f"{got[first] if first < len(got) else '(none)'!r} vs {exprs[first] if first < len(exprs) else '(none)'!r}")
    beta = np.array([b["value"] for b in doc["base_parameters"]], float)
    sigma = np.asarray(doc.get("joint_noise_sigma") or [1.0] * robot.n_joints, float)
    # each effect with the setting the identification chose on the data (a Coulomb model's smoothing)
    chosen = {(e["effect"], e["joint"] - 1): e.get("setting", {}) for e in doc.get("effects", [])}
    effects = [e.with_setting(**chosen[(e.effect, e.joint)]) if chosen.get((e.effect, e.joint)) else e for e in effects]
    return ArmModel(robot, tuple(effects), base.independent, beta, sigma)
