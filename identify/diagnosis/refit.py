"""The declared model with the diagnosis's findings added, as ``identify`` fits it.

:func:`findings_model` turns findings into what ``identify`` takes (declared effects, a
tilted gravity, a torque scale, delays): declaring the same in the robot file gives the same
fit. Around it: the exact fits the search's gates (d) and (f) read (:func:`trial_fit`), the
declared settings fixed at what the data chose (:func:`settled_robot`), each found delay refined
on the exact model (:func:`refine_delays`), the findings' parameters as the final fit gives
them (:func:`update_parameters`), the findings whose sign that fit turns
(:func:`sign_reversed`) and what is left of one (:func:`coulomb_level`: a Stribeck or
load term held at 0 leaves its Coulomb level; :func:`merge_offset_into_spring`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..identification import IdentificationResult, IdentifyOptions, identify
from ..preprocess import Prepared
from ..robot import DeclaredEffect, Robot
from ..spatial import Array
from .candidates import DISSIPATIVE, DISSIPATIVE_PARAMETER, Candidate
from .report import Finding

FIXED_OPTIONS = ("velocity", "period_rad")

STRIBECK_LEVEL = {"velocity": 0.0}
"""The Coulomb level a Stribeck finding brings, as declared: a sharp ``sign(qd)``, as the search
scored it (diagnosis_candidates._stribeck_columns), not a smoothing searched on the data. The
smoothing of the sign and the Stribeck velocity both shape the friction below a few times
``v_s`` alone: on one trajectory the two trade against each other, and the settings' search,
free to move the smoothing beside a peak held at its velocity, lands where they cancel (blind
Stribeck seed 6206: smoothing 0.086 rad/s beside ``v_s`` 0.075, the peak fitted 1.41 for the
true 0.39, the fit's own error above the sharp level's, 0.43 % for 0.37 %, and the validation's
0.61 % for 0.49 %: the peak was judged negligible and named Coulomb friction)."""


def findings_model(robot: Robot, found: list[Finding]) -> tuple[Robot, IdentifyOptions]:
    """The declared model with every finding added, as `identify` takes it: a joint's
    friction, offset, rotor inertia, spring or cogging as a declared effect (its searched
    setting kept), friction on every joint as three declared effects per joint, a tilt of
    gravity as the tilted gravity vector, a drive gain as the torque's scale, a delay of the
    torque channel as its lag, a joint's late position as its motion's lag (IdentifyOptions).
    A found Coulomb level on a joint with a Stribeck finding is a sharp ``sign(qd)``
    (:data:`STRIBECK_LEVEL`). Declaring the same in the robot file gives the same fit."""
    nj = robot.n_joints
    declared: list[DeclaredEffect] = []
    gravity = np.asarray(robot.gravity, float)
    scale = np.ones(nj)
    delay = np.zeros(nj)
    motion_delay = np.zeros(nj)
    have = {(e.effect, j) for e in robot.effects for j in (range(1, nj + 1) if e.joint is None else [e.joint])}
    nonnegative: list[str] = []
    stribeck = {f.joint for f in found if f.effect == "stribeck_friction"}
    for f in found:
        nonnegative += _bounded_columns(f, have)
        if f.effect == "coulomb_friction" and f.joint is None:  # friction on every joint it covers
            joints = sorted({int(k[2:]) for k in f.parameters if k.startswith("fc")})
            declared += [DeclaredEffect(e, j) for j in joints for e in ("coulomb_friction", "viscous_friction", "torque_offset")]
        elif f.effect == "gravity_tilt":
            axis = np.array([f.parameters["tilt_x_rad"], f.parameters["tilt_y_rad"], 0.0])
            gravity = rotation_matrix(axis) @ gravity
        elif f.effect == "torque_gain" and f.joint is not None:
            scale[f.joint] /= f.parameters["gain"]
        elif f.effect == "time_delay" and f.joint is None:
            delay += f.parameters["delay_s"]
        elif f.effect == "time_delay" and f.joint is not None:
            motion_delay[f.joint] += f.parameters["delay_s"]
        elif f.joint is not None:
            # a found Coulomb's smoothing is chosen on the data, as for a declared one, unless a
            # Stribeck peak on its joint shapes its low speeds (:data:`STRIBECK_LEVEL`)
            fixed = {k: v for k, v in f.parameters.items() if k in FIXED_OPTIONS and f.effect != "coulomb_friction"}
            if f.effect == "coulomb_friction" and f.joint in stribeck:
                fixed = dict(STRIBECK_LEVEL)
            declared.append(DeclaredEffect(f.effect, f.joint + 1, fixed))
            if f.effect == "spring" and "rest_position" in f.parameters and ("torque_offset", f.joint + 1) not in have:
                declared.append(DeclaredEffect("torque_offset", f.joint + 1))
            if f.effect in ("stribeck_friction", "load_dependent_coulomb") and "fc" in f.parameters and ("coulomb_friction", f.joint + 1) not in have:
                # found with its Coulomb level; a Stribeck peak's level is the sharp sign(qd) it
                # was scored with (:data:`STRIBECK_LEVEL`)
                declared.append(DeclaredEffect("coulomb_friction", f.joint + 1, dict(STRIBECK_LEVEL) if f.effect == "stribeck_friction" else {}))
    model = replace(robot, gravity=gravity, effects=tuple(robot.effects) + tuple(declared))
    return model, IdentifyOptions(torque_scale=tuple(scale) if np.any(scale != 1.0) else None,
                                  delay_s=tuple(delay) if np.any(delay != 0.0) else None,
                                  motion_delay_s=tuple(motion_delay) if np.any(motion_delay != 0.0) else None,
                                  nonnegative=tuple(nonnegative))


def _bounded_columns(f: Finding, have: set[tuple[str, int]]) -> list[str]:
    """The identify columns of finding ``f`` physics bounds at 0 (diagnosis_candidates.NONNEGATIVE):
    its friction, rotor inertia or spring stiffness, and the Coulomb level it brings with it;
    not a column the robot file declares (that one is fitted as declared)."""
    if f.joint is None:
        if f.effect != "coulomb_friction":
            return []
        joints = sorted({int(k[2:]) for k in f.parameters if k.startswith("fc")})
        return [f"{p}{j}" for j in joints for p, e in (("fc", "coulomb_friction"), ("fv", "viscous_friction")) if (e, j) not in have]
    j = f.joint + 1
    column = {"spring": "ks"}.get(f.effect, DISSIPATIVE_PARAMETER.get(f.effect))
    out = [f"{column}{j}"] if column is not None and (f.effect, j) not in have else []
    if f.effect in ("stribeck_friction", "load_dependent_coulomb") and "fc" in f.parameters and ("coulomb_friction", j) not in have:
        out.append(f"fc{j}")
    return out


def sign_reversed(found: list[Finding]) -> list[Finding]:
    """The one-joint friction or inertia findings whose fitted parameter is not positive."""
    return [f for f in found if f.joint is not None and f.effect in DISSIPATIVE
            and f.parameters.get(DISSIPATIVE_PARAMETER[f.effect], 1.0) <= 0.0]


def trial_fit(robot: Robot, experiments: list[Prepared], found: list[Finding], load: Array) -> IdentificationResult:
    """The model with ``found`` added, fitted as `identify` fits it.
    Gate (d) reads how far its prior on the modeled values (identify.prior) had to widen to
    agree with least squares (``inf``: beyond any width; None: the robot file models no
    inertial values): a finding that lets least squares wander from the modeled values along
    what the data barely excite (a tilt trading against the first moments) widens it, and the
    data alone cannot tell that finding from a worse model. Gate (f) reads its residual at the
    validation stamps."""
    model, options = findings_model(robot, found)
    return identify(model, experiments, None, replace(options, covariance="white", load_parameters=tuple(load), stamp_errors=False))


def prior_widening(result: IdentificationResult) -> float | None:
    """The factor ``result``'s prior was widened by (``inf``: dropped; None: no prior)."""
    if result.prior is None:
        return None
    w = result.prior.get("widened_by")
    return float("inf") if w is None else float(w)


