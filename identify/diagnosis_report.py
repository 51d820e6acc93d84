"""What the diagnosis reports: each :class:`Finding` and the whole :class:`Diagnosis` (the
``armid diagnose --json`` document), and the sentences the text output and the report say
of a finding, of a candidate set aside, and of a finding the validation extrapolates.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .diagnosis_candidates import DISSIPATIVE_PARAMETER
from .spatial import Array


@dataclass
class Finding:
    effect: str
    joint: int | None
    parameters: dict[str, float]
    explained: float  # fraction of the held-out residual power this finding removed
    error_before: float
    error_after: float
    lookalike: str | None = None
    separate_by: str | None = None

    def sentence(self) -> str:
        where = f"joint {self.joint + 1}" if self.joint is not None else "arm"
        signature = {
            "coulomb_friction": "residual follows sign(qd)", "viscous_friction": "residual follows qd",
            "stribeck_friction": "residual peaks at low speed with sign(qd)", "torque_offset": "residual has a constant offset",
            "rotor_inertia": "residual follows qdd", "torque_gain": "residual is proportional to the torque",
            "time_delay": "residual follows the rate of change of the torque", "cogging": "residual is periodic in position",
            "spring": "residual grows linearly with position", "gravity_tilt": "residual follows a gravity load about a tilted axis",
            "load_dependent_coulomb": "residual follows sign(qd), growing with the joint's load torque",
        }[self.effect]
        name = self.effect.replace("_", " ")
        # a parameter named as the effect's last word is the effect's value: "torque gain 1.143"
        params = ", ".join(f"{v:.4g}" if name.endswith(f" {k}") else f"{k} {v:.4g}" for k, v in self.parameters.items())
        text = f"{where}: {signature}: {name} {params}; held-out error (identification data) {100 * self.error_before:.2f} % -> {100 * self.error_after:.2f} %"
        if self.lookalike:
            text += f" (cannot be told apart from {self.lookalike.replace('_', ' ')} on this data; to separate them: {self.separate_by})"
        return text

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"effect": self.effect, "joint": None if self.joint is None else self.joint + 1,
                               "parameters": self.parameters, "explained": self.explained}
        if self.lookalike:
            out["lookalike"] = {"effect": self.lookalike, "separate_by": self.separate_by}
        return out


@dataclass
class Diagnosis:
    found: list[Finding]
    absorbed: list[dict[str, Any]]
    before: dict[str, Any]
    after: dict[str, Any]
    base_effects: list[str]
    rounds: list[list[tuple[str, float]]] = field(default_factory=list)
    residual_before: tuple[Array, Array] | None = None  # validation (tau, tau_hat) before
    residual_after: tuple[Array, Array] | None = None
    validation_motion: tuple[Array, Array, Array, Array] | None = None  # t, q, qd, qdd
    used: Array | None = None  # (n, N) validation equations the scores used
    predictions: tuple[Array, Array, Array] | None = None  # t, raw tau, final model's tau_hat at the validation stamps
    noise_floor: dict[str, Any] | None = None
    # candidates that cleared every other gate but pulled the estimate away from the modeled
    # values (DiagnoseOptions.max_prior_widening): set aside, not findings
    conflicting: list[dict[str, Any]] = field(default_factory=list)
    # position-dependent findings the validation uses beyond the positions they were found on
    extrapolated: list[dict[str, Any]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"found": [f.to_json() for f in self.found], "absorbed": self.absorbed, "declared": self.base_effects,
                "set_aside": self.conflicting, "extrapolated": self.extrapolated,
                "before": self.before, "after": self.after, "noise_floor": self.noise_floor,
                "chosen_on": "the identification data: fitted on its even tenths, scored on its odd tenths; a finding that "
                             "raises its joint's error on the validation data consistently (over its tenths) is set aside (a veto, never a ranking)",
                "measured_on": "the validation data (before and after), at every sample's own stamp against the raw torque"}


POSITION_DEPENDENT = ("spring", "cogging")
"""Effects that are functions of one joint's position: beyond the positions a finding was
fitted on, it is an extrapolation (a spring may be the local slope of a ripple longer than
the motion; held-out tenths of the same motion cannot tell)."""


def _extrapolated(found: list[Finding], q_ident: Array, q_valid: Array, tolerance: float = 0.05) -> list[dict[str, Any]]:
    """The position-dependent findings whose joint the validation takes more than
    ``tolerance`` of the identified range beyond it, with both ranges."""
    out = []
    for f in found:
        if f.effect not in POSITION_DEPENDENT or f.joint is None:
            continue
        lo, hi = float(q_ident[:, f.joint].min()), float(q_ident[:, f.joint].max())
        vlo, vhi = float(q_valid[:, f.joint].min()), float(q_valid[:, f.joint].max())
        beyond = (max(lo - vlo, 0.0) + max(vhi - hi, 0.0)) / max(hi - lo, 1e-12)
        if beyond > tolerance:
            out.append({"effect": f.effect, "joint": f.joint + 1, "identified_range": [lo, hi], "validation_range": [vlo, vhi],
                        "beyond_fraction": beyond})
    return out


def extrapolation_sentence(x: dict[str, Any]) -> str:
    """One line for a finding the validation extrapolates (the text output and the report)."""
    lo, hi = x["identified_range"]
    vlo, vhi = x["validation_range"]
    return (f"{x['effect'].replace('_', ' ')} on joint {x['joint']} was found on positions {lo:.4g}..{hi:.4g}; the validation "
            f"goes to {vlo:.4g}..{vhi:.4g}, {100 * x['beyond_fraction']:.0f} % of that range beyond it: there the finding is "
            "an extrapolation, and a local fit of something else (a ripple longer than the motion) extrapolates badly. "
            "Identify on a motion that covers the validation's positions to tell")


def set_aside_sentence(c: dict[str, Any]) -> str:
    """What the text and the report say of a candidate set aside: by gate (d) or (f), or because
    the final fit turned the sign of its friction or inertia."""
    where = "the arm" if c["joint"] is None else f"joint {c['joint']}"
    if c.get("reason") == "validation":
        return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests on the identification data, but on the "
                f"validation data it takes {where}'s error from {100 * c['validation_error_before']:.3g} % to "
                f"{100 * c['validation_error_with']:.3g} %, over most of its tenths (t = {c['t']:.2g}): it does not hold beyond "
                "the run it was found on")
    if c.get("reason") == "sign":
        name = DISSIPATIVE_PARAMETER[c["effect"]]
        return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests, but refitted with the other findings "
                f"on all the identification data its {name} came out {c['parameters'][name]:.4g}: friction that pushes the joint "
                "along, or a negative inertia, is not physical (another effect's shape it was bent to)")
    wider = "widened beyond any width" if c["prior_widened_by"] is None else f"{c['prior_widened_by'] / c['before']:.3g}x wider"
    return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests, but with it least squares on the "
            f"identification data moves away from the robot file's modeled values (the prior would have to be {wider}): "
            "the data cannot tell it from a worse model")
