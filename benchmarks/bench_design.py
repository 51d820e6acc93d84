"""Design time per trajectory: :func:`identify.excitation.design` against the design path as
it was before issue 19 (vendored below), in the same process, on the demo's eight designs
(the simulated PUMA 560: six single-link experiments chained pose to pose, two whole-arm).

The reference is the old code as it stood: L-BFGS-B's own finite differences, one candidate
at a time, each scaled and run through the regressor alone, the regressor recomputing the
joints' constants on every call. Both share today's compiled regressor kernel, warmed first;
the kernel's own change (small calls on the calling thread, not numba's parallel region,
which took 17 ms for 160 samples under load) is not in the ratio, so the ratio understates
the gain on a loaded machine. Per design: both times, their ratio, and the designs' quality (condition number of the
column-scaled base regressor, D-criterion ``log det(W_b^T W_b)``).

    python benchmarks/bench_design.py [names...]     # default: all eight (link6 ... link1 whole_a whole_b)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from figures_json import recorded
from scipy.optimize import minimize

from armid.identify import excitation as ex
from armid.identify.dynamics import _joint_constants, _out_layout, check_joint_arrays, regressor
from armid.identify.effects import effect_columns
from armid.identify.identification import declared_effects
from armid.identify.kernels.regressor_lanes import regressor_rows
from armid.identify.robot import Robot
from armid.identify.trajectories import FourierTrajectory
from armid.io.robot_file import load_robot

ROBOT = Path(__file__).resolve().parent.parent / "config" / "robots" / "puma560.yaml"
START = np.array([0.0, 0.7854, -0.7854, 0.0, 0.0, 0.0])  # config/rigs/sim.yaml's initial position


# ---- the reference: the design path before issue 19, verbatim but for the names ----

def _regressor_before(robot: Robot, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``identify.dynamics.regressor`` before: the joints' constants recomputed on every call."""
    q, qd, qdd = check_joint_arrays(robot, q, qd, qdd)
    n, nj = q.shape
    out = np.empty((n, nj, 10 * nj)) if out is None else out
    layout = _out_layout(out)
    revolute = np.array([j.revolute for j in robot.joints])
    a0, ac, a_s, p0, pc, ps, t0, u = _joint_constants(robot)
    g = -np.asarray(robot.gravity, dtype=float)
    row_stride, seg_len, seg_stride, first_aligned = layout
    regressor_rows(revolute, a0, ac, a_s, p0, pc, ps, t0, u, g, np.ascontiguousarray(q), np.ascontiguousarray(qd),
                   np.ascontiguousarray(qdd), out, row_stride, seg_len, seg_stride, first_aligned)
    return out


