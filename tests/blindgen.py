"""Blind test cases: random arms, analytic excitation, exact torque, chosen effects, sensor faults.

An identification method is only tested by data it did not make. This module shares no code
with armid (it imports numpy, scipy, pinocchio and yaml only): it draws a random serial arm in
standard DH (Khosla: ``Rz(theta) Tz(d) Tx(a) Rx(alpha)``) or modified DH (Craig:
``Rx(alpha) Tx(a) Rz(theta) Tz(d)``), builds the Pinocchio model the way
``../shared/tools/baseline.py`` does, moves it along finite Fourier series (Swevers) whose
velocity and acceleration are analytic, takes the exact torque from ``pin.rnea``, adds one
chosen effect, and records it as a sensor would (sampling 100 Hz-1 kHz, time-stamp jitter,
encoder quantisation, velocity noise, torque or current noise, an optional low-pass).

The robot file holds the *modeled* inertial values (the truth perturbed by 20-30 %, as a CAD
model is); the truth is in ``truth.json`` beside it. Each noisy file has a ``*_clean.csv`` twin
(the same recorded torque without noise) so the noise floor is known::

    from blindgen import make_case, relative_error
    case = make_case(7, "out/case7", effect="coulomb_friction", effect_joint=2, effect_size=0.2)
    # armid identify out/case7/ident.csv --robot out/case7/robot.yaml --validate out/case7/valid.csv \
    #     --predictions out/case7/pred.csv
    err, covered = relative_error(case.valid_csv, "out/case7/pred.csv")

Public: ``make_case`` (one case; ``load_case`` reads a folder back), ``blind_specs`` (sweeps:
clean cases across rates/noise/sensors, every effect from barely visible to large),
``relative_error`` and ``noise_floor`` (scoring against the raw validation torque at its own
stamps), ``oracle_error`` (least squares on the true kinematics: what is attainable),
``distinct_fraction`` (how much of an effect the declared model cannot absorb), ``EFFECTS``,
``NOISE_LEVELS``. Files of a case: robot.yaml, ident.csv (or ident1..K.csv), valid.csv,
``*_clean.csv`` twins, optional ptp.csv, truth.json.
"""

from __future__ import annotations

import hashlib
import json
import math
import pickle
from collections import OrderedDict
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import yaml

RATES_HZ = (100.0, 200.0, 500.0, 1000.0)

# Sensor noise levels. torque: white noise std as a fraction of each joint's peak |torque|;
# qd: velocity noise std (rad/s or m/s); counts: encoder counts per revolution (None: no
# quantisation); q: white position noise std (rad or m).
NOISE_LEVELS: dict[str, dict[str, Any]] = {
    "none": {"torque": 0.0, "qd": 0.0, "counts": None, "q": 0.0},
    "low": {"torque": 0.003, "qd": 1e-3, "counts": 2**20, "q": 0.0},
    "medium": {"torque": 0.01, "qd": 3e-3, "counts": 2**16, "q": 0.0},
    "high": {"torque": 0.03, "qd": 1e-2, "counts": 2**14, "q": 1e-4},
}

# Generator effect -> (INTERFACES.md catalogue name a diagnosis should report, arm-wide?).
EFFECTS: dict[str, tuple[str, bool]] = {
    "viscous_friction": ("viscous_friction", False),
    "coulomb_friction": ("coulomb_friction", False),
    "smooth_coulomb": ("coulomb_friction", False),  # fc * tanh(qd / v), as the published Panda model
    "stribeck_friction": ("stribeck_friction", False),
    "torque_offset": ("torque_offset", False),
    "rotor_inertia": ("rotor_inertia", False),
    "torque_gain": ("torque_gain", False),
    "time_delay": ("time_delay", True),
    "cogging": ("cogging", False),
    "spring": ("spring", False),
    "gravity_tilt": ("gravity_tilt", True),
    "load_coulomb": ("load_dependent_coulomb", False),  # (fc + c |tau_load|) sign(qd)
    "friction_all": ("coulomb_friction", True),  # Coulomb + viscous + offset on every joint: the arm-wide friction candidate (joint null)
}


# ----------------------------------------------------------------------------- the arm


@dataclass
class Link:
    """One DH/MDH row and its link's inertial values (about the COM, link-frame axes)."""

    a: float
    alpha: float
    d: float
    theta: float
    prismatic: bool
    mass: float
    com: list[float]
    inertia: list[float]  # xx xy xz yy yz zz
    q_limits: list[float]
    v_limit: float
    torque_constant: float


@dataclass
class Arm:
    convention: str  # "dh" | "mdh"
    links: list[Link]
    gravity: list[float] = field(default_factory=lambda: [0.0, 0.0, -9.81])


