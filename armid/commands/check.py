"""``armid check``: does an identified model hold on new data, and if not, what changed
(identify.check). The model is what ``armid identify --json`` wrote, held fixed."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from armid.schema.errors import RecordingError

from .arguments import RECORDINGS, ROBOT_HELP, add_topic_argument, load_robot_argument
from .identify import preparation_arguments, recipe_from_arguments
from .output import check_writable, inputs_read, show_warnings, write_json_and_predictions


def fixed_model(robot: Any, doc: dict[str, Any], path: str) -> tuple[Any, Any]:
    """The identification document's model (:class:`~armid.identify.diagnosis.check.FixedModel`) and what
    it showed on its own data (:class:`~armid.identify.diagnosis.check.Reference`: its validation error
    where it was validated, else its held-out error, else its fit error)."""
    import numpy as np

    from armid.identify.diagnosis.check import FixedModel, Reference
    from armid.identify.payload.arm import arm_model_from_identification

    arm = arm_model_from_identification(robot, doc)
    effects = tuple(_with_load(e, doc, path) for e in arm.effects)
    scale = doc.get("torque_scale")
    if scale is not None and (not isinstance(scale, list) or len(scale) != robot.n_joints):
        raise RecordingError(path, f"torque_scale: must be {robot.n_joints} numbers or null, got {scale!r}")
    model = FixedModel(robot, effects, arm.columns, arm.beta, None if scale is None else np.asarray(scale, float),
                       None if doc.get("joint_noise_sigma") is None else arm.joint_sigma)
    for kind in ("validation", "held_out", "fit"):
        errors = doc.get(kind)
        if isinstance(errors, dict) and isinstance(errors.get("relative_error"), int | float) and \
                isinstance(errors.get("relative"), list) and len(errors["relative"]) == robot.n_joints:
            return model, Reference(float(errors["relative_error"]), np.asarray(errors["relative"], float), kind)
    raise RecordingError(path, "no fit or validation errors (fit.relative_error, fit.relative): is it the output of armid identify --json?")


def _with_load(effect: Any, doc: dict[str, Any], path: str) -> Any:
    """A load-dependent friction with the load the identification used (its effect's ``load``
    in the document: the rigid body whose torque it carries)."""
    from dataclasses import replace

    import numpy as np

    from armid.identify.effects import LoadFriction

    if not isinstance(effect, LoadFriction):
        return effect
    entry = next((e for e in doc.get("effects", []) if isinstance(e, dict) and e.get("effect") == effect.effect
                  and e.get("joint") == effect.joint + 1), {})
    load = entry.get("load")
    n = len(effect.load_parameters)
    if not isinstance(load, list) or len(load) != n or not all(isinstance(x, int | float) and np.isfinite(x) for x in load):
        raise RecordingError(path, f"effects: load_dependent_coulomb on joint {effect.joint + 1} needs its 'load' ({n} numbers: "
                                   "the identification's rigid body), as armid identify --json writes it")
    return replace(effect, load_parameters=tuple(float(x) for x in load))


def _check(args: argparse.Namespace) -> int:
    import numpy as np

    from armid.identify.diagnosis.check import beyond_motion, check

    from .. import pipeline
    from ..check_report import verdict_lines
    from .estimate import identification_document

    check_writable(args.urdf, args.mjcf)
    robot = load_robot_argument(args.robot)
    doc = identification_document(args.model, robot)
    model, reference = fixed_model(robot, doc, args.model)
    to_write = _model_to_write(args, robot, doc, model.effects)
    inputs = pipeline.load(robot, recipe_from_arguments(args), args.data, topic=args.topic)
    show_warnings(inputs.warnings)
    inputs_read()
    for path, prep in zip(inputs.sources, inputs.experiments):
        for note in prep.notes:
            print(f"{path}: {note}", file=sys.stderr)
    result = check(model, inputs.experiments, reference)
    motion = doc.get("motion")
    if isinstance(motion, dict) and not result.holds:
        try:
            beyond = beyond_motion(motion, inputs.experiments)
        except (KeyError, IndexError, TypeError):
            raise RecordingError(args.model, f"motion: must hold position_low, position_high, speed and acceleration for "
                                             f"{robot.n_joints} joints") from None
        result.beyond_motion = beyond
    out = result.to_json()
    out["model"] = {"path": args.model, "samples": doc.get("samples"), "reference": reference.kind}
    write_json_and_predictions(args.json, out, args.predictions,
                               lambda: (np.concatenate([s.at_stamps.t for p in inputs.experiments for s in p.segments]), result.predictions))
    if args.report:
        from ..check_report import write_check_report

        write_check_report(result, robot, Path(args.report))
    for line in verdict_lines(robot.name, result):
        print(line)
    if to_write is not None:
        print(f"{robot.name}: {_write_model_files(args, robot, to_write, model.effects, result)}")
    return 0


def _model_to_write(args: argparse.Namespace, robot: Any, doc: dict[str, Any], effects: tuple[Any, ...]) -> tuple[Any, Any] | None:
    """``--urdf`` / ``--mjcf``: the document's physically consistent parameters, the links' and
    the effects' (in the order of ``effects``), read before the data; None without either option."""
    if not (args.urdf or args.mjcf):
        return None
    import numpy as np

    feasible = doc.get("feasible")
    entries = feasible.get("parameters") if isinstance(feasible, dict) else None
    if not isinstance(feasible, dict) or not isinstance(entries, list) or len(entries) != robot.n_parameters:
        raise RecordingError(args.model, f"feasible.parameters: --urdf and --mjcf write the physically consistent parameters "
                                         f"({robot.n_parameters} for {robot.name}): identify with --feasible --json")
    try:
        phi = np.array([float(p["value"]) for p in entries])
        values = {(e["effect"], int(e["joint"]), e["parameter"]): float(e["value"]) for e in feasible.get("effects", [])}
        effect_phi = np.array([values[(e.effect, e.joint + 1, name)] for e in effects for name in e.parameter_names])
    except (KeyError, TypeError, ValueError) as err:
        raise RecordingError(args.model, f"feasible: a parameter or an effect without its value ({err})") from None
    if not np.all(np.isfinite(phi)) or not np.all(np.isfinite(effect_phi)):
        raise RecordingError(args.model, "feasible: a parameter that is not a finite number")
    return phi, effect_phi


