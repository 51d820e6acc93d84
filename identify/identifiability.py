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

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.linalg import qr

from .errors import PoorExcitationWarning
from .spatial import Array

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