def _rot(axis: str, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _sym(v: list[float] | np.ndarray) -> np.ndarray:
    xx, xy, xz, yy, yz, zz = v
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


def _entries(m: np.ndarray) -> list[float]:
    return [float(m[0, 0]), float(m[0, 1]), float(m[0, 2]), float(m[1, 1]), float(m[1, 2]), float(m[2, 2])]


def _random_rotation(rng: np.random.Generator, max_angle: float | None = None) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(-math.pi, math.pi) if max_angle is None else rng.uniform(-max_angle, max_angle)
    return pin.exp3(axis * angle)


def build_model(arm: Arm, gravity: np.ndarray | None = None) -> pin.Model:
    """Pinocchio model of ``arm``, joints and link frames placed as baseline.py places them.

    DH: joint i sits at frame i-1, link frame i is ``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` after it.
    MDH: joint i is placed by ``Rx(alpha) Tx(a) Rz(theta) Tz(d)`` and the link frame is the joint's.
    A prismatic joint's q adds to d.
    """
    model = pin.Model()
    parent, placement = 0, pin.SE3.Identity()
    for i, ln in enumerate(arm.links):
        jm = pin.JointModelPZ() if ln.prismatic else pin.JointModelRZ()
        rx = pin.SE3(_rot("x", ln.alpha), np.array([ln.a, 0.0, 0.0]))
        rz = pin.SE3(_rot("z", ln.theta), np.array([0.0, 0.0, ln.d]))
        if arm.convention == "mdh":
            jid = model.addJoint(parent, jm, rx * rz, f"j{i + 1}")
            body = pin.SE3.Identity()
        else:
            jid = model.addJoint(parent, jm, placement, f"j{i + 1}")
            body = rz * rx
            placement = body
        model.appendBodyToJoint(jid, pin.Inertia(ln.mass, np.array(ln.com), _sym(ln.inertia)), body)
        parent = jid
    model.gravity.linear = np.asarray(arm.gravity if gravity is None else gravity, dtype=float)
    return model


def link_frame_parameters(ln: Link) -> list[float]:
    """Khosla's 10 parameters of the link (eq. 10): m, m*s (COM), inertia about the link frame."""
    m, c = ln.mass, np.array(ln.com)
    i_o = _sym(ln.inertia) + m * (c @ c * np.eye(3) - np.outer(c, c))
    return [m, *(m * c).tolist(), *_entries(i_o)]


def random_arm(rng: np.random.Generator, n_joints: int, convention: str, prismatic_at: int | None) -> tuple[Arm, list[dict]]:
    """A random arm and, per link, the box (dims, rotation) its inertia comes from."""
    rows = []
    for _ in range(n_joints):
        alpha = float(rng.choice([0.0, math.pi / 2, -math.pi / 2])) if rng.random() < 0.85 else float(rng.uniform(-math.pi, math.pi))
        a = float(rng.uniform(0.05, 0.5)) if rng.random() < 0.65 else 0.0
        d = float(rng.uniform(0.05, 0.5)) if (rng.random() < 0.5 or a == 0.0) else 0.0
        theta = float(rng.uniform(-math.pi, math.pi)) if rng.random() < 0.3 else 0.0
        rows.append([a, alpha, d, theta])
    masses = np.sort(rng.uniform(0.3, 8.0, n_joints))[::-1]
    links, boxes = [], []
    for i, (a, alpha, d, theta) in enumerate(rows):
        # the link's segment in its own frame: from the proximal joint's origin to the distal one
        if convention == "dh":
            start = -_rot("x", alpha).T @ np.array([a, 0.0, 0.0]) - _rot("x", alpha).T @ np.array([0.0, 0.0, d])
            end = np.zeros(3)
        else:
            start = np.zeros(3)
            if i + 1 < n_joints:
                a2, al2, d2, _ = rows[i + 1]
                end = np.array([a2, 0.0, 0.0]) + _rot("x", al2) @ np.array([0.0, 0.0, d2])
            else:
                end = np.array([0.0, 0.0, rng.uniform(0.05, 0.15)])
        com = start + rng.uniform(0.2, 0.8) * (end - start) + rng.uniform(-0.03, 0.03, 3)
        length = float(np.linalg.norm(end - start))
        dims = np.array([max(length, 0.06), rng.uniform(0.04, 0.12), rng.uniform(0.04, 0.12)]) * rng.uniform(0.8, 1.2, 3)
        rot = _random_rotation(rng)
        m = float(masses[i])
        inertia = _box_inertia(m, dims, rot)
        prismatic = i == prismatic_at
        if prismatic:
            q_lim = [-0.15, 0.15]
            v_lim = float(rng.uniform(0.2, 0.5))
            kt = float(rng.uniform(50.0, 500.0))
        else:
            half = float(rng.uniform(1.5, 3.0))
            q_lim = [-half, half]
            v_lim = float(rng.uniform(1.0, 3.0))
            kt = float(rng.uniform(2.0, 60.0))
        links.append(Link(a, alpha, d, theta, prismatic, m, com.tolist(), _entries(inertia), q_lim, v_lim, kt))
        boxes.append({"dims": dims, "rot": rot})
    return Arm(convention, links), boxes


def _box_inertia(m: float, dims: np.ndarray, rot: np.ndarray) -> np.ndarray:
    lx, ly, lz = dims
    box = m / 12.0 * np.diag([ly**2 + lz**2, lx**2 + lz**2, lx**2 + ly**2])
    return rot @ box @ rot.T


def modeled_links(rng: np.random.Generator, arm: Arm, boxes: list[dict]) -> list[dict]:
    """The CAD model: mass, COM and inertia each off by 20-30 %, still physically consistent.

    The inertia is the true box, slightly reshaped (dims +-5 %, turned up to 0.2 rad), scaled by
    1 +- 20-30 %: a positive multiple of a valid inertia stays valid.
    """
    out = []
    for ln, box in zip(arm.links, boxes):
        sgn = lambda: rng.choice([-1.0, 1.0])  # noqa: E731
        mass = ln.mass * (1 + sgn() * rng.uniform(0.2, 0.3))
        com = np.array(ln.com)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        com = com + direction * max(0.02, np.linalg.norm(com)) * rng.uniform(0.2, 0.3)
        dims = box["dims"] * rng.uniform(0.95, 1.05, 3)
        rot = box["rot"] @ _random_rotation(rng, 0.2)
        scale = 1 + sgn() * rng.uniform(0.2, 0.3)  # independent of the mass error
        out.append({"mass": float(mass), "com": com.tolist(), "inertia": _entries(scale * _box_inertia(ln.mass, dims, rot))})
    return out


# ---------------------------------------------------------------------- the excitation


@dataclass
class Fourier:
    """q_j(t) = q0_j + sum_l a_jl/(w l) sin(w l t) - b_jl/(w l) cos(w l t), w = 2 pi f0 (Swevers)."""

    f0: float
    a: np.ndarray  # (n, L)
    b: np.ndarray  # (n, L)
    q0: np.ndarray  # (n,)

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w = 2 * math.pi * self.f0
        wl = w * np.arange(1, self.a.shape[1] + 1)  # (L,)
        s, c = np.sin(np.multiply.outer(t, wl)), np.cos(np.multiply.outer(t, wl))  # (N, L)
        q = self.q0 + s @ (self.a / wl).T - c @ (self.b / wl).T
        qd = c @ self.a.T + s @ self.b.T
        qdd = -s @ (self.a * wl).T + c @ (self.b * wl).T
        return q, qd, qdd


def random_fourier(rng: np.random.Generator, arm: Arm, f0: float | None = None) -> Fourier:
    """Random coefficients scaled so q stays in 40-85 % of the range and |qd| under 80 % of its limit."""
    n = len(arm.links)
    f0 = float(rng.uniform(0.05, 0.3)) if f0 is None else f0
    harmonics = int(rng.integers(3, 6))
    a, b = rng.normal(size=(n, harmonics)), rng.normal(size=(n, harmonics))
    tt = np.linspace(0.0, 1.0 / f0, 4001)
    q0 = np.zeros(n)
    for j, ln in enumerate(arm.links):
        probe = Fourier(f0, a[j : j + 1], b[j : j + 1], np.zeros(1))
        q, qd, _ = probe(tt)
        half = 0.5 * (ln.q_limits[1] - ln.q_limits[0])
        scale = min(rng.uniform(0.4, 0.85) * half / (0.5 * np.ptp(q)), 0.8 * ln.v_limit / np.abs(qd).max())
        a[j] *= scale
        b[j] *= scale
        mid = 0.5 * (q.max() + q.min()) * scale
        room = half - 0.5 * np.ptp(q) * scale
        centre = 0.5 * (ln.q_limits[0] + ln.q_limits[1]) + rng.uniform(-0.9, 0.9) * max(room, 0.0) * 0.9
        q0[j] = centre - mid
    return Fourier(f0, a, b, q0)


@dataclass
class PointToPoint:
    """Quintic moves between random poses, each followed by a dwell; analytic q, qd, qdd."""

    knots: np.ndarray  # (K+1, n) poses
    t_start: np.ndarray  # (K,) move start times
    t_move: np.ndarray  # (K,) move durations

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k = np.clip(np.searchsorted(self.t_start, t, side="right") - 1, 0, len(self.t_start) - 1)
        s = np.clip((t - self.t_start[k]) / self.t_move[k], 0.0, 1.0)
        moving = ((t - self.t_start[k]) < self.t_move[k]) & (t >= self.t_start[k])
        delta = self.knots[k + 1] - self.knots[k]
        pos = 10 * s**3 - 15 * s**4 + 6 * s**5
        vel = (30 * s**2 - 60 * s**3 + 30 * s**4) / self.t_move[k]
        acc = (60 * s - 180 * s**2 + 120 * s**3) / self.t_move[k] ** 2
        q = self.knots[k] + delta * pos[:, None]
        return q, delta * (vel * moving)[:, None], delta * (acc * moving)[:, None]


def random_ptp(rng: np.random.Generator, arm: Arm, duration_s: float) -> PointToPoint:
    lo = np.array([ln.q_limits[0] for ln in arm.links])
    hi = np.array([ln.q_limits[1] for ln in arm.links])
    vmax = np.array([ln.v_limit for ln in arm.links])
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    knots, starts, moves = [mid + rng.uniform(-0.6, 0.6, len(lo)) * half], [], []
    t = 0.5
    while t < duration_s:
        nxt = mid + rng.uniform(-0.6, 0.6, len(lo)) * half
        tm = max(0.5, float(np.max(1.875 * np.abs(nxt - knots[-1]) / (0.6 * vmax))))  # quintic peak speed 1.875 D/T
        starts.append(t)
        moves.append(tm)
        knots.append(nxt)
        t += tm + rng.uniform(0.5, 2.0)
    return PointToPoint(np.array(knots), np.array(starts), np.array(moves))


# ---------------------------------------------------------------------- torque and effects


def rigid_torque(model: pin.Model, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """(N, n) inverse dynamics by Pinocchio's RNEA, sample by sample."""
    data = model.createData()
    return np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(len(q))])