def _write_model_files(args: argparse.Namespace, robot: Any, model: tuple[Any, Any], effects: tuple[Any, ...], result: Any) -> str:
    """Write the model checked (:func:`_model_to_write`) with a load found on the last link
    (its mass, centre and inertia, where these data determine them) added to that link: the
    arm as these data show it. Other changes are named, not written."""
    import numpy as np

    from armid.identify.robot import Inertial, link_parameters

    from ..urdf_export import write_urdf
    from .identify import model_files_line

    phi, effect_phi = model[0].copy(), model[1]
    added, named = [], []
    for c in result.found:
        p = c.parameters
        if c.effect == "payload" and p["m"] > 0 and p.get("cx") is not None:
            load = Inertial(p["m"], (p["cx"], p["cy"], p["cz"]), tuple(p[f"I{k}"] for k in ("xx", "xy", "xz", "yy", "yz", "zz")))
            phi[-10:] += link_parameters(load)
            added.append(f"with the load of {p['m']:.3f} kg found on link {robot.n_joints}")
        else:
            named.append(f"{'a load' if c.effect == 'payload' else c.effect.replace('_', ' ')} on "
                         f"{'the arm' if c.joint is None else f'joint {c.joint + 1}'}")
    notes = added + ([f"not in it, found changed: {', '.join(named)}"] if named else [])
    labels = [label for e in effects for label in e.labels()]
    if args.urdf:
        k = 0
        values = {}
        for e in effects:
            values[(e.effect, e.joint + 1)] = float(effect_phi[k])
            k += len(e.parameter_names)
        write_urdf(args.urdf, robot, phi, values)
    written = model_files_line(args, robot, np.concatenate([phi, effect_phi]), list(effects), robot.parameter_names + labels)
    return f"the model of {args.model}" + (f" ({', '.join(notes)})" if notes else "") + written.replace("; ", ": ", 1)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid check``: its options."""
    p = sub.add_parser("check", help="does an identified model hold on new data; if not, what changed (a load, friction, a gain ...)")
    p.add_argument("data", nargs="+", help=f"the new recordings ({RECORDINGS})")
    p.add_argument("--robot", required=True, help=ROBOT_HELP)
    p.add_argument("--model", required=True, metavar="IDENTIFIED.json",
                   help="the model to check: what armid identify --json wrote (held fixed: nothing it identified is refitted)")
    p.add_argument("--json", metavar="OUT", help="write the verdict, what changed and the errors before and after as JSON")
    p.add_argument("--report", metavar="DIR", help="write check.md with each joint's error against the model's own and the floor")
    p.add_argument("--predictions", metavar="CSV", help="write the predicted torques with what changed (t, tau_hat1..n), each "
                                                        "sample from the fit on the other tenths")
    p.add_argument("--urdf", metavar="OUT", help="write the model checked as a URDF: the physically consistent parameters of "
                                                 "--model (identify --feasible --json), a load found on the last link added")
    p.add_argument("--mjcf", metavar="OUT", help="the same as MJCF for MuJoCo (armid identify --mjcf; needs armid[mujoco])")
    preparation_arguments(p)
    add_topic_argument(p)
    p.set_defaults(run=_check)
