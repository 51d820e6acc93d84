"""A lab's fleet of arms recorded day after day, with known changes: the data of ``armid fleet``'s tests.

It shares no code with armid: the arms, the trajectories, the torques and the sensors are
:mod:`blindgen`'s (numpy, scipy, pinocchio, yaml only). Each arm is a random serial arm with
Coulomb and viscous friction on every joint and an offset on every torque; its robot file
declares those and a drive gain on joint 2 (the lab tracks them), with modeled inertials
off by 20-30 % as a CAD model is. Each day the arm runs a new random Fourier trajectory (a
nearby base frequency, new coefficients), recorded with new noise; the recordings' time
stamps are absolute (seconds since the epoch, one day apart, the hour varying), and their
file names say nothing of their order (a random token in a sub-folder)::

    from fleetgen import make_fleet
    fleet = make_fleet(tmp_path / "fleet")
    # armid fleet tmp_path/fleet --out out --workers 1 --engine local
    fleet.changes  # what was planted: arm, kind, joint, index (1-based, in time), first recording

The changes (``CHANGES``), each from its recording ``k`` on (1-based, in time order):

- ``friction_step``: the Coulomb friction of one joint of one arm 1.6 times what it was;
- ``gain_drift``: joint 2's drive gain of another arm grows by 2.5 % a day (the sensor reads
  ``gain`` times the torque);
- ``tool``: a 1 kg tool fixed to the last link of a third arm, its centre 6 cm off the last
  joint's axis.

The other arms do not change. ``truth.json`` in each arm's folder holds the truth of every
recording (the link parameters in Khosla's order, the friction, the gain).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import blindgen as bg
import numpy as np

EPOCH_S = 1_717_200_000.0
"""The first day's midnight (seconds since 1970): 2024-06-01 00:00 UTC."""

DAY_S = 86_400.0

CHANGES: dict[str, dict[str, Any]] = {
    "cell2_left": {"kind": "friction_step", "joint": 3, "first": 6, "factor": 1.6},
    "cell3_right": {"kind": "gain_drift", "joint": 2, "first": 4, "per_day": 0.025},
    "cell4_left": {"kind": "tool", "joint": None, "first": 7, "mass_kg": 1.0, "offset_m": (0.06, 0.0, 0.04)},
}
"""The arms that change, what, and from which recording (1-based, in time order)."""

ARMS = ("cell1_left", "cell2_left", "cell3_right", "cell4_left", "cell5_right", "cell6_left")

DECLARED = [{"effect": "viscous_friction", "joint": None}, {"effect": "coulomb_friction", "joint": None, "velocity": 0.0},
            {"effect": "torque_offset", "joint": None}, {"effect": "torque_gain", "joint": 2}]
"""What each arm's robot file declares (a sharp Coulomb sign: the generator's friction is ``fc sign(qd)``)."""


@dataclass
class Fleet:
    root: Path
    arms: list[str]
    changes: list[dict[str, Any]]  # one per planted change: arm, kind, joint, index (1-based), first (its relative path)
    recordings: dict[str, list[str]]  # per arm, the recordings' paths relative to root, in time order
    bad: dict[str, str] = field(default_factory=dict)  # with_bad_recordings: kind -> path relative to root


def _with_tool(arm: bg.Arm, mass: float, offset: tuple[float, float, float]) -> bg.Arm:
    """The arm with a point-like tool (a 4 cm cube) of ``mass`` fixed at ``offset`` in the last link's frame."""
    last = arm.links[-1]
    c, ct = np.array(last.com), np.array(offset, float)
    m_new = last.mass + mass
    c_new = (last.mass * c + mass * ct) / m_new

    def shifted(inertia: np.ndarray, m: float, d: np.ndarray) -> np.ndarray:
        return inertia + m * (d @ d * np.eye(3) - np.outer(d, d))

    cube = mass * 0.04**2 / 6.0 * np.eye(3)
    inertia = shifted(bg._sym(last.inertia), last.mass, c - c_new) + shifted(cube, mass, ct - c_new)
    links = [*arm.links[:-1], replace(last, mass=m_new, com=c_new.tolist(), inertia=bg._entries(inertia))]
    return bg.Arm(arm.convention, links, arm.gravity)