_SWEEPS: OrderedDict[bytes, np.ndarray] = OrderedDict()


def arm_torque(arm: Arm, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, gravity: np.ndarray | None = None) -> np.ndarray:
    """:func:`rigid_torque` of ``arm`` under ``gravity`` (default its own), the last few sweeps
    kept by content: sizing an effect evaluates the same trajectory again and again (209 RNEA
    sweeps for 12 cases, half of the generator's time, where 50 differ)."""
    g = np.asarray(arm.gravity if gravity is None else gravity, dtype=float)
    digest = hashlib.blake2b(pickle.dumps(arm) + g.tobytes(), digest_size=20)
    for x in (q, qd, qdd):
        digest.update(np.ascontiguousarray(x, dtype=float).tobytes())
    key = digest.digest()
    if key not in _SWEEPS:
        _SWEEPS[key] = rigid_torque(build_model(arm, g), q, qd, qdd)
        if len(_SWEEPS) > 8:
            _SWEEPS.popitem(last=False)
    _SWEEPS.move_to_end(key)
    return _SWEEPS[key].copy()


@dataclass
class Effect:
    """The effect actually applied: generator name, 0-based joints, parameters (per joint lists)."""

    name: str
    joints: list[int]
    params: dict[str, Any]


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _as_list(effects: Effect | list[Effect] | None) -> list[Effect]:
    return [] if effects is None else [effects] if isinstance(effects, Effect) else list(effects)


def recorded_torque(arm: Arm, traj, t: np.ndarray, effects: Effect | list[Effect] | None) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """Noise-free recorded torque at stamps t, and (q, qd, qdd) at t.

    The rigid body under the (possibly tilted) gravity, plus the additive effects, then the
    drive gains, then the offsets. With a time delay all of it is the torque at ``t - delay``
    (the torque channel lags the positions), evaluated on the analytic trajectory.
    """
    effects = _as_list(effects)
    q, qd, qdd = traj(t)
    gravity = np.array(arm.gravity, dtype=float)
    delay = 0.0
    for e in effects:
        if e.name == "gravity_tilt":
            gravity = _rot(e.params["axis"], e.params["angle_rad"]) @ gravity
        elif e.name == "time_delay":
            delay += e.params["delay_s"]
        elif e.name not in EFFECTS:
            raise ValueError(f"unknown effect {e.name!r} (known: {', '.join(EFFECTS)})")
    qe, qde, qdde = traj(t - delay) if delay else (q, qd, qdd)
    tau = arm_torque(arm, qe, qde, qdde, gravity)
    out = tau.copy()
    order = {"torque_gain": 1, "torque_offset": 2}  # additive physics first, then the drive gain, then the offset
    for e in sorted(effects, key=lambda e: order.get(e.name, 0)):
        p, name = e.params, e.name
        for k, j in enumerate(e.joints):
            v = qde[:, j]
            if name == "viscous_friction":
                out[:, j] += p["fv"][k] * v
            elif name == "coulomb_friction":
                out[:, j] += p["fc"][k] * np.sign(v)
            elif name == "smooth_coulomb":
                out[:, j] += p["fc"][k] * np.tanh(v / p["v_s"][k])
            elif name == "stribeck_friction":
                out[:, j] += (p["fc"][k] + (p["fs"][k] - p["fc"][k]) * np.exp(-((v / p["vs"][k]) ** 2))) * np.sign(v)
            elif name == "torque_offset":
                out[:, j] += p["offset"][k]
            elif name == "rotor_inertia":
                out[:, j] += p["ia"][k] * qdde[:, j]
            elif name == "torque_gain":
                out[:, j] *= p["gain"][k]
            elif name == "cogging":
                ang = 2 * math.pi * qe[:, j] / p["period_rad"][k]
                out[:, j] += p["a_sin"][k] * np.sin(ang) + p["a_cos"][k] * np.cos(ang)
            elif name == "spring":
                out[:, j] += p["k"][k] * (qe[:, j] - p["q0"][k])
            elif name == "load_coulomb":
                out[:, j] += (p["fc"][k] + p["c_load"][k] * np.abs(tau[:, j])) * np.sign(v)
            elif name == "friction_all":
                out[:, j] += p["fc"][k] * np.sign(v) + p["fv"][k] * v + p["offset"][k]
    return out, (q, qd, qdd)


