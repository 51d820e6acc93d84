"""Which parameters the data can give: unique, in linear combinations, or not at all (5.4).

Khosla classifies the dynamics parameters from the kinematics alone. Numerically: stack the
regressor over many random configurations; a zero column is a parameter that never
affects the torques (unidentifiable); a column that depends linearly on earlier ones is
identifiable only regrouped into them. Taking columns in a fixed preference order, QR
gives the independent ("base") set ``b`` and the regrouping ``K`` with
``W_d = W_b K``, so that ``W phi = W_b beta`` with

.. math:: \\beta = \\phi_b + K \\phi_d

(Gautier 1990; Khosla's Table 2 entry ``m5 + m4`` is such a ``beta``). Links are taken from
base to tip, and within a link ``Ixx Ixy Ixz Iyz Izz msx msy`` before ``Iyy msz m`` (the
customary choice: ``Iyy, msz, m`` regroup into other parameters), so expressions read
``Izz1 + Iyy2 + 0.1865*m3``.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import qr

from .errors import PoorExcitationWarning
from .spatial import Array

if TYPE_CHECKING:
    from .robot import Robot

UNIQUE = "unique"
COMBINATION = "combination"
UNIDENTIFIABLE = "unidentifiable"

LINK_PREFERENCE = (4, 5, 6, 8, 9, 1, 2, 7, 3, 0)
"""Order in which the 10 parameters of a link are offered to the base set."""


@dataclass(frozen=True)
class BaseParameters:
    """The base parameters of a regressor with columns named ``names``.

    ``independent`` and ``dependent`` index the columns; ``regrouping`` is ``K``
    (len(independent), len(dependent)); ``zero`` lists the columns that are identically 0.
    """

    names: tuple[str, ...]
    independent: Array
    dependent: Array
    regrouping: Array
    zero: Array

    @property
    def n_base(self) -> int:
        return int(self.independent.size)

    def projection(self) -> Array:
        """``P`` (p, n_columns) with ``beta = P phi`` (``phi_b + K phi_d``, 5.4)."""
        p = np.zeros((self.n_base, len(self.names)))
        p[np.arange(self.n_base), self.independent] = 1.0
        if self.dependent.size:
            p[:, self.dependent] += self.regrouping
        return p

    def base_values(self, phi: Array) -> Array:
        """``beta = phi_b + K phi_d`` for standard parameters ``phi``."""
        phi = np.asarray(phi, dtype=float)
        return phi[self.independent] + self.regrouping @ phi[self.dependent]

    def base_matrix(self, w: Array) -> Array:
        """The columns of ``w`` (..., n_params) that carry the base parameters."""
        return w[..., self.independent]

    def expressions(self, precision: int = 4) -> list[str]:
        """Readable expressions, one per base parameter: ``"m4 + m5"``."""
        out = []
        for k, col in enumerate(self.independent):
            terms = [self.names[col]]
            for d, dcol in enumerate(self.dependent):
                c = self.regrouping[k, d]
                if abs(c) < 1e-9:
                    continue
                if abs(c - 1.0) < 1e-9:
                    terms.append(f"+ {self.names[dcol]}")
                elif abs(c + 1.0) < 1e-9:
                    terms.append(f"- {self.names[dcol]}")
                else:
                    sign = "-" if c < 0 else "+"
                    terms.append(f"{sign} {abs(c):.{precision}g}*{self.names[dcol]}")
            out.append(" ".join(terms))
        return out

    def classes(self) -> list[str]:
        """Per standard parameter: unique, combination or unidentifiable (Khosla 5.4)."""
        out = [UNIDENTIFIABLE] * len(self.names)
        involved = np.abs(self.regrouping) > 1e-9
        for k, col in enumerate(self.independent):
            out[col] = COMBINATION if involved[k].any() else UNIQUE
        for d, col in enumerate(self.dependent):
            out[col] = COMBINATION if involved[:, d].any() else UNIDENTIFIABLE
        return out


def base_parameters(w: Array, names: list[str] | tuple[str, ...], order: list[int] | None = None, rtol: float = 1e-8,
                    zero_rtol: float = 1e-10) -> BaseParameters:
    """Base parameters of the stacked regressor ``w`` (rows, n_params).

    ``order`` is the preference in which columns are offered to the base set (default:
    as given). Columns are scaled to unit norm first so that units do not decide; a column
    under ``zero_rtol`` of the largest is zero (scaled, its rounding would look independent).
    """
    w = np.asarray(w, dtype=float)
    p = w.shape[1]
    order = list(range(p)) if order is None else list(order)
    norms = np.linalg.norm(w, axis=0)
    scale = norms.max() if norms.size and norms.max() > 0 else 1.0
    zero = np.flatnonzero(norms <= zero_rtol * scale)
    live = [c for c in order if c not in set(zero.tolist())]
    if not live:
        return BaseParameters(tuple(names), np.array([], int), np.array([], int), np.zeros((0, 0)), zero)
    ws = w[:, live] / norms[live]
    r = qr(ws, mode="r", pivoting=False)[0]
    diag = np.abs(np.diag(r))
    keep = diag > rtol * diag.max()
    independent = np.array([live[k] for k in range(len(live)) if keep[k]], dtype=int)
    dependent = np.array([live[k] for k in range(len(live)) if not keep[k]], dtype=int)
    if dependent.size:
        kmat, *_ = np.linalg.lstsq(w[:, independent], w[:, dependent], rcond=None)
        kmat[np.abs(kmat) < 1e-10 * max(1.0, np.abs(kmat).max())] = 0.0
    else:
        kmat = np.zeros((independent.size, 0))
    return BaseParameters(tuple(names), independent, dependent, kmat, zero)


def preferred_order(n_links: int, n_extra: int = 0) -> list[int]:
    """Column preference: links base to tip, :data:`LINK_PREFERENCE` within, extras last."""
    return [10 * i + k for i in range(n_links) for k in LINK_PREFERENCE] + list(range(10 * n_links, 10 * n_links + n_extra))


@dataclass(frozen=True)
class Excitation:
    """How well a recording's base regressor is conditioned (Khosla 5.2)."""

    rank: int
    n_base: int
    condition_number: float
    weak: list[str]


