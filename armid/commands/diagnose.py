"""``armid diagnose``: the declared model's fit, the undeclared effects found in its residual,
and the errors before and after (identify.diagnosis)."""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from typing import Any

from armid.schema.errors import PoorExcitationWarning

from .arguments import RECORDINGS, ROBOT_HELP, add_topic_argument, load_robot_argument
from .identify import add_feasible_arguments, feasible_report, preparation_arguments, recipe_from_arguments, wants_feasible
from .output import check_writable, inputs_read, show_warnings, write_json_and_predictions


def _diagnose(args: argparse.Namespace) -> int:
    from armid.identify.diagnosis.search import extrapolation_sentence, negligible_sentence, set_aside_sentence

    from .. import pipeline

    check_writable(args.urdf, args.mjcf)
    robot = load_robot_argument(args.robot)
    inputs = pipeline.load(robot, recipe_from_arguments(args), args.data, args.validate, args.topic)
    show_warnings(inputs.warnings)
    inputs_read()
    experiments, validation = inputs.experiments, inputs.validation
    for path, prep in zip(inputs.sources, experiments + validation):
        for note in prep.notes:
            print(f"{path}: {note}", file=sys.stderr)
    diag = pipeline.diagnose(robot, inputs)
    doc = diag.to_json()
    feasible_line = None
    if wants_feasible(args):
        feasible_line = _diagnosed_feasible(args, robot, diag, experiments, validation, doc)
    assert diag.predictions is not None
    t_stamps, _, tau_hat = diag.predictions
    write_json_and_predictions(args.json, doc, args.predictions, lambda: (t_stamps, tau_hat))
    if args.report:
        from ..report import write_diagnosis_report

        write_diagnosis_report(diag, robot, Path(args.report), doc.get("feasible"), identified_on=", ".join(Path(d).name for d in args.data),
                               validated_on=", ".join(Path(d).name for d in args.validate))
    for f in diag.found:
        print(f.sentence())
    if diag.verdict():
        print(diag.verdict())
    for x in diag.negligible:
        print(f"not a finding: {negligible_sentence(x)}")
    for note in diag.notes:
        print(note)
    for a in diag.absorbed:
        print(f"absorbed (not a finding): {a['effect']} on joint {a['joint']} joins {a['into']}")
    for c in diag.conflicting:
        print(f"set aside (not a finding): {set_aside_sentence(c)}")
    for x in diag.extrapolated:
        print(f"extrapolated: {extrapolation_sentence(x)}")
    if diag.differs is not None:
        for line in differs_lines(robot.name, diag.differs):
            print(line)
    print(f"{robot.name}: validation error {100 * doc['before']['relative_error']:.3g} % -> {100 * doc['after']['relative_error']:.3g} %")
    if feasible_line:
        print(feasible_line)
    return 0


def differs_lines(name: str, differs: Any) -> list[str]:
    """The validation data the final model does not explain: the figures, and what changed
    there (``armid check``'s search on them, the final model held fixed)."""
    floor = differs.noise_floor["relative_error"]
    lines = [f"{name}: the validation data differ from the identification data: the final model's validation error "
             f"{100 * differs.before['relative_error']:.3g} % against {100 * differs.reference.relative_error:.3g} % on the identification "
             f"data" + ("" if floor is None else f" and a noise floor of {100 * floor:.3g} %") + "; what changed there (armid check):"]
    lines += [f"  {c.sentence()}" for c in differs.found] + [f"  {n}" for n in differs.notes]
    if not differs.found:
        lines.append("  nothing in the catalogue nor a load on the last link explains it")
    else:
        lines.append(f"  validation error {100 * differs.before['relative_error']:.3g} % -> {100 * differs.after['relative_error']:.3g} % "
                     "with what changed (each sample predicted by the fit on the other tenths of the validation data)")
    return lines


def _diagnosed_feasible(args: argparse.Namespace, robot: Any, diag: Any, experiments: list[Any], validation: list[Any], doc: dict[str, Any]) -> str | None:
    """The feasible estimate of the model diagnose ends with: the declared model plus every
    finding (identify.diagnosis.findings_model), the same fit as its 'after'."""
    from armid.identify.diagnosis.search import findings_model
    from armid.identify.identification import identify

    model, options = findings_model(robot, diag.found)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)
        result = identify(model, experiments, validation, options)
    line = feasible_report(args, model, result, validation, doc)
    doc["feasible"]["model"] = {"declared": doc.get("declared", []),
                                "added_findings": [f"{f.effect}@{'arm' if f.joint is None else f.joint + 1}" for f in diag.found]}
    return line


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid diagnose``: its options."""
    p = sub.add_parser("diagnose", help="residual analysis: find undeclared effects, add them, refit, error before/after")
    p.add_argument("data", nargs="+", help=f"recordings to identify on ({RECORDINGS})")
    p.add_argument("--robot", required=True, help=ROBOT_HELP)
    p.add_argument("--validate", nargs="+", metavar="DATA", required=True, help="held-out recordings: the errors before and after are measured on them, and a finding they contradict is set aside (findings are chosen on the identification data)")
    p.add_argument("--json", metavar="OUT", help="write the findings and the errors before and after as JSON")
    p.add_argument("--report", metavar="DIR", help="write diagnosis.md with residual plots per joint")
    p.add_argument("--predictions", metavar="CSV", help="write the final model's predicted validation torques (t, tau_hat1..n)")
    add_feasible_arguments(p)
    preparation_arguments(p)
    add_topic_argument(p)
    p.set_defaults(run=_diagnose)