def settled_robot(robot: Robot, result: IdentificationResult) -> Robot:
    """``robot`` with its declared effects' settings (a Coulomb model's smoothing) fixed at
    what ``result`` chose on the data, one declared effect per joint: refitting it with a
    finding added then costs a solve, not the settings' grid search again."""
    chosen = {(e.effect, e.joint): dict(e.setting) for e in result.effects}
    out = []
    for e in robot.effects:
        for one in e.per_joint(robot.n_joints):
            assert one.joint is not None
            out.append(replace(one, options={**one.options, **chosen.get((one.effect, one.joint - 1), {})}))
    return replace(robot, effects=tuple(out))


def refine_delays(robot: Robot, found: list[Finding], experiments: list[Prepared], load: Array) -> None:
    """Each found delay, refined on the identification data with the exact model (the motion
    or the torque shifted in time) as `identify` fits it: the fit's error on a grid of
    0.6-1.6 times the search's estimate (not unimodal: a shift by about a period of the
    excitation's harmonics fits again), then Brent's method between the best point's neighbours."""
    from scipy.optimize import minimize_scalar

    for f in found:
        if f.effect != "time_delay":
            continue
        d0 = f.parameters["delay_s"]

        def error(d: float, f: Finding = f) -> float:
            f.parameters["delay_s"] = float(d)
            model, options = findings_model(robot, found)
            return float(identify(model, experiments, None, replace(options, load_parameters=tuple(load))).fit["relative_error"])

        grid = d0 * np.array([0.6, 0.8, 1.0, 1.25, 1.6])
        errors = [error(d) for d in grid]
        k = int(np.argmin(errors))
        lo, hi = sorted((grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]))
        best = minimize_scalar(error, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3 * abs(d0), "maxiter": 6})
        f.parameters["delay_s"] = float(best.x) if best.fun <= errors[k] else float(grid[k])