def size_effect(rng: np.random.Generator, arm: Arm, traj, t: np.ndarray, name: str, joints: list[int], size: float,
                overrides: dict[str, Any] | None = None) -> Effect:
    """Parameters making the effect's RMS about ``size`` times the joint's rigid-body torque RMS.

    Measured on the identification run; arm-wide effects (delay, tilt) are sized against the
    whole torque, linearly from a small trial value.
    """
    q, qd, qdd = traj(t)
    tau = arm_torque(arm, q, qd, qdd)
    rms = [max(_rms(tau[:, j]), 1e-3) for j in joints]
    sign = lambda: float(rng.choice([-1.0, 1.0]))  # noqa: E731
    p: dict[str, Any] = {}
    if name == "viscous_friction":
        p["fv"] = [size * r / _rms(qd[:, j]) for r, j in zip(rms, joints)]
    elif name == "coulomb_friction":
        p["fc"] = [size * r for r in rms]
    elif name == "smooth_coulomb":
        p["v_s"] = [float(rng.uniform(0.01, 0.05)) * arm.links[j].v_limit for j in joints]
        p["fc"] = [size * r / _rms(np.tanh(qd[:, j] / vs)) for r, j, vs in zip(rms, joints, p["v_s"])]
    elif name == "stribeck_friction":
        p["vs"] = [float(rng.uniform(0.03, 0.15)) * arm.links[j].v_limit for j in joints]
        ratio = [float(rng.uniform(1.5, 3.0)) for _ in joints]
        shape = [_rms((1 + (rt - 1) * np.exp(-((qd[:, j] / vs) ** 2))) * np.sign(qd[:, j])) for j, vs, rt in zip(joints, p["vs"], ratio)]
        p["fc"] = [size * r / s for r, s in zip(rms, shape)]
        p["fs"] = [fc * rt for fc, rt in zip(p["fc"], ratio)]
    elif name == "torque_offset":
        p["offset"] = [sign() * size * r for r in rms]
    elif name == "rotor_inertia":
        p["ia"] = [size * r / _rms(qdd[:, j]) for r, j in zip(rms, joints)]
    elif name == "torque_gain":
        p["gain"] = [1.0 + sign() * min(size, 0.75) for _ in joints]  # a gain of 0 is a dead sensor (refused as bad input), not an effect
    elif name == "cogging":
        k = [int(rng.integers(4, 40)) for _ in joints]
        p["period_rad"] = [2 * math.pi / kk for kk in k]
        phase = [float(rng.uniform(0, 2 * math.pi)) for _ in joints]
        amp = [size * r * math.sqrt(2) for r in rms]
        p["a_sin"] = [a * math.cos(ph) for a, ph in zip(amp, phase)]
        p["a_cos"] = [a * math.sin(ph) for a, ph in zip(amp, phase)]
    elif name == "spring":
        lim = [arm.links[j].q_limits for j in joints]
        p["q0"] = [float(rng.uniform(lo, hi)) for lo, hi in lim]
        p["k"] = [size * r / _rms(q[:, j] - q0) for r, j, q0 in zip(rms, joints, p["q0"])]
    elif name == "load_coulomb":
        share = [float(rng.uniform(0.3, 0.7)) for _ in joints]
        shape = [_rms((sh + (1 - sh) * np.abs(tau[:, j]) / _rms(tau[:, j])) * np.sign(qd[:, j])) for sh, j in zip(share, joints)]
        p["fc"] = [sh * size * r / sp for sh, r, sp in zip(share, rms, shape)]
        p["c_load"] = [(1 - sh) * size * r / _rms(tau[:, j]) / sp for sh, r, j, sp in zip(share, rms, joints, shape)]
    elif name == "friction_all":
        share = [rng.dirichlet([2.0, 2.0, 1.0]) for _ in joints]
        sg = [sign() for _ in joints]
        shape = [_rms(s[0] * np.sign(qd[:, j]) + s[1] * qd[:, j] / _rms(qd[:, j]) + g * s[2]) for s, j, g in zip(share, joints, sg)]
        p["fc"] = [s[0] * size * r / sp for s, r, sp in zip(share, rms, shape)]
        p["fv"] = [s[1] * size * r / _rms(qd[:, j]) / sp for s, r, j, sp in zip(share, rms, joints, shape)]
        p["offset"] = [g * s[2] * size * r / sp for s, r, g, sp in zip(share, rms, sg, shape)]
    elif name in ("time_delay", "gravity_tilt"):
        trial = {"time_delay": {"delay_s": 0.005}, "gravity_tilt": {"axis": str(rng.choice(["x", "y"])), "angle_rad": 0.01}}[name]
        key = "delay_s" if name == "time_delay" else "angle_rad"
        if not overrides or key not in overrides:
            moved, _ = recorded_torque(arm, traj, t, Effect(name, joints, trial))
            rel = np.linalg.norm(moved - tau) / np.linalg.norm(tau)
            limit = 0.03 if name == "time_delay" else 0.2  # delays of real drives: 1-30 ms
            trial[key] = float(min(limit, size * trial[key] / max(rel, 1e-12)))
            if name == "gravity_tilt":
                trial[key] *= sign()
        p.update(trial)
    else:
        raise ValueError(f"unknown effect {name!r} (known: {', '.join(EFFECTS)})")
    p.update(overrides or {})
    return Effect(name, joints, p)


# ---------------------------------------------------------------------- sensors and files


@dataclass
class Sensor:
    rate_hz: float
    jitter: float  # std of the stamp error as a fraction of the period
    noise: str
    velocity: bool
    currents: bool
    lowpass_hz: float | None
    torque_noise: np.ndarray  # (n,) std in N*m (or N) at the joint
    qd_noise: float
    counts: int | None
    q_noise: float
    current_lsb: float | None = None  # A


def stamps(rng: np.random.Generator, duration_s: float, rate_hz: float, jitter: float) -> np.ndarray:
    """Sample times rounded to the microsecond (as real logs), jittered but increasing."""
    period = 1.0 / rate_hz
    t = np.arange(int(round(duration_s * rate_hz))) * period
    if jitter > 0:
        t = t + np.clip(rng.normal(0.0, jitter * period, t.shape), -0.45 * period, 0.45 * period)
        t[0] = 0.0
    return np.round(t, 6)


def lowpass_first_order(t: np.ndarray, x: np.ndarray, cutoff_hz: float) -> np.ndarray:
    """First-order low-pass of x (N, n) sampled at stamps t, exact for a piecewise-linear input."""
    tau_c = 1.0 / (2 * math.pi * cutoff_hz)
    y = np.empty_like(x)
    y[0] = x[0]
    for k in range(1, len(t)):
        h = t[k] - t[k - 1]
        e = math.exp(-h / tau_c)
        slope = (x[k] - x[k - 1]) / h
        # y' = (x - y)/tau_c with x linear over the step: closed form
        y[k] = x[k] - tau_c * slope + (y[k - 1] - x[k - 1] + tau_c * slope) * e
    return y


def _write_csv(path: Path, cols: list[str], data: np.ndarray) -> None:
    fmt = ["%.6f"] + ["%.10g"] * (len(cols) - 1)
    np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt=fmt)


def record(rng: np.random.Generator, arm: Arm, traj, t: np.ndarray, effect: Effect | list[Effect] | None, sensor: Sensor,
           path: Path, clean_path: Path | None) -> dict[str, Any]:
    """Write one recording (and its noise-free torque twin); return its noise floor and size."""
    n = len(arm.links)
    clean, (q, qd, _) = recorded_torque(arm, traj, t, effect)
    if sensor.lowpass_hz:
        clean = lowpass_first_order(t, clean, sensor.lowpass_hz)
    noisy = clean + rng.normal(size=clean.shape) * sensor.torque_noise
    qm = q + rng.normal(size=q.shape) * sensor.q_noise
    if sensor.counts:
        for j, ln in enumerate(arm.links):
            step = (2 * math.pi if not ln.prismatic else 1.0) / sensor.counts
            qm[:, j] = np.round(qm[:, j] / step) * step
    cols, blocks = ["t"] + [f"q{j + 1}" for j in range(n)], [t[:, None], qm]
    if sensor.velocity:
        cols += [f"qd{j + 1}" for j in range(n)]
        blocks.append(qd + rng.normal(size=qd.shape) * sensor.qd_noise)
    kt = np.array([ln.torque_constant for ln in arm.links])
    if sensor.currents:
        cols += [f"i{j + 1}" for j in range(n)]
        current = noisy / kt
        if sensor.current_lsb:
            current = np.round(current / sensor.current_lsb) * sensor.current_lsb
            noisy = current * kt  # what the file says, for the noise floor
        blocks.append(current)
    else:
        cols += [f"tau{j + 1}" for j in range(n)]
        blocks.append(noisy)
    _write_csv(path, cols, np.hstack(blocks))
    if clean_path is not None:
        _write_csv(clean_path, ["t"] + [f"tau{j + 1}" for j in range(n)], np.column_stack([t, clean]))
    floor = float(np.linalg.norm(noisy - clean) / np.linalg.norm(noisy))
    return {"samples": len(t), "noise_floor": floor, "noise_norm": float(np.linalg.norm(noisy - clean)),
            "max_abs_torque": np.abs(clean).max(axis=0).tolist()}


