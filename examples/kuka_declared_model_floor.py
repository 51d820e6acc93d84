"""How low can the declared model go on the KUKA LWR4+ recordings? (issue 15's 1.6 % line)

    python examples/kuka_declared_model_floor.py [--data ../shared/data/kuka_lwr4]

Independent of armid (Pinocchio's regressor and numpy's least squares only). The declared
model is the rigid body plus Coulomb (``fc tanh(qd / v)``), viscous friction and an offset on
every joint. For each recording it fits that model *to the recording itself*, against the
raw torque, with each joint's smoothing ``v`` chosen from a grid (coordinate descent) and the
recording's own filtered accelerations: no parameter set of the declared model predicts
that recording better, so this is a floor for any held-out error on it. Then it evaluates
recording 1's own best parameters on recording 2 (same trajectory, repeated), which is what
an identification on 1 can at best hope for, and splits the difference; last, recording 1's
measured torque itself replayed as the prediction of recording 2 (what a perfect memory of
recording 1, its noise included, would score).
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np
import pinocchio as pin

GRID = (0.0, 0.001, 0.003, 0.006, 0.01, 0.02, 0.03, 0.06, 0.1, 0.2)
JOINTS = [f"lwr_{i}_joint" for i in range(7)]


def load_model(data: pathlib.Path) -> pin.Model:
    model = pin.buildModelFromUrdf(str(data / "kuka_lwr4.urdf"))
    extra = [n for n in model.names[1:] if n not in JOINTS]
    if extra:
        model = pin.buildReducedModel(model, [model.getJointId(n) for n in extra], pin.neutral(model))
    return model


def regressors(model: pin.Model, rec: dict[str, np.ndarray]) -> tuple[np.ndarray, dict[float, np.ndarray]]:
    """Rigid-body rows (N, n, 10 n) and, per smoothing v, the friction rows (N, n, 3 n)."""
    data = model.createData()
    q, qd, qdd = rec["positions"], rec["velocities"], rec["accelerations"]
    rigid = np.stack([pin.computeJointTorqueRegressor(model, data, q[k], qd[k], qdd[k]) for k in range(len(q))])
    n = q.shape[1]
    friction = {}
    for v in GRID:
        f = np.zeros((len(q), n, 3 * n))
        for j in range(n):
            f[:, j, 3 * j] = np.sign(qd[:, j]) if v == 0 else np.tanh(qd[:, j] / v)
            f[:, j, 3 * j + 1] = qd[:, j]
            f[:, j, 3 * j + 2] = 1.0
        friction[v] = f
    return rigid, friction


def assemble(rigid: np.ndarray, friction: dict[float, np.ndarray], smoothing: list[float]) -> np.ndarray:
    f = friction[GRID[0]].copy()
    for j, v in enumerate(smoothing):
        f[:, :, 3 * j] = friction[v][:, :, 3 * j]
    a = np.concatenate([rigid, f], axis=2)
    return a.reshape(-1, a.shape[2])


def relative_error(a: np.ndarray, x: np.ndarray, tau: np.ndarray) -> float:
    return float(np.linalg.norm(tau.reshape(-1) - a @ x) / np.linalg.norm(tau))


def best_fit(rigid: np.ndarray, friction: dict[float, np.ndarray], tau: np.ndarray) -> tuple[np.ndarray, list[float], float]:
    """Least squares on the recording itself, each joint's smoothing by coordinate descent."""
    n = tau.shape[1]
    smoothing = [0.01] * n
    best = (np.inf, smoothing)
    for _ in range(3):
        for j in range(n):
            for v in GRID:
                trial = smoothing[:j] + [v] + smoothing[j + 1 :]
                a = assemble(rigid, friction, trial)
                x = np.linalg.lstsq(a, tau.reshape(-1), rcond=None)[0]
                e = relative_error(a, x, tau)
                if e < best[0]:
                    best = (e, trial)
            smoothing = best[1]
    a = assemble(rigid, friction, smoothing)
    x = np.linalg.lstsq(a, tau.reshape(-1), rcond=None)[0]
    return x, smoothing, relative_error(a, x, tau)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(pathlib.Path(__file__).resolve().parents[2] / "shared/data/kuka_lwr4"))
    args = ap.parse_args()
    data = pathlib.Path(args.data)
    model = load_model(data)
    recs = {k: dict(np.load(data / f"measurements_{k}.npz")) for k in (1, 2, 3)}
    fits = {}
    for k, rec in recs.items():
        rigid, friction = regressors(model, rec)
        x, smoothing, err = best_fit(rigid, friction, rec["torques"])
        fits[k] = (rigid, friction, x, smoothing)
        print(f"recording {k}: the declared model fitted to the recording itself: {100 * err:.3f} % "
              f"(smoothing {', '.join(f'{v:g}' for v in smoothing)} rad/s)")
    rigid2, friction2, _, smoothing2 = fits[2]
    a2 = assemble(rigid2, friction2, smoothing2)
    x1 = fits[1][2] if fits[1][3] == smoothing2 else np.linalg.lstsq(
        assemble(fits[1][0], fits[1][1], smoothing2), recs[1]["torques"].reshape(-1), rcond=None)[0]
    print(f"recording 1's own best parameters (recording 2's smoothing) on recording 2: {100 * relative_error(a2, x1, recs[2]['torques']):.3f} %")
    diff = recs[1]["torques"] - recs[2]["torques"]
    print("recordings 1 and 2 repeat one trajectory; their raw torques differ by "
          + ", ".join(f"{v:.2f}" for v in np.sqrt(np.mean(diff**2, axis=0))) + " N*m RMS on joints 1..7")
    # the repetition itself as a predictor: recording 1's measured torque, sample for sample
    print(f"recording 1's raw torque replayed as the prediction of recording 2: "
          f"{100 * np.linalg.norm(diff) / np.linalg.norm(recs[2]['torques']):.3f} %")


if __name__ == "__main__":
    main()
