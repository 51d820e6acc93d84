"""``armid excite``: the operator's excitation, designed (or given) trajectories checked against
every limit, run on the drives and recorded."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from armid.schema.errors import BusOpenError, InputFileError, OptionError, UsageError

from ..schema.json_text import write_json
from .arguments import positive_number, seed_number, whole_count
from .output import inputs_read
from .rig import check_rig_budget, open_rig_driver, rest_pose, rig_from_arguments, simulating
from .ros2 import add_ros2_arguments, ros2_bridge
from .session import add_zenoh_arguments, open_zenoh


def _excite(args: argparse.Namespace) -> int:
    import time

    import numpy as np
    from rich.console import Console

    rig = rig_from_arguments(args)
    robot = rig.robot
    n = robot.n_joints
    if args.frequency is not None and args.frequency >= 0.5 / rig.period_s:
        raise OptionError("--frequency", f"{args.frequency:g} Hz is not below the {0.5 / rig.period_s:g} Hz Nyquist frequency "
                                         f"of {rig.source}'s {rig.period_s:g} s period")
    console = Console(stderr=True)
    simulate = simulating(rig, args)
    links: list[int] = []
    for spec in args.link or []:
        if spec == "all":
            links += list(range(n - 1, -1, -1))  # Khosla's sequence: last link first
        else:
            try:
                j = int(spec)
            except ValueError:
                raise UsageError(f"--link: {spec!r} is not a joint number or 'all'") from None
            if not 1 <= j <= n:
                raise UsageError(f"--link: joint {j} does not exist; {robot.name} has joints 1..{n}")
            links.append(j - 1)
    trajectory = load_trajectory(args.trajectory, n, rig.period_s) if args.trajectory else None  # checked before any drive is enabled
    inputs_read()
    out = Path(args.out or f"runs/{time.strftime('%Y%m%d-%H%M%S')}")
    # the pose the arm will be at: the rig's (simulated) start, or the drives' own report
    start = np.asarray(rig.simulation.get("initial_position", np.zeros(n)), float) if simulate else None
    zsession = stream = None
    holder: dict[str, Any] = {}
    if not args.no_zenoh and not args.dry_run:  # every record on armid/<robot>/joint_state, each experiment on events
        from armid.daq.stream import Stream

        zsession = open_zenoh(args)

        def status() -> dict[str, Any]:
            s = holder.get("session")
            acq = s.acquisition if s is not None else None
            return {"component": "excite", "records": acq.sequence if acq else 0, "invalid": acq.invalid.tolist() if acq else [],
                    "dropped_by_stream": s._sinks[-1].dropped if s is not None else 0}

        stream = Stream(zsession, robot.name, "excite", status)
    try:
        with ros2_bridge(args, None if args.dry_run else zsession, robot.name, [j.name for j in robot.joints], ("joint_state", "events")):
            return _excite_run(args, rig, robot, n, simulate, links, trajectory, out, start, console, stream, holder)
    finally:
        if stream is not None:
            stream.close()
        if zsession is not None:
            zsession.close()


def _excite_run(args: argparse.Namespace, rig: Any, robot: Any, n: int, simulate: bool, links: list[int], trajectory: Any, out: Path,
                start: Any, console: Any, stream: Any, holder: dict[str, Any]) -> int:
    import numpy as np

    from armid.daq.excite import ExcitationSession
    from armid.identify import excitation as ex

    from ..experiments import Experiment, design_experiments, run_experiments

    checked, unchecked = (check_rig_budget(rig), "") if args.dry_run else ("", "")
    if start is None:  # the pose the drives report; the drives are let be while this process designs
        try:
            driver, sim = open_rig_driver(rig, args)
            with ExcitationSession(rig, driver, simulator=sim, tracking_limit_rad=args.tracking_limit) as probe:
                start = probe.position
        except BusOpenError as err:
            if not args.dry_run:
                raise
            start, unchecked = rest_pose(rig), "the serial port and the servos" if rig.is_serial else "the bus and the drives"
            console.print(f"armid excite: not checked: {err}; designing from {np.round(start, 4).tolist()} rad "
                          f"instead of the drives' pose", markup=False, highlight=False, soft_wrap=True)
    if trajectory is not None:
        traj, moving = trajectory
        limits = ex.Limits.of(robot)
        p = ex.plan(traj, start, limits, periods=args.periods)
        ex.check_plan(robot, p, rig.period_s, limits)
        design = ex.Design(traj, moving, tuple(range(n)), [], [], 0, float("nan"), float("nan"), {})
        experiments = [Experiment(Path(args.trajectory).stem, design, p)]
    else:
        whole = [("whole", args.periods)] if not links or args.whole else []
        experiments = design_experiments(robot, start, links, whole, rig.period_s, link_frequency_hz=args.frequency or 0.5,
                                          link_periods=args.periods, whole_frequency_hz=args.frequency or 0.2, seed=args.seed,
                                          log=lambda m: console.print(f"  {m}"))
    write_json(out / "designs.json", {e.name: e.design.to_json() for e in experiments})
    if args.dry_run:
        console.print(f"armid excite: dry run, nothing recorded: {len(experiments)} trajector{'y' if len(experiments) == 1 else 'ies'} "
                      f"checked against every limit; checked {checked}" + (f"; not checked: {unchecked}" if unchecked else ""),
                      markup=False, highlight=False, soft_wrap=True)
        return 0
    console.print(f"armid excite: {len(experiments)} trajectories checked against every limit; recording to {out}")
    # designing can keep this process busy for tens of seconds: only now the drives run with it
    driver, sim = open_rig_driver(rig, args)
    with ExcitationSession(rig, driver, simulator=sim, tracking_limit_rad=args.tracking_limit, stream=stream,
                           say=lambda text: console.print(f"armid excite: {text}", markup=False, highlight=False)) as session:
        holder["session"] = session
        console.print(f"armid excite: timing: {session.driver.timing_note}")
        moved = float(np.abs(start - session.position).max())
        if moved > 0.02:
            raise UsageError(f"the arm is {moved:.3f} rad from the pose the trajectories were designed from: it moved; run again")
        from ..live import RateLine, acquisition_counts, enabled

        rate = RateLine()

        def status() -> str:
            acq = session.acquisition
            if acq is None:
                return ""
            records, lost, invalid = acquisition_counts(acq, session.driver)
            faults = 1 if session.control.stop_reason and "fault" in session.control.stop_reason else 0
            return rate(records, lost, invalid, faults, sum(s.dropped for s in acq.sinks))

        reports = run_experiments(session, experiments, out, console, status=status if enabled() else None)
    write_json(out / "runs.json", [r.to_json() for r in reports])
    if driver.waits_note():  # the simulated chain's own stalls, waited through (drivers.line_progress)
        console.print(f"armid excite: {driver.waits_note()}", markup=False, highlight=False)
    for r in reports:
        outcome = "completed" if r.completed else f"STOPPED: {r.stop_reason}"
        gaps = f"{r.waited_through} gap{'s' if r.waited_through != 1 else ''}"
        waited = f"; waited through {gaps} in the frames while this process was not scheduled" if r.waited_through else ""
        console.print(f"{r.name}: {outcome}; {r.records} records in {r.recording}; max tracking error "
                      f"{1000 * max(r.max_tracking_error):.1f} mrad{waited}")
    return 0 if all(r.completed for r in reports) else 1


def load_trajectory(path: str | Path, n_joints: int, period_s: float) -> tuple[Any, tuple[int, ...]]:
    """A trajectory JSON for ``armid excite --trajectory``: a ``designs.json`` entry (or a file
    holding exactly one), ``{"fourier": {...}}``, or the Fourier block itself. Returns the
    trajectory and the moving joints (0-based); every problem names the file and the field."""
    import numpy as np

    from armid.identify.trajectories import FourierTrajectory

    src = str(path)
    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        raise InputFileError(src, "", "no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputFileError(src, "", f"cannot read ({err})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        raise InputFileError(src, f"line {err.lineno} column {err.colno}", f"not valid JSON ({err.msg})") from None
    except RecursionError:
        raise InputFileError(src, "", "nested too deeply to be a trajectory") from None
    where = ""
    if not isinstance(doc, dict):
        raise InputFileError(src, "", f"must be a JSON object with 'fourier' (a designs.json entry), got {type(doc).__name__}")
    if "fourier" not in doc and "q0" not in doc:
        designs = {k: v for k, v in doc.items() if isinstance(v, dict) and "fourier" in v}
        if len(designs) == 1 and len(doc) == 1:
            where, doc = next(iter(designs.items()))
        elif designs:
            raise InputFileError(src, "", f"holds {len(designs)} designs ({', '.join(designs)}); save the one to run in a file of its own")
        else:
            raise InputFileError(src, "fourier", "missing (a designs.json entry or {\"fourier\": {q0, a, b, base_frequency_hz}})")
    f = doc["fourier"] if "fourier" in doc else doc
    fw = f"{where}.fourier" if where else ("fourier" if "fourier" in doc else "")

    def field(key: str) -> str:
        return f"{fw}.{key}" if fw else key

    if not isinstance(f, dict):
        raise InputFileError(src, fw or "fourier", "must be an object with q0, a, b, base_frequency_hz")
    for key in ("q0", "a", "b", "base_frequency_hz"):
        if key not in f:
            raise InputFileError(src, field(key), "missing")

    def array(key: str, ndim: int) -> np.ndarray:
        try:
            a = np.asarray(f[key], dtype=float)
        except (TypeError, ValueError):
            raise InputFileError(src, field(key), f"must be {'a list' if ndim == 1 else 'a list of lists'} of numbers") from None
        if a.ndim != ndim:
            raise InputFileError(src, field(key), f"must be {'a list' if ndim == 1 else 'a list of lists (joint x harmonic)'} of numbers")
        if not np.isfinite(a).all():
            raise InputFileError(src, field(key), "must hold finite numbers only")
        return a

    q0 = array("q0", 1)
    if q0.shape[0] != n_joints:
        raise InputFileError(src, field("q0"), f"{q0.shape[0]} joints, the rig's robot has {n_joints}")
    a, b = array("a", 2), array("b", 2)
    for key, m in (("a", a), ("b", b)):
        if m.shape[0] != n_joints or m.shape[1] < 1:
            raise InputFileError(src, field(key), f"shape {m.shape}, expected ({n_joints}, harmonics >= 1)")
    if a.shape != b.shape:
        raise InputFileError(src, field("b"), f"shape {b.shape} differs from a's {a.shape}")
    hz = f["base_frequency_hz"]
    if isinstance(hz, bool) or not isinstance(hz, int | float) or not math.isfinite(hz):
        raise InputFileError(src, field("base_frequency_hz"), f"must be a finite number, got {hz!r}")
    top = 0.5 / period_s / a.shape[1]
    if not 0 < hz < top:
        raise InputFileError(src, field("base_frequency_hz"), f"must lie in (0, {top:g}) Hz (its {a.shape[1]} harmonics below "
                                                               f"the {0.5 / period_s:g} Hz Nyquist frequency of the rig's period), got {hz}")
    moving_doc = doc.get("moving_joints", list(range(1, n_joints + 1)))
    if (not isinstance(moving_doc, list) or not moving_doc
            or any(isinstance(j, bool) or not isinstance(j, int) or not 1 <= j <= n_joints for j in moving_doc)
            or len(set(moving_doc)) != len(moving_doc)):
        raise InputFileError(src, f"{where}.moving_joints" if where else "moving_joints",
                             f"must be a list of distinct joint numbers 1..{n_joints}, got {moving_doc!r}")
    return FourierTrajectory(q0, a, b, float(hz)), tuple(j - 1 for j in moving_doc)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid excite``: its options."""
    p = sub.add_parser("excite", help="the operator's excitation: designed and checked trajectories, run on the drives, recorded")
    p.add_argument("--rig", required=True, help="rig file")
    p.add_argument("--link", action="append", metavar="J", help="single-link experiment of joint J (repeat; 'all' = Khosla's sequence N..1)")
    p.add_argument("--whole", action="store_true", help="also a whole-arm run (the default without --link)")
    p.add_argument("--trajectory", metavar="JSON", help="run this designed trajectory (designs.json entry or {fourier: ...}) instead of designing")
    p.add_argument("--periods", type=whole_count, default=2, help="periods of each trajectory (default 2)")
    p.add_argument("--frequency", type=positive_number, metavar="HZ", help="base frequency (default 0.5 Hz single-link, 0.2 Hz whole arm)")
    p.add_argument("--tracking-limit", type=positive_number, default=0.2, metavar="RAD", help="quick stop beyond this tracking error (default 0.2 rad)")
    p.add_argument("--seed", type=seed_number, default=0, help="seed of the trajectory optimiser's starts")
    p.add_argument("--out", help="output folder (default runs/<date-time>)")
    p.add_argument("--dry-run", action="store_true", help="check all that needs no drive (every limit, the plan, the bus budget), say what was not; enable nothing")
    p.add_argument("--interface", help="override the rig's python-can interface")
    p.add_argument("--channel", help="override the rig's channel")
    p.add_argument("--simulate", action=argparse.BooleanOptionalAction, default=None,
                   help="run the rig's simulated arm in this process (default: when the bus is virtual)")
    p.add_argument("--no-zenoh", action="store_true", help="do not stream the records and the experiments' events")
    add_zenoh_arguments(p)
    add_ros2_arguments(p)
    p.set_defaults(run=_excite)