# ---------------------------------------------------------------------- the case


@dataclass
class Case:
    """Paths and metadata of one generated case (all paths absolute)."""

    seed: int
    out_dir: Path
    robot_yaml: Path
    ident_csv: Path
    valid_csv: Path
    valid_clean_csv: Path
    truth_json: Path
    ptp_csv: Path | None
    ptp_clean_csv: Path | None
    n_joints: int
    convention: str
    rate_hz: float
    noise: str
    velocity: bool
    currents: bool
    jitter: float
    lowpass_hz: float | None
    effect: str | None  # generator name
    expected: str | None  # INTERFACES.md catalogue name a diagnosis should report
    effect_joint: int | None  # 1-based; None for arm-wide (or no effect)
    effect_size: float | None  # requested size (relative to the joint's rigid-body torque RMS)
    effect_realized: float | None  # measured: ||recorded - rigid|| / ||rigid|| on the affected joints, validation run
    noise_floor: float  # validation: ||tau_noisy - tau_clean|| / ||tau_noisy||
    ptp_noise_floor: float | None
    params: dict[str, Any]  # the main effect's parameters
    ident_csvs: list[Path]  # every identification run (ident_csv is the first)
    effect_distinct: float | None = None  # fraction of the effect the declared model cannot absorb (distinct_fraction)
    effect_visible: float | None = None  # validation: ||effect torque||_F / ||torque noise||_F over all joints


MIN_DISTINCT = 0.25
"""A randomly placed effect must keep at least this fraction of its torque outside the model's span."""


