"""What one identification says that can be compared from run to run (issue 37's fleet).

A fleet tracks each arm's quantities over its recordings and tests them for changes
(:mod:`identify.changes`). Only what every run identifies on its own can be compared: raw
link parameters cannot (most are not identifiable, and their least-squares values are
arbitrary along the unexcited directions), so the tracked quantities are

- the **base parameters** (Khosla 5.4), by the expression ``armid identify --json`` gives
  them (``msx4 + 0.2683*m4``): structural, so the same expression in every run of one robot
  file; the link of its first term is its joint;
- the **declared effects' coefficients** (``coulomb_friction.fc`` of joint 3, ...);
- the **declared drive gains** (``torque_gain``), which the identification profiles without
  a standard deviation; :func:`gain_std` gives them one.

Each comes with its value, its standard deviation and its unit.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from .effects import PROFILED
from .identification import IdentificationResult, declared_gains
from .spatial import Array

LINK_UNITS = {"m": "kg", "ms": "kg m", "I": "kg m^2"}
"""Units of Khosla's link parameters by the start of their name (``m``, ``msx``, ``Ixx``)."""

EFFECT_UNITS: dict[str, tuple[str, str]] = {
    "fc": ("N m", "N"), "fs": ("N m", "N"), "offset": ("N m", "N"), "cog_a": ("N m", "N"), "cog_b": ("N m", "N"),
    "fv": ("N m s/rad", "N s/m"), "ia": ("kg m^2", "kg"), "ks": ("N m/rad", "N/m"), "fl": ("1", "1"),
}
"""Units of the effects' coefficients on a revolute and on a prismatic joint."""

_TERM = re.compile(r"^\s*(m|ms[xyz]|I[xyz]{2})(\d+)")


@dataclass(frozen=True)
class Tracked:
    """One quantity of one identification. ``kind``: ``base``, ``effect`` or ``gain``;
    ``parameter``: the base parameter's expression, ``effect.coefficient`` or ``torque_gain``;
    ``joint``: 1-based (None for a base parameter whose first term names no link)."""

    kind: str
    parameter: str
    joint: int | None
    value: float
    std: float
    unit: str


def leading_link(expression: str) -> int | None:
    """The link (1-based) of a base parameter's first term: ``Ixx2 - Izz2 + ...`` is link 2."""
    match = _TERM.match(expression)
    return int(match.group(2)) if match else None


def expression_unit(expression: str) -> str:
    """A base parameter's unit, its first term's (the others carry theirs in their coefficients)."""
    match = _TERM.match(expression)
    if not match:
        return ""
    name = match.group(1)
    return LINK_UNITS["m" if name == "m" else "ms" if name.startswith("ms") else "I"]


def gain_std(result: IdentificationResult) -> Array:
    """Standard deviation (N,) of each declared drive gain (NaN for the other joints).

    The gain ``g_j`` is fitted by profiling least squares over it (identify.identification);
    its variance here is Gauss-Newton's at that optimum, from the per-joint R factors alone:
    the measured torque divided by the gain is ``y_j = W_j beta + e``, so ``d y_j / d log g_j
    = -y_j`` joins ``W_j`` as one more column and the information matrix of
    ``(beta, log g)`` is that of the augmented columns. Scaled by the residual's correlation
    length (the data weigh as ``n / L`` independent equations, as the prior weighs them),
    and without the prior's information on ``beta`` (which would narrow it): on the
    conservative side.

    .. math:: \\operatorname{cov}(\\beta, \\log g) = s^2 L \\, (J^T J)^{-1}, \\quad
              \\sigma_g = g \\, \\sigma_{\\log g}
    """
    nj = result.robot.n_joints
    out = np.full(nj, np.nan)
    gains = declared_gains(result.robot)
    if not gains or result.factors is None or result.torque_scale is None:
        return out
    factors, est = result.factors, result.estimate
    p = factors.n_parameters
    weights = 1.0 / np.maximum(est.joint_sigma, 1e-300) if est.weighting == "wls" else np.ones(nj)
    blocks = []
    for k, r in enumerate(factors.r):
        u = np.zeros((r.shape[0], len(gains)))
        if k in gains:
            u[:, gains.index(k)] = r[:, p]
        blocks.append(weights[k] * np.hstack([r[:, :p], u]))
    jac = np.vstack(blocks)
    rows = float(factors.counts.sum())
    rss = float(np.sum(factors.residual_squares(est.beta) * weights**2))
    s2 = rss / max(rows - p - len(gains), 1.0)
    length = float((result.prior or {}).get("correlation_length_equations") or 1)
    cov = s2 * length * np.linalg.pinv(jac.T @ jac)
    for i, j in enumerate(gains):
        out[j] = float(result.torque_scale[j]) * float(np.sqrt(max(cov[p + i, p + i], 0.0)))
    return out


def tracked_quantities(result: IdentificationResult) -> list[Tracked]:
    """The base parameters (those led by a link parameter), the declared effects'
    identifiable coefficients and the declared drive gains of one identification, in that order."""
    doc = result.to_json()
    revolute = [j.revolute for j in result.robot.joints]
    # a base parameter that is an effect's column alone (``fc3``) is tracked as that effect
    out = [Tracked("base", b["expression"], leading_link(b["expression"]), float(b["value"]), float(b["std"]),
                   expression_unit(b["expression"])) for b in doc["base_parameters"] if leading_link(b["expression"]) is not None]
    for e in doc["effects"]:
        joint = int(e["joint"])
        for name, value in e["parameters"].items():
            if value is None:
                continue  # not identifiable in this run: nothing to compare
            std = e["std"][name]
            unit = EFFECT_UNITS.get(name, ("", ""))[0 if revolute[joint - 1] else 1]
            out.append(Tracked("effect", f"{e['effect']}.{name}", joint, float(value), np.nan if std is None else float(std), unit))
    stds = gain_std(result)
    scale = result.torque_scale
    for j in declared_gains(result.robot):
        if scale is not None:
            out.append(Tracked("gain", PROFILED[0], j + 1, float(scale[j]), float(stds[j]), "1"))
    return out