def rotation_matrix(rotation_vector: Array) -> Array:
    """Rodrigues: the rotation by ``|v|`` about ``v``."""
    angle = float(np.linalg.norm(rotation_vector))
    if angle == 0.0:
        return np.eye(3)
    k = rotation_vector / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def update_parameters(found: list[Finding], result: IdentificationResult) -> None:
    """A declared finding's parameters as the final fit (all the identification data) gives them."""
    value, _ = result.parameter_values()
    by_name = dict(zip(result.names, value))
    for f in found:
        if f.joint is None or f.effect in ("torque_gain", "time_delay", "gravity_tilt"):
            continue
        j = f.joint + 1
        if f.effect == "cogging":
            a, b = by_name.get(f"cog_a{j}", np.nan), by_name.get(f"cog_b{j}", np.nan)
            if np.isfinite(a) and np.isfinite(b):
                f.parameters.update(amplitude=float(np.hypot(a, b)), phase_rad=float(np.arctan2(b, a)))
            continue
        if f.effect == "spring":
            k, off = by_name.get(f"ks{j}", np.nan), by_name.get(f"offset{j}", np.nan)
            if np.isfinite(k):
                f.parameters["stiffness"] = float(k)
                if "rest_position" in f.parameters and np.isfinite(off) and k != 0:
                    f.parameters["rest_position"] = float(-off / k)
            continue
        for label in list(f.parameters):
            v = by_name.get(f"{label}{j}", np.nan)
            if np.isfinite(v):
                f.parameters[label] = float(v)
        for e in result.effects:  # the Coulomb smoothing chosen on the data
            if e.effect == f.effect and e.joint == f.joint and e.setting and f.effect == "coulomb_friction":
                f.parameters.update({k: float(v) for k, v in e.setting})


def coulomb_level(f: Finding) -> Finding | None:
    """A Stribeck or load-dependent friction finding whose peak or load term the final fit holds
    at 0, as the Coulomb friction it brings (its ``fc``); None for any other (or no Coulomb level)."""
    if f.effect not in ("stribeck_friction", "load_dependent_coulomb") or f.parameters.get("fc", 0.0) <= 0.0:
        return None
    return Finding("coulomb_friction", f.joint, {"fc": f.parameters["fc"]}, f.explained, f.error_before, f.error_after)


def merge_offset_into_spring(found: list[Finding], chosen: list[Candidate]) -> tuple[list[Finding], list[Candidate]]:
    """An offset found first and a spring on the same joint later are one spring off zero."""
    drop = set()
    for k, f in enumerate(found):
        if f.effect != "spring":
            continue
        for m, g in enumerate(found[:k]):
            if g.effect == "torque_offset" and g.joint == f.joint:
                f.error_before, f.explained = g.error_before, 1.0 - (1.0 - g.explained) * (1.0 - f.explained)
                drop.add(m)
    keep = [k for k in range(len(found)) if k not in drop]
    # the offset's columns stay in the model (the spring's parameters include them)
    return [found[k] for k in keep], chosen