def distinct_fraction(arm: Arm, traj, t: np.ndarray, effects: list[Effect], baseline: list[Effect], declare: list[dict[str, Any]],
                      max_samples: int = 3000) -> float:
    """How much of an effect no model parameter can absorb: ||(I - P) d|| / ||d||.

    ``d`` is the recorded torque with ``effects`` minus that with ``baseline`` (stacked over
    joints and samples), ``P`` the projection onto the rigid-body regressor (Pinocchio's, under
    the nominal gravity) and the declared linear effects' columns. 0: the effect is a rigid-body
    parameter's twin (rotor inertia on joint 1 and Izz1); 1: nothing in the model looks like it.
    """
    ts = t[:: max(1, len(t) // max_samples)]
    with_e, (q, qd, qdd) = recorded_torque(arm, traj, ts, effects)
    d = (with_e - recorded_torque(arm, traj, ts, baseline)[0]).reshape(-1)
    model = build_model(arm)
    data = model.createData()
    n = model.nv
    y = np.stack([pin.computeJointTorqueRegressor(model, data, q[k], qd[k], qdd[k]) for k in range(len(ts))])
    cols = {"coulomb_friction": lambda j: np.sign(qd[:, j]), "viscous_friction": lambda j: qd[:, j],
            "torque_offset": lambda j: np.ones(len(ts)), "rotor_inertia": lambda j: qdd[:, j]}
    extra = []
    for dcl in declare:
        if dcl.get("effect") in cols:
            for j in range(n) if dcl.get("joint") is None else [int(dcl["joint"]) - 1]:
                c = np.zeros((len(ts), n))
                c[:, j] = cols[dcl["effect"]](j)
                extra.append(c[:, :, None])
    a = np.concatenate([y, *extra], axis=2).reshape(len(ts) * n, -1)
    a = a / np.maximum(np.linalg.norm(a, axis=0), 1e-12)
    residual = d - a @ np.linalg.lstsq(a, d, rcond=1e-10)[0]
    return float(np.linalg.norm(residual) / max(np.linalg.norm(d), 1e-300))


MAX_SNR_SIZE = 1.0
"""An snr-sized effect stays within its joint's own rigid-body torque RMS (a weak joint caps its visibility)."""


def _size_for_snr(arm: Arm, traj, t: np.ndarray, name: str, joints: list[int], overrides: dict[str, Any] | None,
                  extras: list[Effect], snr: float, level: float, draws: int, size: float) -> tuple[Effect, float]:
    """The effect sized so its torque, over all joints, is ``snr`` times the whole arm's torque noise.

    ``||effect||_F = snr * sqrt(N * sum_j std_j^2)`` on the identification run, with std_j the
    noise level times joint j's peak torque (without the effect): snr 1-2 is barely visible in
    the whole-arm error (about sqrt(1 + snr^2) times the noise floor if nothing absorbs it).
    """
    base = recorded_torque(arm, traj, t, extras)[0]
    target = snr * math.sqrt(len(t) * float(np.sum((level * np.abs(base).max(axis=0)) ** 2)))
    for _ in range(3):
        eff = size_effect(np.random.default_rng(draws), arm, traj, t, name, joints, size, overrides)
        norm = float(np.linalg.norm(recorded_torque(arm, traj, t, [eff, *extras])[0] - base))
        if norm <= 0 or abs(norm / target - 1) < 1e-3 or size >= MAX_SNR_SIZE:
            break
        size = min(MAX_SNR_SIZE, size * target / norm)
    return size_effect(np.random.default_rng(draws), arm, traj, t, name, joints, size, overrides), size


def _resolve_joints(name: str, joint: int | str | None, n: int, u: float) -> list[int]:
    """0-based joints of an effect: every joint for arm-wide effects or "all", else the 1-based one, else drawn (u in [0, 1))."""
    if EFFECTS[name][1] or joint == "all":
        return list(range(n))
    if joint is None:
        return [min(n - 1, int(u * n))]
    if not 1 <= int(joint) <= n:
        raise ValueError(f"effect joint {joint} is not in 1..{n}")
    return [int(joint) - 1]


def make_case(seed: int, out_dir: str | Path, n_joints: int | None = None, convention: str | None = None,
              rate_hz: float | None = None, noise: str | None = "medium", effect: str | None = None,
              effect_joint: int | str | None = None, effect_size: float | None = None,
              effect_params: dict[str, Any] | None = None, velocity: bool | None = True, currents: bool | None = False,
              jitter: float | None = 0.0, duration_s: float | None = None, valid_duration_s: float | None = None,
              prismatic: bool | None = None, lowpass_hz: float | None = None, ptp: bool = False,
              declare: list[dict[str, Any]] | None = None, extra_effects: list[dict[str, Any]] | None = None,
              n_ident: int = 1, current_lsb: float | None = None, effect_snr: float | None = None) -> Case:
    """Make one blind case in ``out_dir``: robot.yaml, ident.csv, valid.csv, valid_clean.csv, truth.json.

    Deterministic per ``seed``; every option left ``None`` is drawn from the seed (each option
    from its own stream, so fixing one does not change the others). ``effect_joint`` is 1-based,
    ``"all"`` for every joint, or None for a random joint. ``effect_size`` is the effect's RMS
    relative to the joint's rigid-body torque RMS on the (first) identification run (default
    log-uniform 0.03-0.3). ``extra_effects`` adds more, each ``{"effect", "joint", "size",
    "params"}`` as above (e.g. the friction a robot file declares, under an undeclared effect).
    ``declare`` goes into the robot file's ``effects`` list. ``ptp`` adds ptp.csv/ptp_clean.csv,
    a point-to-point validation run. ``n_ident`` > 1 writes ident1.csv..identK.csv, Fourier
    runs of one design with different coefficients. ``current_lsb`` quantises the currents (A).
    ``effect_snr`` sets the size instead: the effect's torque over all joints is that many times
    the whole arm's torque noise (1-2 is barely above the noise floor; see ``_size_for_snr``).
    """
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(8)]
    r_arm, r_exc, r_sens, r_eff, r_noise, r_model, r_opt, r_ptp = streams
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)

    draw = {  # drawn always, in a fixed order, so options do not shift each other
        "n": int(r_opt.integers(3, 8)), "conv": str(r_opt.choice(["dh", "mdh"])), "rate": float(r_opt.choice(RATES_HZ)),
        "noise": str(r_opt.choice(["low", "medium", "high"])), "vel": bool(r_opt.random() < 0.6),
        "cur": bool(r_opt.random() < 0.4), "jit": float(r_opt.choice([0.0, r_opt.uniform(0.05, 0.2)])),
        "pri": bool(r_opt.random() < 0.2), "size": float(math.exp(r_opt.uniform(math.log(0.03), math.log(0.3)))),
        "ej": float(r_opt.random()), "pj": float(r_opt.random()),
    }
    n = n_joints if n_joints is not None else draw["n"]
    convention = convention or draw["conv"]
    rate_hz = float(rate_hz or draw["rate"])
    noise = noise or draw["noise"]
    velocity = draw["vel"] if velocity is None else velocity
    currents = draw["cur"] if currents is None else currents
    jitter = draw["jit"] if jitter is None else jitter
    prismatic = draw["pri"] if prismatic is None else prismatic
    prismatic_at = min(n - 1, int(draw["pj"] * n)) if prismatic else None
    if effect is not None and effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r} (known: {', '.join(EFFECTS)})")
    if noise not in NOISE_LEVELS:
        raise ValueError(f"unknown noise level {noise!r} (known: {', '.join(NOISE_LEVELS)})")
    if convention not in ("dh", "mdh"):
        raise ValueError(f"convention must be dh or mdh, got {convention!r}")
    if n < 1 or n_ident < 1:
        raise ValueError(f"n_joints and n_ident must be positive, got {n} and {n_ident}")

    arm, boxes = random_arm(r_arm, n, convention, prismatic_at)
    modeled = modeled_links(r_model, arm, boxes)
    fourier_id = [random_fourier(r_exc, arm)]
    def similar() -> float:  # same design, new coefficients: a nearby base frequency within 0.05-0.3 Hz
        return float(np.clip(fourier_id[0].f0 * r_exc.uniform(0.8, 1.25), 0.05, 0.3))

    fourier_va = random_fourier(r_exc, arm, similar())
    fourier_id += [random_fourier(r_exc, arm, similar()) for _ in range(n_ident - 1)]
    dur_id = duration_s if duration_s is not None else float(np.clip(2.0 / fourier_id[0].f0, 20.0, 45.0))
    dur_va = valid_duration_s if valid_duration_s is not None else float(np.clip(1.0 / fourier_va.f0, 10.0, 20.0))
    t_id = [stamps(r_sens, dur_id, rate_hz, jitter)]
    t_va = stamps(r_sens, dur_va, rate_hz, jitter)
    t_id += [stamps(r_sens, dur_id, rate_hz, jitter) for _ in range(n_ident - 1)]

    extras = []
    for e in extra_effects or []:
        if e["effect"] not in EFFECTS:
            raise ValueError(f"unknown effect {e['effect']!r} (known: {', '.join(EFFECTS)})")
        joints = _resolve_joints(e["effect"], e.get("joint"), n, float(r_eff.random()))
        extras.append(size_effect(r_eff, arm, fourier_id[0], t_id[0], e["effect"], joints, float(e.get("size", 0.1)), e.get("params")))

    main, distinct = None, None
    size = effect_size if effect_size is not None else draw["size"]
    if effect is not None:
        first = _resolve_joints(effect, effect_joint, n, draw["ej"])
        # a joint drawn at random must be one where the effect is not a rigid-body parameter's twin
        # (rotor inertia on joint 1 is Izz1): try the joints in turn from the drawn one
        tries = [[(first[0] + k) % n] for k in range(n)] if effect_joint is None and len(first) == 1 else [first]
        if effect_snr is not None and NOISE_LEVELS[noise]["torque"] == 0:
            raise ValueError("effect_snr needs torque noise (noise other than 'none')")
        for joints in tries:
            draws = int(r_eff.integers(2**62))  # the same random choices (signs, periods) on every sizing pass
            main = size_effect(np.random.default_rng(draws), arm, fourier_id[0], t_id[0], effect, joints, size, effect_params)
            if effect_snr is not None:  # two passes: the size is (nearly) linear in the parameters
                main, size = _size_for_snr(arm, fourier_id[0], t_id[0], effect, joints, effect_params, extras, effect_snr,
                                           NOISE_LEVELS[noise]["torque"], draws, size)
            distinct = distinct_fraction(arm, fourier_id[0], t_id[0], [main, *extras], extras, declare or [])
            if distinct >= MIN_DISTINCT:
                break
    effects = ([main] if main else []) + extras

    level = NOISE_LEVELS[noise]
    # torque noise relative to each joint's peak recorded torque on the identification run
    peak = np.abs(recorded_torque(arm, fourier_id[0], t_id[0], effects)[0]).max(axis=0)
    sensor = Sensor(rate_hz, jitter, noise, velocity, currents, lowpass_hz, level["torque"] * peak, level["qd"], level["counts"], level["q"],
                    current_lsb)

    names = ["ident"] if n_ident == 1 else [f"ident{k + 1}" for k in range(n_ident)]
    ident_csvs = [out / f"{nm}.csv" for nm in names]
    infos = {nm: record(r_noise, arm, f, t, effects, sensor, path, out / f"{nm}_clean.csv")
             for nm, f, t, path in zip(names, fourier_id, t_id, ident_csvs)}
    valid_csv, valid_clean = out / "valid.csv", out / "valid_clean.csv"
    infos["valid"] = record(r_noise, arm, fourier_va, t_va, effects, sensor, valid_csv, valid_clean)
    ptp_csv, ptp_clean, traj_pt = None, None, None
    if ptp:
        traj_pt = random_ptp(r_ptp, arm, dur_va)
        ptp_csv, ptp_clean = out / "ptp.csv", out / "ptp_clean.csv"
        infos["ptp"] = record(r_noise, arm, traj_pt, stamps(r_sens, dur_va, rate_hz, jitter), effects, sensor, ptp_csv, ptp_clean)

    realized, visible = None, None
    if main is not None:  # the main effect alone, on the validation run
        rigid, _ = recorded_torque(arm, fourier_va, t_va, extras)
        moved, _ = recorded_torque(arm, fourier_va, t_va, effects)
        js = main.joints
        realized = float(np.linalg.norm(moved[:, js] - rigid[:, js]) / np.linalg.norm(rigid[:, js]))
        noise_norm = infos["valid"]["noise_norm"]
        visible = float(np.linalg.norm(moved - rigid) / noise_norm) if noise_norm > 0 else None  # None: noise-free case

    peaks = np.max([info["max_abs_torque"] for info in infos.values()], axis=0)
    robot_yaml = out / "robot.yaml"
    _write_robot(robot_yaml, f"blind_{seed}", arm, modeled, peaks, declare or [])

    joint_1 = None if main is None or len(main.joints) != 1 else main.joints[0] + 1

    def describe(e: Effect, requested: float | None) -> dict[str, Any]:
        one = e.joints[0] + 1 if len(e.joints) == 1 else None
        return {"name": e.name, "expected": EFFECTS[e.name][0], "joint": one, "joints": [j + 1 for j in e.joints],
                "size": requested, "params": e.params}

    truth = {
        "seed": seed, "convention": convention, "n_joints": n, "gravity": arm.gravity,
        "links": [asdict(ln) for ln in arm.links],
        "khosla_parameters": [link_frame_parameters(ln) for ln in arm.links],
        "modeled": modeled,
        "excitation": {k: {"f0": f.f0, "a": f.a.tolist(), "b": f.b.tolist(), "q0": f.q0.tolist()}
                       for k, f in [*zip(names, fourier_id), ("valid", fourier_va)]},
        "sensor": {"rate_hz": rate_hz, "jitter": jitter, "noise": noise, "velocity": velocity, "currents": currents,
                   "lowpass_hz": lowpass_hz, "torque_noise_std": sensor.torque_noise.tolist(), "qd_noise_std": sensor.qd_noise,
                   "counts_per_rev": sensor.counts, "q_noise_std": sensor.q_noise, "current_lsb": current_lsb},
        "effect": None if main is None else {**describe(main, size), "realized": realized, "snr": effect_snr, "distinct": distinct,
                                            "visible": visible},
        "extra_effects": [describe(e, float(d.get("size", 0.1))) for e, d in zip(extras, extra_effects or [])],
        "declared": declare or [],
        "files": infos,
    }
    if traj_pt is not None:
        truth["excitation"]["ptp"] = {"knots": traj_pt.knots.tolist(), "t_start": traj_pt.t_start.tolist(), "t_move": traj_pt.t_move.tolist()}
    truth_json = out / "truth.json"
    truth_json.write_text(json.dumps(truth, indent=1))
    return Case(seed, out, robot_yaml, ident_csvs[0], valid_csv, valid_clean, truth_json, ptp_csv, ptp_clean, n, convention, rate_hz,
                noise, velocity, currents, jitter, lowpass_hz, effect, EFFECTS[effect][0] if effect else None, joint_1,
                size if main else None, realized, infos["valid"]["noise_floor"],
                infos["ptp"]["noise_floor"] if ptp else None, main.params if main else {}, ident_csvs, distinct, visible)


