"""What the diagnosis reports: each :class:`Finding` and the whole :class:`Diagnosis` (the
``armid diagnose --json`` document), and the sentences the text output and the report say
of a finding, of a candidate set aside, and of a finding the validation extrapolates.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from ..spatial import Array
from .candidates import DISSIPATIVE_PARAMETER


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
    # the validation error (relative_error, every joint) with the findings before this one and
    # with it too (Diagnosis: measured in the order found), and its torque's rms there (N*m or N)
    validation_before: float | None = None
    validation_after: float | None = None
    torque_rms: float | None = None

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
        text = f"{where}: {signature}: {name} {params}"
        if self.validation_before is not None and self.validation_after is not None:
            text += f"; validation error {100 * self.validation_before:.3g} % -> {100 * self.validation_after:.3g} %"
        if self.torque_rms is not None:
            text += f" ({self.torque_rms:.3g} N*m rms{'' if self.joint is not None else ' on the joint it moves most'})"
        text += f"; held-out error (identification data) {100 * self.error_before:.2f} % -> {100 * self.error_after:.2f} %"
        if self.lookalike:
            text += f" (cannot be told apart from {self.lookalike.replace('_', ' ')} on this data; to separate them: {self.separate_by})"
        return text

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"effect": self.effect, "joint": None if self.joint is None else self.joint + 1,
                               "parameters": self.parameters, "explained": self.explained,
                               "held_out": {"relative_error_before": self.error_before, "relative_error_after": self.error_after}}
        if self.validation_before is not None:
            out["validation"] = {"relative_error_before": self.validation_before, "relative_error_after": self.validation_after}
            out["torque_rms"] = self.torque_rms
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
    # findings below the materiality (MATERIALITY): not found, with their size
    negligible: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # what was not tested, and why
    # identify.check's CheckResult of the validation data against the final model, where it
    # does not hold on them (the validation data differ from the identification data)
    differs: Any = None

    def verdict(self) -> str | None:
        """The sentence where nothing was found: what the error stands at against the floor
        (never that the model explains data it does not: see :attr:`differs`)."""
        if self.found:
            return None
        floor = (self.noise_floor or {}).get("relative_error")
        e = self.after["relative_error"]
        if self.differs is None and floor is not None and e**2 <= (1.0 + EXPLAINS_RISE) * floor**2:
            return f"nothing significant found: the declared model explains the data to its noise ({100 * e:.3g} % against a floor of {100 * floor:.3g} %)"
        floor_text = "no noise floor" if floor is None else f"a noise floor of {100 * floor:.3g} %"
        return (f"nothing significant found in the identification data's residual; the declared model's validation error {100 * e:.3g} % "
                f"stands above {floor_text}: what remains is not in the catalogue" + (" or lies in the validation data alone (below)" if self.differs else ""))

    def to_json(self) -> dict[str, Any]:
        return {"validation_differs": None if self.differs is None else self.differs.to_json(), "found": [f.to_json() for f in self.found], "absorbed": self.absorbed, "declared": self.base_effects,
                "set_aside": self.conflicting, "extrapolated": self.extrapolated, "negligible": self.negligible,
                "materiality": {"min_validation_drop": MATERIALITY, "how": MATERIALITY_HOW}, "notes": self.notes,
                "before": self.before, "after": self.after, "noise_floor": self.noise_floor,
                "chosen_on": "the identification data: fitted on its even tenths, scored on its odd tenths; a finding that "
                             "raises its joint's error on the validation data consistently (over its tenths) is set aside (a veto, never a ranking)",
                "measured_on": "the validation data (before and after), at every sample's own stamp against the raw torque"}


EXPLAINS_RISE = 0.5
"""The model explains data to their noise while its error's power is within this fraction
above the noise floor's (``e^2 <= 1.5 f^2``: the error at most 1.22 times the floor), as
``armid check`` holds a model (identify.check.CheckOptions.rise)."""

MATERIALITY = 0.02
"""A finding must remove at least this fraction of the validation error's power above the
noise floor, measured with the findings kept before it: ``e_b^2 - e_a^2 >= 0.02 (e_b^2 - f^2)``
(``e`` relative_error before and after it, ``f`` the validation's noise floor). Where the model
error dominates (the KUKA LWR4+'s torque sensors: f ~ 0.002 %) that is about 1 % of the error
(2.00 % -> 1.98 %): the issue 33 lab's 2.76 % -> 2.73 % for a gain and a spring together is 2.2 %
of the power for the two, below it for each. Near the noise floor the power above it is what
any effect can remove, so an effect barely above the noise (the blind sweep's smallest) is
judged against that, not against the noise no model removes. Below it the effect is reported
as negligible with its torque's rms, never as found, and left out of the model."""

MATERIALITY_HOW = ("each finding, added in the order found to the declared model and the findings kept before it, must lower the "
                   "validation relative_error e so that e_before^2 - e_after^2 >= min_validation_drop * (e_before^2 - noise_floor^2): "
                   "that fraction of the error's power above the noise floor; below it the effect is reported under 'negligible' "
                   "with its torque's rms on the validation data (N*m), and left out of the model")


def negligible_sentence(x: dict[str, Any]) -> str:
    """One line for an effect below the materiality (the text output and the report)."""
    where = "the arm" if x["joint"] is None else f"joint {x['joint']}"
    return (f"{x['effect'].replace('_', ' ')} on {where}: negligible: {x['torque_rms']:.3g} N*m rms (validation error "
            f"{100 * x['validation_error_before']:.3g} % -> {100 * x['validation_error_with']:.3g} %: under the "
            f"{100 * MATERIALITY:g} % of the error's power above the noise floor a finding must remove)")


POSITION_DEPENDENT = ("spring", "cogging")
"""Effects that are functions of one joint's position: beyond the positions a finding was
fitted on, it is an extrapolation (a spring may be the local slope of a ripple longer than
the motion; held-out tenths of the same motion cannot tell)."""


def extrapolated_findings(found: list[Finding], q_ident: Array, q_valid: Array, tolerance: float = 0.05) -> list[dict[str, Any]]:
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
    """What the text and the report say of a candidate set aside: by gate (d) or (f), because
    an exact fit (gate (g)'s or the final one) held its friction, inertia or stiffness at 0 or
    turned its sign, or because it raised the validation error in the final fit."""
    where = "the arm" if c["joint"] is None else f"joint {c['joint']}"
    if c.get("reason") == "validation" and "t" in c:  # gate (f): the search's fit, its joint's error
        return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests on the identification data, but on the "
                f"validation data it takes {where}'s error from {100 * c['validation_error_before']:.3g} % to "
                f"{100 * c['validation_error_with']:.3g} %, over most of its tenths (t = {c['t']:.2g}): it does not hold beyond "
                "the run it was found on")
    if c.get("reason") == "validation":  # the materiality test: the final fit, the arm's error
        return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests on the identification data, but fitted "
                f"with the findings before it on all of them it takes the validation error from {100 * c['validation_error_before']:.3g} % "
                f"to {100 * c['validation_error_with']:.3g} %: it does not hold beyond the run it was found on")
    if c.get("reason") == "sign":
        name = DISSIPATIVE_PARAMETER[c["effect"]]
        value = c["parameters"][name]
        if value == 0.0:
            return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests, but refitted with the other "
                    f"findings on all the identification data its best admissible fit holds {name} at 0 (friction dissipative, "
                    "inertia and stiffness positive): it explains nothing the model without it does not")
        return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests, but refitted with the other findings "
                f"on all the identification data its {name} came out {value:.4g}: friction that pushes the joint "
                "along, a negative inertia or a spring that pushes away from its rest is not physical (another effect's shape it was bent to)")
    wider = "widened beyond any width" if c["prior_widened_by"] is None else f"{c['prior_widened_by'] / c['before']:.3g}x wider"
    return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests, but with it least squares on the "
            f"identification data moves away from the robot file's modeled values (the prior would have to be {wider}): "
            "the data cannot tell it from a worse model")
