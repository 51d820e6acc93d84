"""Reading recordings (INTERFACES.md 'Recordings') into arrays.

CSV with a header: ``t``, ``q1..qn``, optional ``qd1..qdn`` and ``qdd1..qddn``, and
``tau1..taun`` or ``i1..in`` (scaled by each joint's ``torque_constant``). Also NumPy
``.npz`` archives with ``times, positions, velocities[, accelerations], torques`` (the
layout of the shared KUKA LWR4+ data). Recordings written by ``daq/`` (MCAP) are read there.
"""

from __future__ import annotations

import csv
import json
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import RecordingError
from .robot import Robot
from .spatial import Array

_JOINT_COLUMN = re.compile(r"(q|qd|qdd|tau|i)(\d+)")


@dataclass
class Recording:
    """Raw samples as read: time (n,), joint arrays (n, N); ``qd``/``qdd`` may be absent.

    ``lines`` gives each sample's line in the source file (for messages); ``notes`` says
    what reading did (units converted, columns missing).
    """

    source: str
    t: Array
    q: Array
    tau: Array
    qd: Array | None = None
    qdd: Array | None = None
    lines: Array | None = None
    notes: list[str] = field(default_factory=list)
    torque_held: bool = False  # torque held over the period before each stamp (drive currents)

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])


def read_recording(path: str | Path, robot: Robot) -> Recording:
    """Read one recording for ``robot``; raises :class:`RecordingError` naming what is wrong."""
    path = Path(path)
    if not path.exists():
        raise RecordingError(str(path), "no such file")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return _read_npz(path, robot)
    if suffix == ".mcap":
        return _read_mcap(path, robot)
    return _read_csv(path, robot)


MCAP_TOPIC = "/joint_state"


def _read_mcap(path: Path, robot: Robot) -> Recording:
    """A recording from ``armid record``: positions, drive velocities, measured currents
    times the torque constants; cycles where a joint's frames did not arrive are left out."""
    arrays, _, notes = read_mcap_arrays(path)
    if not arrays:
        raise RecordingError(str(path), "no joint_state record could be read" + (f": {notes[0]}" if notes else ""))
    n = arrays["position"].shape[1]
    if n != robot.n_joints:
        raise RecordingError(str(path), f"{n} joints recorded, robot {robot.name} has {robot.n_joints}")
    valid = arrays["valid"].all(axis=1)
    if not valid.all():
        notes.append(f"left out {int((~valid).sum())} cycles with a joint marked invalid")
    kt = np.array([j.torque_constant for j in robot.joints])
    keep = valid
    t = arrays["t"][keep]
    velocity = _drive_velocity(t, arrays["velocity"][keep], arrays["velocity_fresh"][keep], notes)
    return Recording(str(path), t, arrays["position"][keep], arrays["measured_current"][keep] * kt, velocity, None, None,
                     notes + ["torque = measured current x torque_constant"], torque_held=True)


def _drive_velocity(t: Array, velocity: Array, fresh: Array, notes: list[str]) -> Array | None:
    """The drives' velocity at every sample. A PDO plan may carry it every k-th cycle only;
    it is then interpolated (cubic) through the cycles that carried it: the drives' own
    velocity beats differentiating quantised positions, which needs a low-pass that smears
    the Coulomb step at every reversal (measured: viscous friction 14 % low at 20 Hz)."""
    if fresh.all():
        return velocity
    share = fresh.mean(axis=0)
    if t.size < 8 or share.min() < 0.2:
        notes.append("drive velocity too sparse to use: velocity from the positions")
        return None
    from scipy.interpolate import CubicSpline

    out = velocity.copy()
    for j in range(velocity.shape[1]):
        f = fresh[:, j]
        if not f.all():
            out[:, j] = CubicSpline(t[f], velocity[f, j])(t)
    notes.append(f"drive velocity reported on {100 * share.min():.0f} % of the cycles: interpolated (cubic) onto the others")
    return out