def load_case(out_dir: str | Path) -> Case:
    """The ``Case`` of a folder ``make_case`` wrote (read back from its truth.json)."""
    out = Path(out_dir).resolve()
    truth = json.loads((out / "truth.json").read_text())
    se, eff = truth["sensor"], truth["effect"]
    runs = [p for p in out.glob("ident[0-9]*.csv") if p.stem[5:].isdigit()]
    idents = [out / "ident.csv"] if (out / "ident.csv").exists() else sorted(runs, key=lambda p: int(p.stem[5:]))
    ptp = (out / "ptp.csv").exists()
    return Case(truth["seed"], out, out / "robot.yaml", idents[0], out / "valid.csv", out / "valid_clean.csv", out / "truth.json",
                out / "ptp.csv" if ptp else None, out / "ptp_clean.csv" if ptp else None, truth["n_joints"], truth["convention"],
                se["rate_hz"], se["noise"], se["velocity"], se["currents"], se["jitter"], se["lowpass_hz"],
                eff["name"] if eff else None, eff["expected"] if eff else None, eff["joint"] if eff else None,
                eff["size"] if eff else None, eff["realized"] if eff else None, truth["files"]["valid"]["noise_floor"],
                truth["files"]["ptp"]["noise_floor"] if ptp else None, eff["params"] if eff else {}, idents,
                eff.get("distinct") if eff else None, eff.get("visible") if eff else None)


def _write_robot(path: Path, name: str, arm: Arm, modeled: list[dict], peaks: np.ndarray, declare: list[dict]) -> None:
    joints = []
    for i, (ln, mo) in enumerate(zip(arm.links, modeled)):
        joints.append({
            "name": f"j{i + 1}", "type": "prismatic" if ln.prismatic else "revolute",
            "a": ln.a, "alpha": ln.alpha, "d": ln.d, "theta": ln.theta, "torque_constant": ln.torque_constant,
            "limits": {"position": list(ln.q_limits), "velocity": ln.v_limit, "torque": round(1.5 * float(peaks[i]) + 0.01, 3)},
            "inertial": {"mass": mo["mass"], "com": mo["com"], "inertia": mo["inertia"]},
        })
    doc = {"name": name, "gravity": [0.0, 0.0, -9.81], "convention": arm.convention, "joints": joints, "effects": declare}
    path.write_text("# Blind case by tests/blindgen.py: modeled inertials are the truth off by 20-30 % (truth.json)\n"
                    + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))


def blind_specs(kind: str, count: int, seed0: int = 0, effects: list[str] | None = None,
                snrs: tuple[float, ...] = (1.5, 3.0, 6.0, 12.0, 25.0)) -> list[dict[str, Any]]:
    """``make_case`` keyword sets for a blind sweep (``seed`` included).

    ``clean``: ``count`` cases, no effect, rates 100/200/500/1000 Hz, noise low/medium/high,
    velocity or not, torque or current, jitter or not, all rotating at co-prime periods.
    ``effects``: each effect (all of EFFECTS by default) on ``count`` seeds, on a random joint,
    at sizes from barely above the noise floor to large (``snrs``: whole-arm effect / noise,
    rotating), sensors rotating as for clean, except that a torque gain's cases record currents
    (a gain is a torque constant's error: a joint torque sensor has none). Effect case k uses seed0 + k like clean case k:
    the same arm and sensor draws (a paired design), only the effect differs.
    """
    rates, levels = (100.0, 200.0, 500.0, 1000.0), ("low", "medium", "high")

    def sensor(k: int) -> dict[str, Any]:
        return {"rate_hz": rates[k % 4], "noise": levels[k % 3], "velocity": k % 5 not in (1, 3),
                "currents": k % 7 in (2, 4, 6), "jitter": 0.1 if k % 2 else 0.0}

    if kind == "clean":
        return [{"seed": seed0 + k, **sensor(k)} for k in range(count)]
    if kind == "effects":
        out = []
        for e_index, name in enumerate(effects or list(EFFECTS)):
            for k in range(count):
                m = e_index * count + k
                spec = {"seed": seed0 + m, "effect": name, "effect_snr": snrs[m % len(snrs)], **sensor(m)}
                if name == "torque_gain":  # a drive gain is a torque constant's error: it is in a recording of currents
                    spec["currents"] = True
                out.append(spec)
        return out
    raise ValueError(f"kind must be clean or effects, got {kind!r}")


# ---------------------------------------------------------------------- scoring


def read_csv(path: str | Path) -> dict[str, np.ndarray]:
    a = np.genfromtxt(path, delimiter=",", names=True)
    return {k: np.atleast_1d(a[k]) for k in a.dtype.names}