def _day_state(arm_name: str, arm: bg.Arm, day: int, friction: dict[str, list[float]]) -> tuple[bg.Arm, list[bg.Effect], float]:
    """The arm, its effects and joint 2's gain on day ``day`` (1-based)."""
    change = CHANGES.get(arm_name)
    fc, fv, offset = list(friction["fc"]), list(friction["fv"]), list(friction["offset"])
    gain = 1.0
    if change and day >= change["first"]:
        if change["kind"] == "friction_step":
            fc[change["joint"] - 1] *= change["factor"]
        elif change["kind"] == "gain_drift":
            gain = 1.0 + change["per_day"] * (day - change["first"] + 1)
        elif change["kind"] == "tool":
            arm = _with_tool(arm, change["mass_kg"], change["offset_m"])
    n = len(arm.links)
    effects = [bg.Effect("coulomb_friction", list(range(n)), {"fc": fc}), bg.Effect("viscous_friction", list(range(n)), {"fv": fv}),
               bg.Effect("torque_offset", list(range(n)), {"offset": offset})]
    if gain != 1.0:
        effects.append(bg.Effect("torque_gain", [1], {"gain": [gain]}))
    return arm, effects, gain


@dataclass
class FrictionArm:
    """A random arm, its modeled (CAD-like) links, a base frequency for its trajectories, and
    Coulomb and viscous friction per joint sized from its torque on a probe trajectory."""

    arm: bg.Arm
    modeled: list[dict[str, Any]]
    f0: float
    rms: np.ndarray  # each joint's rigid-body torque rms on the probe
    peak: np.ndarray  # twice each joint's largest rigid-body torque on the probe (the robot file's limit)
    fc: list[float]
    fv: list[float]


def random_arm_with_friction(rng: np.random.Generator, n_joints: int, convention: str, duration_s: float, rate_hz: float) -> FrictionArm:
    """:class:`FrictionArm` drawn from ``rng`` (the fleet's arms and :mod:`checkgen`'s)."""
    arm, boxes = bg.random_arm(rng, n_joints, convention, None)
    modeled = bg.modeled_links(rng, arm, boxes)
    f0 = float(rng.uniform(0.15, 0.25))
    probe = bg.random_fourier(rng, arm, f0)
    q, qd, qdd = probe(bg.stamps(rng, duration_s, rate_hz, 0.0))
    rigid = bg.rigid_torque(bg.build_model(arm), q, qd, qdd)
    rms = np.maximum(np.sqrt(np.mean(rigid**2, axis=0)), 1e-2)
    speed = np.sqrt(np.mean(qd**2, axis=0))
    fc = (rms * rng.uniform(0.05, 0.1, n_joints)).tolist()
    fv = (rms * rng.uniform(0.03, 0.06, n_joints) / speed).tolist()
    return FrictionArm(arm, modeled, f0, rms, np.abs(rigid).max(axis=0) * 2.0, fc, fv)


def make_arm(root: Path, arm_name: str, seed: int, n_recordings: int = 10, n_joints: int = 4, duration_s: float = 20.0,
             rate_hz: float = 200.0) -> list[str]:
    """One arm's folder: robot.yaml, its recordings in random sub-folders, truth.json. Returns
    the recordings' paths relative to ``root`` in time order."""
    rng = np.random.default_rng(seed)
    folder = root / arm_name
    folder.mkdir(parents=True, exist_ok=True)
    a = random_arm_with_friction(rng, n_joints, "dh" if seed % 2 else "mdh", duration_s, rate_hz)
    arm, modeled, f0, peak = a.arm, a.modeled, a.f0, a.peak
    friction = {"fc": a.fc, "fv": a.fv, "offset": (a.rms * rng.uniform(-0.03, 0.03, n_joints)).tolist()}
    paths, truth = [], []
    for day in range(1, n_recordings + 1):
        today, effects, gain = _day_state(arm_name, arm, day, friction)
        traj = bg.random_fourier(rng, arm, float(np.clip(f0 * rng.uniform(0.85, 1.15), 0.1, 0.3)))
        noise = ("low", "medium")[int(rng.integers(0, 2))]
        level = bg.NOISE_LEVELS[noise]
        t = bg.stamps(rng, duration_s, rate_hz, 0.05)
        clean, _ = bg.recorded_torque(today, traj, t, effects)
        sensor = bg.Sensor(rate_hz, 0.05, noise, True, False, None, level["torque"] * np.abs(clean).max(axis=0), level["qd"],
                           level["counts"], level["q"])
        start = EPOCH_S + (day - 1) * DAY_S + float(rng.uniform(6.0, 18.0)) * 3600.0
        rel = Path(arm_name) / f"batch{int(rng.integers(1, 4))}" / f"run_{rng.integers(16**6):06x}.csv"
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shifted = _Shifted(traj, start)
        bg.record(rng, today, shifted, t + start, effects, sensor, root / rel, None)
        paths.append(rel.as_posix())
        truth.append({"recording": rel.as_posix(), "day": day, "start_time": float(np.round(start, 6)), "noise": noise,
                      "khosla_parameters": [bg.link_frame_parameters(ln) for ln in today.links], "gain_joint2": gain,
                      "fc": effects[0].params["fc"], "fv": friction["fv"], "offset": friction["offset"]})
    bg._write_robot(folder / "robot.yaml", arm_name, arm, modeled, peak, DECLARED)
    (folder / "truth.json").write_text(json.dumps({"seed": seed, "change": CHANGES.get(arm_name), "recordings": truth}, indent=1))
    return paths