def _read_csv(path: Path, robot: Robot) -> Recording:
    n = robot.n_joints
    try:
        with path.open(newline="") as handle:
            reader = csv.reader(handle)
            header = next(reader, None)
            if header is None:
                raise RecordingError(str(path), "empty file (no header line)")
            header = [h.strip() for h in header]
            rows = list(reader)
    except UnicodeDecodeError as err:
        raise RecordingError(str(path), f"not a text CSV file ({err.reason})") from err
    columns = {name: k for k, name in enumerate(header)}
    if len(columns) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise RecordingError(str(path), f"line 1: duplicate column(s) {', '.join(dup)}")

    def names(prefix: str) -> list[str]:
        return [f"{prefix}{j + 1}" for j in range(n)]

    def has_all(prefix: str) -> bool:
        present = [c in columns for c in names(prefix)]
        if any(present) and not all(present):
            missing = [c for c, p in zip(names(prefix), present) if not p]
            raise RecordingError(str(path), f"line 1: column(s) {', '.join(missing)} missing ({robot.name} has {n} joints)")
        return all(present)

    if "t" not in columns:
        raise RecordingError(str(path), "line 1: no time column 't'")
    if not has_all("q"):
        raise RecordingError(str(path), f"line 1: no position columns q1..q{n}")
    for h in header:
        match = _JOINT_COLUMN.fullmatch(h)
        if match and int(match.group(2)) > n:
            raise RecordingError(str(path), f"line 1: column {h} but {robot.name} has {n} joints")
    use_tau = has_all("tau")
    use_current = has_all("i")
    if not (use_tau or use_current):
        raise RecordingError(str(path), f"line 1: neither torque columns tau1..tau{n} nor current columns i1..i{n}")
    wanted = ["t"] + names("q") + (names("qd") if has_all("qd") else []) + (names("qdd") if has_all("qdd") else [])
    wanted += names("tau") if use_tau else names("i")
    index = [columns[c] for c in wanted]
    data = np.full((len(rows), len(wanted)), np.nan)
    lines = np.arange(2, len(rows) + 2)
    bad_lines: list[int] = []
    for r, row in enumerate(rows):
        if len(row) != len(header):
            if not any(cell.strip() for cell in row):
                continue  # blank line: stays NaN and is dropped as garbage
            bad_lines.append(r + 2)
            continue
        for c, k in enumerate(index):
            try:
                data[r, c] = float(row[k])
            except ValueError:
                pass  # left NaN: reported as a garbage row by preprocessing
    if len(rows) == 0:
        raise RecordingError(str(path), "no data rows after the header")
    notes = []
    if bad_lines:
        notes.append(f"{len(bad_lines)} row(s) with the wrong number of fields (lines {_lines(bad_lines)}); treated as garbage")
    k = 1
    q = data[:, k : k + n]
    k += n
    qd = qdd = None
    if has_all("qd"):
        qd = data[:, k : k + n]
        k += n
    if has_all("qdd"):
        qdd = data[:, k : k + n]
        k += n
    tau = data[:, k : k + n]
    if not use_tau:
        kt = np.array([j.torque_constant for j in robot.joints])
        tau = tau * kt
        notes.append("torque from currents i1..in times each joint's torque_constant")
    return Recording(str(path), data[:, 0], q, tau, qd, qdd, lines, notes)