def excitation(w_base: Array, base_names: list[str], max_condition: float = 1e3, rtol: float = 1e-7) -> Excitation:
    """Rank and condition number of the column-scaled base regressor ``w_base``.

    Warns with :class:`PoorExcitationWarning` when the data leaves a base parameter
    unexcited (rank deficient) or the condition number exceeds ``max_condition``;
    ``weak`` names the base parameters that dominate the weakest direction.
    """
    norms = np.linalg.norm(w_base, axis=0)
    if w_base.shape[1] == 0:
        return Excitation(0, 0, 1.0, [])
    # the singular values of the column-scaled matrix are those of its (small) R factor
    r = qr(w_base, mode="r", check_finite=False)[0][: w_base.shape[1]]
    sv, vt = np.linalg.svd(r / np.where(norms > 0, norms, 1.0))[1:]
    rank = int(np.sum(sv > rtol * sv[0])) if sv[0] > 0 else 0
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    weak_dirs = vt[rank:] if rank < len(sv) else vt[-1:]
    weight = np.max(np.abs(weak_dirs), axis=0)
    weak = [base_names[k] for k in np.argsort(-weight)[:3] if weight[k] > 0.3]
    if rank < w_base.shape[1]:
        warnings.warn(
            f"the data excites {rank} of {w_base.shape[1]} base parameters; not excited: {', '.join(weak)}",
            PoorExcitationWarning,
            stacklevel=2,
        )
    elif cond > max_condition:
        warnings.warn(
            f"poorly exciting data: condition number {cond:.3g} > {max_condition:g}; weakest: {', '.join(weak)}",
            PoorExcitationWarning,
            stacklevel=2,
        )
    return Excitation(rank, w_base.shape[1], cond, weak)


IDENTIFIED_SIGMAS = 3.0
"""A parameter (or combination) is identified by the data when this many of its standard
deviations stay within its physical range (:func:`physical_ranges`)."""

STEEL_KG_PER_M3 = 7850.0
"""The density of the solid rod that bounds an arm's mass when its robot file models no mass."""

_TORQUE_LIKE = ("fc", "fs", "offset", "cog_a", "cog_b")
_INERTIAS = ("Ixx", "Ixy", "Ixz", "Iyy", "Iyz", "Izz")
_LABEL = re.compile(r"(.*?)(\d+)")


@dataclass(frozen=True)
class ArmSize:
    """The sizes a physical range is made of: mass (kg), reach (m) and, per joint, the torque
    (N*m or N) and speed (rad/s or m/s) that bound its effects."""

    mass_kg: float
    reach_m: float
    torque: Array
    speed: Array
    acceleration: Array  # NaN where the robot file gives no limit

    @classmethod
    def of(cls, robot: Robot) -> ArmSize:
        """The arm's size from its robot file.

        ``reach_m``: the sum of the joints' fixed translations (the DH ``a`` and ``d``, a URDF
        joint's origin; the first joint's placement in the base frame left out), a prismatic
        joint's travel and the largest modeled centre of mass: no point of a link lies farther
        from the first joint, nor from its own frame. ``mass_kg``: the modeled
        links' total mass; where a link has no inertial, at least a solid steel rod of the
        reach in length and a quarter of it across. ``torque``: each joint's torque limit,
        else the torque the whole mass makes at the reach under gravity; ``speed``: each
        joint's velocity limit, else 1 rad/s (or m/s)."""
        reach = 0.0
        com = 0.0
        for i, j in enumerate(robot.joints):
            # the first joint's own placement (a URDF's mount on its table) moves no link in its frame
            reach += float((np.linalg.norm(np.asarray(j.pre, float)[:3, 3]) if i else 0.0) + np.linalg.norm(np.asarray(j.post, float)[:3, 3]))
            if not j.revolute and j.limits.position is not None:
                reach += max((abs(float(x)) for x in j.limits.position if np.isfinite(x)), default=0.0)
            if j.inertial is not None:
                com = max(com, float(np.linalg.norm(j.inertial.com_m)))
        reach = reach + com if reach + com > 0 else 1.0
        masses = [j.inertial.mass_kg for j in robot.joints if j.inertial is not None]
        mass = float(sum(masses))
        if len(masses) < robot.n_joints:
            mass = max(mass, STEEL_KG_PER_M3 * np.pi * (reach / 8.0) ** 2 * reach)
        g = float(np.linalg.norm(robot.gravity)) or 9.81
        torque = np.array([j.limits.torque if j.limits.torque else mass * g * reach for j in robot.joints], float)
        speed = np.array([j.limits.velocity if j.limits.velocity else 1.0 for j in robot.joints], float)
        accel = np.array([j.limits.acceleration if j.limits.acceleration else np.nan for j in robot.joints], float)
        return cls(mass, reach, torque, speed, accel)