class _Shifted:
    """A trajectory read at ``t - start``: the recording's stamps are absolute, its motion starts at 0."""

    def __init__(self, traj: Any, start: float) -> None:
        self.traj, self.start = traj, start

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.traj(np.asarray(t) - self.start)


def make_fleet(root: str | Path, seed: int = 0, arms: tuple[str, ...] = ARMS, n_recordings: int = 10, duration_s: float = 20.0) -> Fleet:
    """The fleet in ``root``: one folder per arm (robot.yaml, recordings, truth.json)."""
    root = Path(root)
    recordings = {name: make_arm(root, name, 1000 * seed + 17 * k + 3, n_recordings, duration_s=duration_s)
                  for k, name in enumerate(arms)}
    changes = []
    for name, change in CHANGES.items():
        if name not in recordings or change["first"] > n_recordings:
            continue
        changes.append({"arm": name, "kind": change["kind"], "joint": change["joint"], "index": change["first"],
                        "first": recordings[name][change["first"] - 1]})
    return Fleet(root, list(arms), changes, recordings)


def truth_change(root: Path, arm: str, expression: str, before_day: int, after_day: int) -> float:
    """How much a base parameter's ``expression`` (``msx4 + 0.2683*m4``: names of Khosla's
    parameters and numbers) truly moved between two days of an arm: evaluated on truth.json's
    link parameters, by this module's own reading of the expression."""
    days = json.loads((root / arm / "truth.json").read_text())["recordings"]

    def value(day: int) -> float:
        phi = days[day - 1]["khosla_parameters"]
        names = {f"{p}{i + 1}": phi[i][k] for i in range(len(phi))
                 for k, p in enumerate(("m", "msx", "msy", "msz", "Ixx", "Ixy", "Ixz", "Iyy", "Iyz", "Izz"))}
        return float(eval(expression, {"__builtins__": {}}, names))  # noqa: S307 - names and numbers only, from armid's own output

    return value(after_day) - value(before_day)


def with_bad_recordings(fleet: Fleet, other_seed: int = 99) -> dict[str, str]:
    """Three recordings that cannot be identified, added to the first arm's folder: a corrupt
    one (a valid start, then bytes a failing disk left), one of another robot (5 joints, not
    4) and one whose torque is NaN throughout. Their paths relative to the root, by kind."""
    import tempfile

    root, arm = fleet.root, fleet.arms[0]
    good = (root / fleet.recordings[arm][0]).read_bytes()
    out = {kind: Path(arm) / "batch9" / f"run_{kind}.csv" for kind in ("corrupt", "other_robot", "nan")}
    (root / out["corrupt"]).parent.mkdir(parents=True, exist_ok=True)
    (root / out["corrupt"]).write_bytes(good[:3000] + np.random.default_rng(other_seed).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with tempfile.TemporaryDirectory() as scratch:
        make_arm(Path(scratch), "intruder", other_seed, n_recordings=1, n_joints=5, duration_s=10.0)
        (root / out["other_robot"]).write_bytes(next(Path(scratch).rglob("run_*.csv")).read_bytes())
    lines = good.decode().splitlines()
    n_tau = sum(1 for c in lines[0].split(",") if c.startswith("tau"))
    nan_rows = [",".join(row.split(",")[:-n_tau] + ["nan"] * n_tau) for row in lines[1:]]
    (root / out["nan"]).write_text("\n".join([lines[0], *nan_rows]) + "\n")
    fleet.bad = {kind: path.as_posix() for kind, path in out.items()}
    return fleet.bad


__all__ = ["ARMS", "CHANGES", "DECLARED", "Fleet", "make_arm", "make_fleet", "truth_change", "with_bad_recordings"]
