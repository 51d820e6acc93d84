"""``armid identify``: least-squares identification (eq. 18) of recordings, whole arm or
Khosla's single-link sequence, with ``--feasible``/``--urdf``/``--mjcf`` the physically consistent estimate."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from armid.schema.errors import IdentificationError, RecordingError, UsageError

from .arguments import RECORDINGS, ROBOT_HELP, add_topic_argument, gap_factor, load_robot_argument, lowpass_setting
from .output import check_writable, inputs_read, show_warnings, strict_json, write_json_and_predictions


def recipe_from_arguments(args: argparse.Namespace, **extra: Any) -> Any:
    """The recipe ``--recipe`` names (:data:`~armid.pipeline.RECIPES`: ``identify``, a log the
    user brings, unless told) with the flags the user gave; a flag left out keeps the recipe's
    value, so that ``--recipe drives`` is exactly what the demo and the service do."""
    from ..pipeline import RECIPES

    flags = {"max_gap_factor": args.max_gap_factor, "lowpass_hz": args.lowpass, "torque_hold": args.torque_hold, **extra}
    return RECIPES[args.recipe].with_options(**{k: v for k, v in flags.items() if v is not None})


def preparation_arguments(p: argparse.ArgumentParser) -> None:
    """How the recordings are prepared: a named recipe, and the flags that change it
    (``identify`` and ``diagnose`` alike)."""
    p.add_argument("--recipe", choices=("identify", "drives"), default="identify",
                   help="identify (default): a log you bring (the low-pass chosen from its spectrum, the torque as sampled); "
                        "drives: a recording of armid excite as the demo and the service take it (no low-pass, currents held "
                        "over the period, the samples beside a velocity reversal left out); the flags below change either")
    p.add_argument("--lowpass", type=lowpass_setting, default=None, metavar="HZ|auto|off",
                   help="zero-phase low-pass of the kinematics, the regressor and the torque alike (default: the recipe's; "
                        "identify: auto, chosen from each recording's spectrum; drives: off)")
    p.add_argument("--torque-hold", action="store_true", default=None,
                   help="torques were held over the period before each sample (drive currents between SYNCs; drives: always)")
    p.add_argument("--max-gap-factor", type=gap_factor, default=None, help="split where a step exceeds this many median steps (default 20)")


def _identify(args: argparse.Namespace) -> int:

    from .. import pipeline

    check_writable(args.urdf, args.mjcf)
    robot = load_robot_argument(args.robot)
    recipe = recipe_from_arguments(args, weighting=args.weighting, prior=args.prior)
    if args.single_link:
        return _identify_single_link(args, robot, recipe)
    inputs = pipeline.load(robot, recipe, args.data, args.validate or [], args.topic)
    show_warnings(inputs.warnings)
    inputs_read()
    experiments, validation = inputs.experiments, inputs.validation
    result, excitation = pipeline.identify(robot, experiments, validation, recipe)
    for message in excitation:
        print(f"warning: {message}", file=sys.stderr)
    doc = result.to_json()
    doc["recordings"] = inputs.recordings()
    from armid.identify.diagnosis.check import motion_ranges

    doc["motion"] = motion_ranges(experiments)  # what the model was identified on: armid check says where new data go beyond it
    feasible_line = feasible_report(args, robot, result, validation, doc)
    for path, prep in zip(inputs.sources, experiments + validation):
        for note in prep.notes:
            print(f"{path}: {note}", file=sys.stderr)
    segments = [s for p in (validation or experiments) for s in p.segments]

    def predictions() -> tuple[Any, Any]:
        if not validation:
            raise IdentificationError("--predictions needs --validate data")
        t, _, tau_hat = result.predict_stamps(segments)
        return t, tau_hat

    write_json_and_predictions(args.json, doc, args.predictions, predictions)
    if args.report:
        from ..report import write_report

        write_report(result, doc, segments, Path(args.report), "validation data" if validation else "identification data")
    for b in doc["base_parameters"]:
        if not b["identified"]:
            print(f"base parameter {b['expression']}: {not_identified(b['std'], b['physical_range'])}")
    v = doc["validation"]
    print(
        f"{robot.name}: {doc['samples']} samples, {len(doc['base_parameters'])} base parameters, "
        f"condition number {doc['condition_number']:.3g}, fit error {doc['fit']['relative_error']:.4g}"
        + (f", validation error {v['relative_error']:.4g}" if v else "")
    )
    if feasible_line:
        print(feasible_line)
    return 0


def _identify_single_link(args: argparse.Namespace, robot: Any, recipe: Any) -> int:
    """``armid identify --single-link``: Khosla's off-line sequence on the user's recordings,
    each moving one joint (property 4), identified last link first; each validation recording
    (one joint moving too) predicted and scored on the joint that moved."""
    import numpy as np

    from armid.identify.preprocess import prepare
    from armid.identify.single_link import single_link_sequence
    from armid.io.recordings import write_csv

    if args.feasible or args.urdf or args.mjcf or args.bounding_box or args.report:
        raise UsageError("--single-link gives Khosla's tables and predictions: --feasible, --urdf, --mjcf, --bounding-box and --report "
                         "are for a whole-arm identification")
    runs: dict[int, list[Any]] = {}
    recordings = []
    for path in args.data:
        rec, link = _single_joint_run(path, robot, args.topic)
        runs.setdefault(link, []).append(prepare(rec, robot, recipe.prepare))
        recordings.append({"path": path, "role": "identification", "stopped": rec.stopped})
    checked = [(path, *_single_joint_run(path, robot, args.topic)) for path in args.validate or []]
    recordings += [{"path": path, "role": "validation", "stopped": rec.stopped} for path, rec, _ in checked]
    inputs_read()
    seq = single_link_sequence(robot, runs)
    table = seq.table()
    for row in table:
        value = (f" = {row['estimate']:.6g} +- {row['std']:.3g}" if row["identified"]
                 else f": {not_identified(row['std'], row['physical_range'])}")
        print(f"link {row['link']}: {row['parameter']}{value} (modeled {row['modeled']:.6g})")
    validation, predicted = [], []
    for path, rec, link in checked:
        prep = prepare(rec, robot, recipe.prepare)
        t = np.concatenate([g.t for g in prep.segments])
        tau = np.concatenate([g.tau for g in prep.segments])
        tau_hat = np.concatenate([seq.predict(g.q, g.qd, g.qdd) for g in prep.segments])
        error = float(np.linalg.norm(tau[:, link] - tau_hat[:, link]) / max(float(np.linalg.norm(tau[:, link])), 1e-300))
        validation.append({"recording": path, "joint": link + 1, "samples": int(t.size), "relative_error": error})
        predicted.append((t, tau_hat))
        print(f"{path}: joint {link + 1} predicted with relative error {100 * error:.3g} %")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(strict_json({"single_link": seq.to_json(), "validation": validation, "recordings": recordings},
                                               indent=1) + "\n")
    if args.predictions:
        if not predicted:
            raise IdentificationError("--predictions needs --validate data")
        Path(args.predictions).parent.mkdir(parents=True, exist_ok=True)
        write_csv(args.predictions, np.concatenate([t for t, _ in predicted]), {"tau_hat": np.concatenate([h for _, h in predicted])})
    done = ", ".join(str(step["link"]) for step in seq.steps)
    weak = sum(not row["identified"] for row in table)
    print(f"{robot.name}: single-link sequence over links {done}: {len(table) - weak} combinations identified"
          + (f", {weak} not identified by these data" if weak else "")
          + (f"; validation error {100 * float(np.mean([v['relative_error'] for v in validation])):.3g} % (mean over the runs)" if validation else ""))
    return 0


def not_identified(std: float, physical_range: float | None) -> str:
    """What a table prints instead of a value the data do not identify (its three sigmas
    beyond its physical range: :func:`armid.identify.identifiability.identified_by_data`)."""
    import numpy as np

    from armid.identify.identifiability import IDENTIFIED_SIGMAS

    bound = "an unbounded range" if physical_range is None or not np.isfinite(physical_range) else f"a physical range of {physical_range:.3g}"
    return f"not identified by these data (+-{IDENTIFIED_SIGMAS * std:.3g} at {IDENTIFIED_SIGMAS:g} sigma against {bound})"


def _single_joint_run(path: str, robot: Any, topic: str | None = None) -> tuple[Any, int]:
    """The recording, cut to its excitation window where ``armid excite``'s ``runs.json`` gives
    it, and the one joint (0-based) that moved in it."""
    import numpy as np

    from armid.identify.plausibility import MOVING_RAD, moving_joints

    from ..pipeline import read

    rec, found = read(path, robot, need_motion=False, topic=topic)
    show_warnings(found)
    rec = _excitation_window(Path(path), rec)
    moved = np.flatnonzero(moving_joints(rec.q))
    if moved.size != 1:
        what = "no joint moved" if moved.size == 0 else f"joints {', '.join(str(j + 1) for j in moved)} moved"
        raise RecordingError(path, f"{what} (by more than {MOVING_RAD} rad): a single-link experiment moves one joint alone "
                                   "(Khosla's property 4)")
    return rec, int(moved[0])


def _excitation_window(path: Path, rec: Any) -> Any:
    """The part of an ``armid excite`` recording inside its plan's excitation window (whole
    periods of the design, as the demo and the service identify it), when a ``runs.json`` of
    that run lies in one of the three folders above it; else the whole recording."""
    import numpy as np

    from ..pipeline import Window, cut_to_window

    for folder in list(path.resolve().parents)[:3]:
        runs = folder / "runs.json"
        if not runs.is_file() or rec.cycle is None:
            continue
        try:
            reports = json.loads(runs.read_text())
        except (OSError, ValueError):
            continue
        for r in reports if isinstance(reports, list) else []:
            if not isinstance(r, dict) or Path(str(r.get("recording", ""))).name != path.name or r.get("name") != path.parent.name:
                continue
            w0, w1 = (float(x) for x in r["window_s"])
            # the plan's time is cycles times the rig's period (as the demo and the service cut it),
            # not the stamps' median step: on a bus timed by this host's clock they differ
            period = rec.period_s if rec.period_s is not None else float(np.median(np.diff(rec.t)))
            return cut_to_window(rec, Window(int(r["first_cycle"]), (w0, w1), period))
    return rec


def wants_feasible(args: argparse.Namespace) -> bool:
    """Whether the command line asks for the physically consistent estimate (``--feasible``, or
    an option that needs it)."""
    return bool(args.feasible or args.urdf or args.mjcf or args.bounding_box)


def feasible_report(args: argparse.Namespace, robot: Any, result: Any, validation: list[Any], doc: dict[str, Any]) -> str | None:
    """``--feasible`` / ``--urdf`` / ``--mjcf``: the physically consistent estimate into
    ``doc["feasible"]`` and, with ``--urdf OUT`` or ``--mjcf OUT``, the model written as a URDF
    or as MJCF."""
    if not wants_feasible(args):
        return None
    from armid.identify.feasible import feasible_estimate

    from ..urdf_export import collision_boxes, effect_values, write_urdf

    boxes = collision_boxes(robot) if args.bounding_box else None
    if boxes is not None and all(b is None for b in boxes):
        raise IdentificationError(f"--bounding-box: {robot.source} gives no link a box (no URDF, or only meshes)")
    fr = feasible_estimate(result, validation or None, boxes=boxes)
    doc["feasible"] = fr.to_json()
    if args.urdf:
        write_urdf(args.urdf, robot, fr.phi, effect_values(doc["feasible"]))
    written = model_files_line(args, robot, fr.phi, list(result.effects), fr.names)
    for note in fr.fit.prior_notes:
        print(f"{robot.source}: {note}", file=sys.stderr)
    for check in fr.least_squares_checks:
        for v in check.violations:
            print(f"least squares, link {check.link}: {v}")
    return f"{robot.name}: {fr.summary_line()}" + written


def model_files_line(args: argparse.Namespace, robot: Any, phi: Any, effects: list[Any], names: list[str]) -> str:
    """Write ``--mjcf OUT`` (the ``names`` of ``phi``'s entries place each effect's value) and
    say, for the command's last line, which files were written and what MuJoCo's model leaves out."""
    import numpy as np

    text = f"; URDF written to {args.urdf}" if args.urdf else ""
    if args.mjcf:
        from ..mjcf_export import write_mjcf

        values = [phi[names.index(label)] for e in effects for label in e.labels()]
        _, left_out = write_mjcf(args.mjcf, robot, np.concatenate([phi[: robot.n_parameters], values]), effects)
        text += f"; MJCF written to {args.mjcf}" + (f" (no MuJoCo term, left out: {'; '.join(left_out)})" if left_out else "")
    return text


def add_feasible_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--feasible", action="store_true",
                   help="also the physically consistent estimate (pseudo-inertia PSD, friction >= 0) and a consistency report in the JSON")
    p.add_argument("--urdf", metavar="OUT", help="write the physically consistent model as a URDF (implies --feasible)")
    p.add_argument("--mjcf", metavar="OUT",
                   help="write the physically consistent model as MJCF for MuJoCo: viscous and Coulomb friction, rotor inertia and "
                        "springs as joint damping, frictionloss, armature and stiffness; what MuJoCo has no term for is named "
                        "(implies --feasible; needs armid[mujoco])")
    p.add_argument("--bounding-box", action="store_true",
                   help="keep each link's mass inside the box of its URDF collision geometry (links with a mesh or without geometry: "
                        "no box; implies --feasible)")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid identify``: its options."""
    p = sub.add_parser("identify", help="least-squares identification (eq. 18) with identifiability classes")
    p.add_argument("data", nargs="+", help=f"recordings to identify on ({RECORDINGS})")
    p.add_argument("--robot", required=True, help=ROBOT_HELP)
    p.add_argument("--validate", nargs="+", metavar="DATA", help="held-out recordings for the validation error")
    p.add_argument("--json", metavar="OUT", help="write the result as JSON (docs/reference/interfaces.md)")
    p.add_argument("--report", metavar="DIR", help="write a markdown report with PNG plots")
    p.add_argument("--predictions", metavar="CSV", help="write predicted validation torques (t, tau_hat1..n)")
    p.add_argument("--weighting", choices=("wls", "ols"), default=None, help="per-joint weighted (default) or ordinary LS")
    p.add_argument("--prior", choices=("modeled", "none"), default=None,
                   help="the robot file's modeled values as a prior for what the data do not excite (default), or least squares alone")
    add_feasible_arguments(p)
    preparation_arguments(p)
    add_topic_argument(p)
    p.add_argument("--single-link", action="store_true",
                   help="Khosla's off-line sequence: each recording moves one joint alone; identified last link first, its "
                        "combinations with their std; each --validate run predicted on the joint that moved")
    p.set_defaults(run=_identify)