def physical_ranges(robot: Robot, names: list[str] | tuple[str, ...], modeled: Array | None = None) -> Array:
    """The physical range of each column ``names`` names (``m3``, ``msx3``, ``Izz3``, an
    effect's ``fv3``...): the largest magnitude the parameter can have on this arm
    (:class:`ArmSize`), or its modeled magnitude where that is larger.

    A mass: the arm's mass ``M``; a first moment: ``M`` times the reach ``L``; an inertia
    (and a rotor inertia): ``M L^2``; a torque (Coulomb, Stribeck, offset, cogging): the
    joint's torque ``T``; viscous friction: ``T`` over the joint's speed; a spring: ``T`` per
    radian; a load-dependent friction: 1 (the whole transmitted torque). A column of no known
    kind: infinite (never judged)."""
    size = ArmSize.of(robot)
    m, reach = size.mass_kg, size.reach_m
    out = np.full(len(names), np.inf)
    for k, name in enumerate(names):
        hit = _LABEL.fullmatch(name)
        if hit is None:
            continue
        kind, j = hit.group(1), int(hit.group(2)) - 1
        if not 0 <= j < robot.n_joints:
            continue
        torque = size.torque[j]
        if kind == "m":
            out[k] = m
        elif kind in ("msx", "msy", "msz"):
            out[k] = m * reach
        elif kind in _INERTIAS:
            out[k] = m * reach**2
        elif kind == "ia":
            a = size.acceleration[j]
            out[k] = max(m * reach**2, torque / a if np.isfinite(a) and a > 0 else 0.0)
        elif kind in _TORQUE_LIKE:
            out[k] = torque
        elif kind == "fv":
            out[k] = torque / size.speed[j]
        elif kind == "ks":
            out[k] = torque
        elif kind == "fl":
            out[k] = 1.0
    if modeled is not None:
        mod = np.abs(np.asarray(modeled, float)[: len(names)])
        out[: mod.size] = np.where(np.isfinite(mod), np.maximum(out[: mod.size], mod), out[: mod.size])
    return out


def combination_ranges(rows: Array, column_ranges: Array, modeled: Array | None = None) -> Array:
    """The physical range of each combination ``rows @ phi`` (rows, columns): the sum of its
    columns' ranges weighted by their coefficients' magnitudes (the largest the combination
    can be), or its modeled magnitude where that is larger."""
    rows = np.atleast_2d(np.asarray(rows, float))
    used = np.abs(rows) > 0
    with np.errstate(invalid="ignore"):
        out = np.where(used, np.abs(rows) * column_ranges, 0.0).sum(axis=1)
    if modeled is not None:
        mod = np.abs(np.asarray(modeled, float))
        out = np.where(np.isfinite(mod), np.maximum(out, mod), out)
    return np.asarray(out)


def identified_by_data(std: Array, ranges: Array) -> Array:
    """True where :data:`IDENTIFIED_SIGMAS` standard deviations lie within the physical
    range; False where they exceed it (the data leave the value anywhere in its range and
    beyond) or the std is not finite."""
    std = np.asarray(std, float)
    with np.errstate(invalid="ignore"):
        return np.asarray(np.isfinite(std) & (IDENTIFIED_SIGMAS * std <= np.asarray(ranges, float)))


def parameter_ranges(robot: Robot, names: list[str], base: BaseParameters) -> tuple[Array, Array]:
    """The physical range of every column (:func:`physical_ranges`) and of every base parameter
    (its regrouping's coefficients applied to its columns' ranges, :func:`combination_ranges`)."""
    modeled = robot.modeled_parameters()
    full = np.concatenate([modeled, np.full(len(names) - len(modeled), np.nan)])
    columns = physical_ranges(robot, names, full)
    modeled_base = base.base_values(np.concatenate([modeled, np.zeros(len(names) - len(modeled))]))
    return columns, combination_ranges(base.projection(), columns, modeled_base)


def identified_ranges(robot: Robot, names: list[str], base: BaseParameters, std: Array, base_std: Array) -> tuple[Array, Array, Array, Array]:
    """Each column's and each base parameter's physical range (:func:`parameter_ranges`) and
    whether these data identify it (:func:`identified_by_data`, from its std)."""
    columns, combos = parameter_ranges(robot, names, base)
    return columns, identified_by_data(std, columns), combos, identified_by_data(base_std, combos)