def _read_npz(path: Path, robot: Robot) -> Recording:
    try:
        archive = np.load(path)
    except Exception as err:  # numpy raises several types for a corrupt archive
        raise RecordingError(str(path), f"not a readable .npz archive ({err})") from err
    with archive:
        keys = set(archive.files)
        for key in ("times", "positions", "torques"):
            if key not in keys:
                raise RecordingError(str(path), f"archive has no '{key}' array (has {', '.join(sorted(keys))})")
        t = np.asarray(archive["times"], dtype=float).reshape(-1)
        arrays = {}
        for key in ("positions", "velocities", "accelerations", "torques"):
            if key in keys:
                a = np.asarray(archive[key], dtype=float)
                if a.ndim != 2 or a.shape != (t.shape[0], robot.n_joints):
                    raise RecordingError(
                        str(path), f"'{key}' has shape {a.shape}, expected ({t.shape[0]}, {robot.n_joints}) for {robot.name}"
                    )
                arrays[key] = a
    return Recording(
        str(path),
        t,
        arrays["positions"],
        arrays["torques"],
        arrays.get("velocities"),
        arrays.get("accelerations"),
        np.arange(t.shape[0]),
        [],
    )


def _lines(lines: list[int], most: int = 5) -> str:
    shown = ", ".join(str(x) for x in lines[:most])
    return shown + (f" and {len(lines) - most} more" if len(lines) > most else "")


def write_csv(path: str | Path, t: Array, columns: dict[str, Array]) -> None:
    """Write ``t`` and (n, N) arrays as ``name1..nameN`` columns (the recording layout)."""
    header = ["t"]
    blocks = [np.asarray(t, dtype=float)[:, None]]
    for prefix, values in columns.items():
        values = np.asarray(values, dtype=float)
        header += [f"{prefix}{j + 1}" for j in range(values.shape[1])]
        blocks.append(values)
    np.savetxt(path, np.hstack(blocks), delimiter=",", header=",".join(header), comments="", fmt="%.10g")


def read_mcap_arrays(path: str | Path) -> tuple[dict[str, Array], dict[str, str], list[str]]:
    """Arrays of the ``/joint_state`` messages, the run metadata, and notes on what was lost."""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Metadata
    from mcap.stream_reader import StreamReader

    path = Path(path)
    rows: list[dict[str, Any]] = []
    metadata: dict[str, str] = {}
    notes: list[str] = []
    channels: dict[int, str] = {}
    complete = False
    with open(path, "rb") as f:
        reader = StreamReader(f)
        try:
            for rec in reader.records:
                if isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                elif isinstance(rec, Message) and channels.get(rec.channel_id) == MCAP_TOPIC:
                    rows.append(json.loads(rec.data))
                elif isinstance(rec, Metadata) and rec.name == "armid.run":
                    metadata = dict(rec.metadata)
            complete = True
        except (McapError, EOFError, struct.error, ValueError, KeyError, IndexError, OSError) as err:
            # a truncated or corrupted tail: keep what came before
            size = path.stat().st_size
            notes.append(f"the file breaks after {len(rows)} records ({type(err).__name__}: {err}; {size} bytes): "
                         f"read what came before, the rest of the run is lost")
    if not complete and not rows:
        notes.append("no record could be read")
    if not rows:
        return {}, metadata, notes
    seq = np.array([r["sequence"] for r in rows])
    gaps = np.flatnonzero(np.diff(seq) != 1)
    if gaps.size:
        missing = int(np.sum(np.diff(seq)[gaps] - 1))
        notes.append(f"{missing} records missing in {gaps.size} gap(s) of the sequence numbers (first after sequence {seq[gaps[0]]})")
    arrays = {
        "sequence": seq,
        "cycle": np.array([r["cycle"] for r in rows]),
        "t": np.array([r["header"]["stamp"]["sec"] + 1e-9 * r["header"]["stamp"]["nsec"] for r in rows]),
        "valid": np.array([r["valid"] for r in rows], bool),
        "position": np.array([r["position"] for r in rows], float),
        "velocity": np.array([r["velocity"] for r in rows], float),
        "velocity_fresh": np.array([r.get("velocity_fresh", [True] * len(r["position"])) for r in rows], bool),
        "commanded_current": np.array([r["commanded_current"] for r in rows], float),
        "measured_current": np.array([r["measured_current"] for r in rows], float),
        "status": np.array([r.get("status", [0] * len(r["position"])) for r in rows], np.int64),
    }
    return arrays, metadata, notes