def _stacked_before(robot: Robot, effects: list[Any], q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    n, nj = np.shape(q)
    cols = effect_columns(effects, q, qd, qdd) if effects else None
    m = np.empty((n, nj, 10 * nj + (cols.shape[2] if cols is not None else 0)))
    _regressor_before(robot, q, qd, qdd, out=m[:, :, : 10 * nj])
    if cols is not None:
        m[:, :, 10 * nj :] = cols
    return m.reshape(-1, m.shape[2])


def _experiment_regressor_before(robot: Robot, rows: tuple[int, ...], q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    n, nj = q.shape
    w = _stacked_before(robot, declared_effects(robot), q, qd, qdd).reshape(n, nj, -1)
    return w[:, list(rows), :].reshape(-1, w.shape[2])


def _model_torque_before(robot: Robot, traj: FourierTrajectory, t: np.ndarray, phi: np.ndarray) -> np.ndarray:
    q, qd, qdd = traj.evaluate(t)
    return _regressor_before(robot, q, qd, qdd) @ phi


def _scaled_before(robot: Robot, limits: ex.Limits, q_hold: np.ndarray, moving: tuple[int, ...], a: np.ndarray, b: np.ndarray,
                   f_hz: float, margin: float, t: np.ndarray, phi: np.ndarray) -> FourierTrajectory:
    n = robot.n_joints
    A, B = np.zeros((n, a.shape[1])), np.zeros((n, a.shape[1]))
    A[list(moving)], B[list(moving)] = a, b
    raw = FourierTrajectory(np.zeros(n), A, B, f_hz)
    q, qd, qdd = raw.evaluate(t)
    lo, hi = limits.position_low, limits.position_high
    finite = np.isfinite(lo) & np.isfinite(hi)
    half_range = np.where(finite, 0.5 * (hi - lo), np.pi)
    centre = np.where(finite, 0.5 * (hi + lo), q_hold)
    span = 0.5 * np.ptp(q, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.minimum.reduce([margin * half_range / span, margin * limits.velocity / np.abs(qd).max(axis=0),
                               margin * limits.acceleration / np.abs(qdd).max(axis=0)])
    s = np.where(np.isfinite(s), s, 0.0)
    mid = 0.5 * (q.max(axis=0) + q.min(axis=0))
    q0 = np.array(q_hold, float)
    for j in moving:
        q0[j] = centre[j] - s[j] * mid[j]
    traj = FourierTrajectory(q0, A * s[:, None], B * s[:, None], f_hz)
    for _ in range(30):
        tau = _model_torque_before(robot, traj, t, phi)
        ratio = (np.abs(tau).max(axis=0) / (margin * limits.torque)).max()
        if ratio <= 1.0:
            break
        shrink = max(0.5, 0.97 / np.sqrt(ratio))
        q_now = traj.evaluate(t)[0]
        mid_q = 0.5 * (q_now.max(axis=0) + q_now.min(axis=0))
        traj = FourierTrajectory(mid_q - shrink * (mid_q - traj.q0), traj.a * shrink, traj.b * shrink, f_hz)
    return traj


def design_before(robot: Robot, moving: tuple[int, ...] | None = None, q_hold: np.ndarray | None = None, harmonics: int = 5,
                  base_frequency_hz: float = 0.1, margin: float = 0.8, samples: int = 160, seed: int = 0, iterations: int = 30,
                  starts: int = 2) -> tuple[FourierTrajectory, float, float]:
    """The old ``design``'s optimisation; returns the trajectory, its condition number and log det."""
    n = robot.n_joints
    lim = ex.Limits.of(robot)
    moving = tuple(range(n)) if moving is None else tuple(sorted(moving))
    rows = tuple(range(n)) if len(moving) == n else (min(moving),)
    if q_hold is None:
        finite = np.isfinite(lim.position_low) & np.isfinite(lim.position_high)
        q_hold = np.where(finite, 0.5 * (lim.position_low + lim.position_high), 0.0)
    q_hold = np.asarray(q_hold, float)
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0 / base_frequency_hz, samples, endpoint=False)
    phi = robot.modeled_parameters()
    cols, names, base, _ = ex._experiment_base(robot, rows, moving, q_hold, lim, rng)
    indep = [cols[k] for k in base.independent]
    k_free = len(moving) * (harmonics - 1)

    def trajectory_of(x: np.ndarray) -> FourierTrajectory:
        a, b = ex._rest_to_rest(x[:k_free].reshape(len(moving), -1), x[k_free:].reshape(len(moving), -1))
        return _scaled_before(robot, lim, q_hold, moving, a, b, base_frequency_hz, margin, t, phi)

    scale: np.ndarray | None = None

    def log_det(traj: FourierTrajectory) -> tuple[float, np.ndarray]:
        q, qd, qdd = traj.evaluate(t)
        w = _experiment_regressor_before(robot, rows, q, qd, qdd)[:, indep]
        return float(np.linalg.slogdet(w.T @ w)[1]) if w.size else 0.0, w

    def cost(x: np.ndarray) -> float:
        traj = trajectory_of(x)
        q, qd, qdd = traj.evaluate(t)
        w = _experiment_regressor_before(robot, rows, q, qd, qdd)[:, indep] / scale
        sign, ld = np.linalg.slogdet(w.T @ w / w.shape[0])
        return -ld if sign > 0 else 1e6

    best_x, best_cost = None, np.inf
    for start in range(starts):
        x0 = rng.normal(size=2 * k_free)
        if scale is None:
            _, w0 = log_det(trajectory_of(x0))
            norms = np.linalg.norm(w0, axis=0)
            scale = np.where(norms > 0, norms / np.sqrt(w0.shape[0]), 1.0)
        res = minimize(cost, x0, method="L-BFGS-B", options={"maxiter": iterations // 3 if start else iterations, "eps": 1e-4})
        if res.fun < best_cost:
            best_x, best_cost = res.x, float(res.fun)
    assert best_x is not None
    traj = trajectory_of(best_x)
    ld, w = log_det(traj)
    norms = np.linalg.norm(w, axis=0)
    sv = np.linalg.svd(w / np.where(norms > 0, norms, 1.0), compute_uv=False)
    return traj, float(sv[0] / sv[-1]), ld


# ---- the benchmark ----

def demo_designs(robot: Robot) -> list[tuple[str, dict[str, Any]]]:
    """The demo's design calls (armid.experiments.design_experiments, seed 0): name and keyword arguments."""
    calls: list[tuple[str, dict[str, Any]]] = []
    pose = START
    for k in range(robot.n_joints - 1, -1, -1):
        hold = ex.choose_hold(robot, k, pose, seed=k)
        kw = {"moving": (k,), "q_hold": hold, "base_frequency_hz": 0.5, "seed": k}
        calls.append((f"link{k + 1}", kw))
        pose = ex.design(robot, **kw).trajectory.evaluate(np.zeros(1))[0][0]
    calls += [(name, {"base_frequency_hz": 0.2, "seed": 100 + i, "margin": 0.6}) for i, name in enumerate(("whole_a", "whole_b"))]
    return calls


def main(names: list[str]) -> None:
    robot = load_robot(ROBOT)
    z = np.zeros((4, robot.n_joints))
    regressor(robot, z, z, z)  # the kernel compiled (or loaded from its cache) before any timing
    ex.design(robot, moving=(5,), base_frequency_hz=0.5, iterations=1, starts=1)
    print("design | now s | before s | ratio | condition number now / before | log det now / before")
    total_now = total_before = 0.0
    for name, kw in demo_designs(robot):
        if names and name not in names:
            continue
        start = time.perf_counter()
        d = ex.design(robot, **kw)
        t_now = time.perf_counter() - start
        start = time.perf_counter()
        _, cond_before, ld_before = design_before(robot, **kw)
        t_before = time.perf_counter() - start
        total_now, total_before = total_now + t_now, total_before + t_before
        print(f"{name} | {t_now:.2f} | {t_before:.2f} | {t_before / t_now:.1f}x | {d.condition_number:.4g} / {cond_before:.4g} | "
              f"{d.log_det:.3f} / {ld_before:.3f}", flush=True)
    print(f"all | {total_now:.2f} | {total_before:.2f} | {total_before / total_now:.1f}x")


if __name__ == "__main__":
    with recorded("design"):
        main(sys.argv[1:])