def recorded(csv: dict[str, np.ndarray], torque_constants: np.ndarray | None = None) -> np.ndarray:
    """(N, n) torque of a recording: tau columns, or currents times the torque constants."""
    if "tau1" in csv:
        n = sum(1 for k in csv if k.startswith("tau") and k[3:].isdigit())
        return np.column_stack([csv[f"tau{j + 1}"] for j in range(n)])
    n = sum(1 for k in csv if k.startswith("i") and k[1:].isdigit())
    if torque_constants is None:
        raise ValueError("a current recording needs the torque constants")
    return np.column_stack([csv[f"i{j + 1}"] for j in range(n)]) * torque_constants


def torque_constants(robot_yaml: str | Path) -> np.ndarray:
    doc = yaml.safe_load(Path(robot_yaml).read_text())
    return np.array([float(j.get("torque_constant", 1.0)) for j in doc["joints"]])


def relative_error(valid_csv: str | Path, predictions_csv: str | Path, robot_yaml: str | Path | None = None) -> tuple[float, float]:
    """Held-out ||tau - tau_hat|| / ||tau|| against the RAW recorded torque, and the stamps covered.

    Rows are matched on the time stamp to the microsecond (the generator's stamps are whole
    microseconds, so this is exact). Currents are scaled by the robot file's torque constants
    (``robot_yaml`` defaults to robot.yaml beside the validation file). Returns
    ``(relative_error over matched stamps, matched / validation stamps)``.
    """
    v = read_csv(valid_csv)
    kt = None if "tau1" in v else torque_constants(robot_yaml or Path(valid_csv).parent / "robot.yaml")
    tau = recorded(v, kt)
    p = read_csv(predictions_csv)
    n = tau.shape[1]
    hat = np.column_stack([p[f"tau_hat{j + 1}"] for j in range(n)])
    key_v = np.round(v["t"] * 1e6).astype(np.int64)
    key_p = np.round(p["t"] * 1e6).astype(np.int64)
    index = {k: r for r, k in enumerate(key_p)}
    rows = [(i, index[k]) for i, k in enumerate(key_v) if k in index]
    if not rows:
        return float("nan"), 0.0
    iv, ip = np.array(rows).T
    err = float(np.linalg.norm(tau[iv] - hat[ip]) / np.linalg.norm(tau[iv]))
    return err, len(rows) / len(key_v)


def noise_floor(noisy_csv: str | Path, clean_csv: str | Path, robot_yaml: str | Path | None = None) -> float:
    """||tau_noisy - tau_clean|| / ||tau_noisy|| of a recording and its clean twin."""
    v = read_csv(noisy_csv)
    kt = None if "tau1" in v else torque_constants(robot_yaml or Path(noisy_csv).parent / "robot.yaml")
    noisy = recorded(v, kt)
    clean = recorded(read_csv(clean_csv))
    return float(np.linalg.norm(noisy - clean) / np.linalg.norm(noisy))


def _trajectory(spec: dict[str, Any]):
    if "knots" in spec:
        return PointToPoint(np.array(spec["knots"]), np.array(spec["t_start"]), np.array(spec["t_move"]))
    return Fourier(spec["f0"], np.array(spec["a"]), np.array(spec["b"]), np.array(spec["q0"]))


def oracle_error(case: Case | str | Path, validate: str = "valid", max_samples: int = 4000) -> dict[str, float | None]:
    """What a perfect-kinematics least squares reaches on this case: an attainable reference.

    The true q, qd, qdd (analytic, at each file's stamps) go into Pinocchio's regressor plus the
    declared linear effects' columns; fitted to the recorded (noisy) identification torque,
    evaluated on the validation run and scored against its raw torque. ``before``: that model;
    ``after``: with the true undeclared effect added as one free column per affected joint (its
    exact shape, the size left to the fit: what the effect's own columns reach).
    ``case`` may be a folder ``make_case`` wrote.
    """
    if not isinstance(case, Case):
        case = load_case(case)
    truth = json.loads(case.truth_json.read_text())
    arm = Arm(truth["convention"], [Link(**ln) for ln in truth["links"]], truth["gravity"])
    n = len(arm.links)
    kt = np.array([ln.torque_constant for ln in arm.links])
    model = build_model(arm)
    data = model.createData()
    lowpass = truth["sensor"]["lowpass_hz"]

    def to_effect(d: dict[str, Any]) -> Effect:
        return Effect(d["name"], [j - 1 for j in d["joints"]], d["params"])

    extras = [to_effect(d) for d in truth.get("extra_effects", [])]
    main = to_effect(truth["effect"]) if truth["effect"] else None
    cols = {"coulomb_friction": lambda j, qd, qdd: np.sign(qd[:, j]), "viscous_friction": lambda j, qd, qdd: qd[:, j],
            "torque_offset": lambda j, qd, qdd: np.ones(len(qd)), "rotor_inertia": lambda j, qd, qdd: qdd[:, j]}

    def columns(name: str, path: Path, stride: int, with_effect: bool) -> tuple[np.ndarray, np.ndarray]:
        rec = read_csv(path)
        t = rec["t"]
        tau = recorded(rec, kt)
        traj = _trajectory(truth["excitation"][name])
        q, qd, qdd = traj(t)
        keep = np.arange(0, len(t), stride)
        blocks = [np.stack([pin.computeJointTorqueRegressor(model, data, q[k], qd[k], qdd[k]) for k in keep])]
        for dcl in truth["declared"]:
            if dcl.get("effect") in cols:
                for j in range(n) if dcl.get("joint") is None else [int(dcl["joint"]) - 1]:
                    c = np.zeros((len(keep), n, 1))
                    c[:, j, 0] = cols[dcl["effect"]](j, qd[keep], qdd[keep])
                    blocks.append(c)
        if with_effect and main is not None:
            shape = recorded_torque(arm, traj, t[keep], [main, *extras])[0] - recorded_torque(arm, traj, t[keep], extras)[0]
            for j in main.joints:
                c = np.zeros((len(keep), n, 1))
                c[:, j, 0] = shape[:, j]
                blocks.append(c)
        a = np.concatenate(blocks, axis=2)
        if lowpass:  # the recorded torque went through the amplifier's filter: so do the columns (linear)
            if stride != 1:
                raise ValueError("a low-passed case needs every sample (stride 1)")
            a = lowpass_first_order(t, a.reshape(len(t), -1), lowpass).reshape(a.shape)
        return a, tau[keep]

    out: dict[str, float | None] = {"before": None, "after": None}
    names = [p.stem for p in case.ident_csvs]
    total = sum(len(read_csv(p)["t"]) for p in case.ident_csvs)
    stride = 1 if lowpass else max(1, math.ceil(total / max_samples))
    vpath = case.valid_csv if validate == "valid" else case.ptp_csv
    for key, with_effect in (("before", False), ("after", True)):
        if with_effect and main is None:
            continue
        fit = [columns(nm, p, stride, with_effect) for nm, p in zip(names, case.ident_csvs)]
        a = np.concatenate([f[0] for f in fit]).reshape(-1, fit[0][0].shape[2])
        y = np.concatenate([f[1] for f in fit]).reshape(-1)
        x = np.linalg.lstsq(a, y, rcond=None)[0]
        av, tv = columns(validate, vpath, 1, with_effect)
        out[key] = float(np.linalg.norm(tv - av @ x) / np.linalg.norm(tv))
    return out

