"""How low can the declared model go on the KUKA LWR4+ recordings? (issue 15's 1.6 % line)

    python examples/kuka_declared_model_floor.py [--data ../shared/data/kuka_lwr4] [--residuals P11.csv P12.csv]

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

With ``--residuals``, two ``--predictions`` files of a model identified on recording 1 (any
tool's: validated on recording 1 itself, then on 2), it splits that model's error on
recording 2 per joint into the noise no model of the motion predicts (the two runs'
difference over sqrt 2) and the model's own error, and tries a Fourier series in each
distal joint's position (8 harmonics, per direction of motion) fitted to recording 1's
residual.
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
    ap.add_argument("--residuals", nargs=2, metavar=("P11", "P12"),
                    help="predictions of a model identified on recording 1, at recording 1's and at recording 2's stamps")
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
    if args.residuals:
        split_error(recs, read_predictions(args.residuals[0]), read_predictions(args.residuals[1]))


def read_predictions(path: str) -> np.ndarray:
    p = np.genfromtxt(path, delimiter=",", names=True)
    return np.column_stack([p[n] for n in p.dtype.names[1:]])


def split_error(recs: dict[int, dict[str, np.ndarray]], fitted_1: np.ndarray, predicted_2: np.ndarray) -> None:
    """The model's error on recording 2, per joint: noise (unpredictable) and model error."""
    tau1, tau2 = recs[1]["torques"], recs[2]["torques"]
    err = np.sqrt(np.mean((tau2 - predicted_2) ** 2, axis=0))
    noise = np.sqrt(np.mean((tau1 - tau2) ** 2, axis=0) / 2)
    model = np.sqrt(np.maximum(err**2 - noise**2, 0.0))
    scale = np.linalg.norm(tau2) / np.sqrt(len(tau2))
    print("model's RMS error on recording 2, N*m, joints 1..7: " + ", ".join(f"{v:.3f}" for v in err))
    print("  noise (runs' difference / sqrt 2):               " + ", ".join(f"{v:.3f}" for v in noise))
    print("  model error:                                      " + ", ".join(f"{v:.3f}" for v in model))
    print(f"  in all: noise {100 * np.sqrt(np.sum(noise**2)) / scale:.2f} %, model error {100 * np.sqrt(np.sum(model**2)) / scale:.2f} % "
          f"(relative error {100 * np.linalg.norm(tau2 - predicted_2) / np.linalg.norm(tau2):.3f} %)")

    def series(rec: dict[str, np.ndarray], j: int) -> np.ndarray:
        q, s = rec["positions"][:, j], np.tanh(rec["velocities"][:, j] / 0.03)
        cols = [np.ones_like(q)] + [f(k * q) for k in range(1, 9) for f in (np.sin, np.cos)]
        return np.column_stack(cols + [c * s for c in cols])

    residual_1, corrected = tau1 - fitted_1, predicted_2.copy()
    for j in (4, 5, 6):
        coef = np.linalg.lstsq(series(recs[1], j), residual_1[:, j], rcond=None)[0]
        corrected[:, j] += series(recs[2], j) @ coef
    print(f"with a Fourier series in q (8 harmonics, per direction) on joints 5-7, fitted to recording 1's residual: "
          f"{100 * np.linalg.norm(tau2 - corrected) / np.linalg.norm(tau2):.3f} %")


if __name__ == "__main__":
    main()
