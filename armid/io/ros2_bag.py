"""rosbag2 bags as recordings: ``sensor_msgs/msg/JointState`` on one topic, read with ``rosbags``.

A bag is its folder (``metadata.yaml`` beside sqlite3 or MCAP storage) or one of its files alone
(``.db3``; an ``.mcap`` of profile ``ros2`` that armid did not write:
:func:`armid.io.recordings.recording_kind` tells). ``rosbags.rosbag2.Reader`` opens either storage
and gives the messages in the bag's order; their CDR is read by :mod:`armid.io.ros2_cdr`: the
messages of one layout (one publisher's, usually) in place, the first checked against ``rosbags``'
typestore, any others decoded one by one by the typestore (the KUKA LWR4+ recording, 5027
messages: 40 ms; with a second publisher's 1676 messages interleaved, 60 ms, against 360 ms
decoding every message).

What reading does, and says (:func:`read_bag`):

- joints are matched **by name** to the robot file's (drivers publish them in any order, often
  alphabetical); joints the robot file does not list are ignored, and named; a joint it lists
  that the messages lack is an error;
- messages of a second publisher on the topic (another joint set, a gripper's) are left out and
  counted when exactly one joint set holds every joint of the arm; otherwise an error;
- time is the header stamp; the bag's receive time only when every header stamp is zero (said);
  messages stamped zero among stamped ones are left out (said);
- header stamps that go back (two publishers interleaved, a clock that jumped) are an error; a
  message repeated with its stamp and values is kept once (said), one repeating a stamp with
  other values is an error;
- ``effort`` is joint torque unless the robot file says ``effort: current``: then it is motor
  current, and :func:`armid.identify.recordings.with_torque` makes it a torque (the one place a
  current becomes a torque); an effort empty in every message, or NaN throughout for a joint,
  is refused.

Every error is a :class:`RecordingError` naming the bag, the topic and the problem.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from armid.identify.recordings import Recording, with_torque
from armid.identify.robot import Robot
from armid.schema.errors import RecordingError
from armid.schema.joint_state import JOINT_STATE_TYPE, JOINT_STATES_TOPIC
from armid.schema.joint_states import JointStates

from .ros2_cdr import decode, ros2_columns

DEFAULT_TOPIC = JOINT_STATES_TOPIC
"""The topic read unless ``--topic`` says another: ros2_control's ``joint_state_broadcaster``'s."""

METADATA = "metadata.yaml"


def is_bag_folder(path: Path) -> bool:
    """A rosbag2 bag's folder: it holds ``metadata.yaml``."""
    return path.is_dir() and (path / METADATA).is_file()


def is_rosbag2_mcap(path: Path) -> bool:
    """An MCAP file that a ROS 2 tool wrote (rosbag2, ``rosbags``, ...): its header says profile
    ``ros2`` and a library other than armid's (armid's own recordings say ``armid``, and are read
    with their second channel and metadata by :func:`armid.io.recordings.read_mcap_arrays`)."""
    from mcap.records import Header
    from mcap.stream_reader import StreamReader

    try:
        with path.open("rb") as f:
            first = next(iter(StreamReader(f).records), None)
    except Exception:  # not MCAP, or a header that does not parse: armid's reader says what is wrong
        return False
    return isinstance(first, Header) and first.profile == "ros2" and not first.library.startswith("armid")


@dataclass
class _States:
    """The chosen messages of the topic as columns: their numbers on the topic (0-based), the
    receive times (ns), the header stamps, the joint names and the per-joint arrays (messages,
    names); ``velocity``/``effort`` None where the messages carry none."""

    index: NDArray[np.int64]
    received_ns: NDArray[np.int64]
    sec: NDArray[np.int64]
    nanosec: NDArray[np.int64]
    names: tuple[str, ...]
    position: NDArray[np.float64]
    velocity: NDArray[np.float64] | None
    effort: NDArray[np.float64] | None

    def take(self, keep: NDArray[np.bool_]) -> _States:
        def cut(a: Any) -> Any:
            return None if a is None else a[keep]

        return _States(self.index[keep], self.received_ns[keep], self.sec[keep], self.nanosec[keep], self.names, self.position[keep],
                       cut(self.velocity), cut(self.effort))


@dataclass
class _Block:
    """Messages of one layout: their numbers on the topic (0-based), names, stamps and values as
    published (messages, values)."""

    index: NDArray[np.int64]
    names: tuple[str, ...]
    sec: NDArray[np.int64]
    nanosec: NDArray[np.int64]
    position: NDArray[np.float64]
    velocity: NDArray[np.float64]
    effort: NDArray[np.float64]


class _Bag:
    """One bag's topic: what every message of it says is named as ``BAG: topic T: ...``."""

    def __init__(self, path: Path, topic: str) -> None:
        self.path, self.topic = path, topic
        self.storage = ""

    def error(self, problem: str) -> RecordingError:
        return RecordingError(str(self.path), f"topic {self.topic}: {problem}")

    def messages(self) -> tuple[list[int], list[bytes]]:
        """The topic's messages in the bag's order: receive times (ns) and CDR bytes."""
        from rosbags.rosbag2 import Reader

        src = str(self.path)
        if self.path.is_dir() and not (self.path / METADATA).is_file():
            raise RecordingError(src, f"a folder without {METADATA}: not a rosbag2 bag (a bag's folder holds {METADATA} "
                                      "and its .db3 or .mcap files)")
        try:
            with Reader(self.path) as reader:
                self.storage = _storage(self.path)
                on_topic = [c for c in reader.connections if c.topic == self.topic]
                if not on_topic:
                    topics = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
                    raise self.error("not in the bag (it holds " + (", ".join(topics) if topics else "no topic")
                                     + "; --topic chooses another)")
                wrong = sorted({c.msgtype for c in on_topic} - {JOINT_STATE_TYPE})
                if wrong:
                    raise self.error(f"carries {', '.join(wrong)}, not {JOINT_STATE_TYPE}")
                times, data = [], []
                for _, stamp, raw in reader.messages(connections=on_topic):
                    times.append(int(stamp))
                    data.append(bytes(raw))
        except RecordingError:
            raise
        except Exception as err:  # rosbags' ReaderError, sqlite3's and the MCAP reader's errors for a damaged file
            what = " ".join(str(err).split()) or type(err).__name__
            raise self.error(f"the bag cannot be read, cut short or damaged? ({what})") from None
        if not data:
            raise self.error("no message on it")
        return times, data

    def states(self, robot: Robot) -> tuple[_States, list[str]]:
        """The messages of the one publisher that names every joint of ``robot``, as columns."""
        times, data = self.messages()
        received = np.asarray(times, np.int64)
        groups: dict[tuple[str, ...], list[_Block]] = {}
        for block in self._blocks(data):
            groups.setdefault(block.names, []).append(block)
        names = self._publisher({g: [int(k) for b in blocks for k in b.index] for g, blocks in groups.items()}, robot)
        chosen = sorted(groups[names], key=lambda b: int(b.index[0]))
        notes = []
        others = len(data) - sum(b.index.size for b in chosen)
        if others:
            sets = [", ".join(g) or "no names" for g in groups if g != names]
            notes.append(f"{others} message(s) of another publisher on {self.topic} left out (joints {'; '.join(sets[:3])}): "
                         f"read the {len(data) - others} naming every joint of {robot.name}")
        n = len(names)
        for b in chosen:
            for field, values in (("position", b.position), ("velocity", b.velocity), ("effort", b.effort)):
                if values.shape[1] not in ((n,) if field == "position" else (0, n)):
                    raise self.error(f"message {int(b.index[0]) + 1}: '{field}' has {values.shape[1]} values for {n} joint names")
        index = np.concatenate([b.index for b in chosen])
        order = np.argsort(index, kind="stable")

        def column(field: str) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
            """The field's rows in bag order (NaN where a message carried none) and which carried none."""
            rows = [getattr(b, field) if getattr(b, field).shape[1] else np.full((b.index.size, n), np.nan) for b in chosen]
            empty = [np.full(b.index.size, getattr(b, field).shape[1] == 0) for b in chosen]
            return np.concatenate(rows)[order], np.concatenate(empty)[order]

        velocity, no_velocity = column("velocity")
        effort, no_effort = column("effort")
        if no_effort.any() and not no_effort.all():
            notes.append(f"{int(no_effort.sum())} message(s) without effort: their rows left out (first: message "
                         f"{int(index[order][no_effort][0]) + 1})")
        if no_velocity.any() and not no_velocity.all():
            notes.append(f"{int(no_velocity.sum())} message(s) without velocity: velocity from the positions throughout")
        index = index[order]
        return _States(index, received[index], np.concatenate([b.sec for b in chosen])[order], np.concatenate([b.nanosec for b in chosen])[order],
                       names, np.concatenate([b.position for b in chosen])[order], None if no_velocity.any() else velocity,
                       None if no_effort.all() else effort), notes

    def _blocks(self, data: list[bytes]) -> list[_Block]:
        """The messages as blocks of one layout each: those of one byte length read in place
        (:func:`~armid.io.ros2_cdr.ros2_columns`: every message of one publisher, usually), any
        other decoded one by one by the typestore."""
        sizes: dict[int, list[int]] = {}
        for k, raw in enumerate(data):
            sizes.setdefault(len(raw), []).append(k)
        out = []
        for members in sizes.values():
            cols = ros2_columns([data[k] for k in members], JOINT_STATE_TYPE)
            if cols is not None:
                out.append(_Block(np.asarray(members, np.int64), tuple(decode(data[members[0]], JOINT_STATE_TYPE).name),
                                  cols["sec"][:, 0].astype(np.int64), cols["nanosec"][:, 0].astype(np.int64),
                                  *(np.asarray(cols[f], float) for f in ("position", "velocity", "effort"))))
                continue
            for k in members:
                try:
                    m = decode(data[k], JOINT_STATE_TYPE)
                except Exception as err:  # rosbags' SerdeError and the struct errors of a short message
                    raise self.error(f"message {k + 1}: not a {JOINT_STATE_TYPE} in CDR ({' '.join(str(err).split())})") from None
                out.append(_Block(np.array([k], np.int64), tuple(m.name), np.array([m.header.stamp.sec], np.int64),
                                  np.array([m.header.stamp.nanosec], np.int64),
                                  *(np.asarray(getattr(m, f), float).reshape(1, -1) for f in ("position", "velocity", "effort"))))
        return out

    def _publisher(self, groups: dict[tuple[str, ...], list[int]], robot: Robot) -> tuple[str, ...]:
        """The one joint set among the messages' that names every joint of ``robot``."""
        wanted = {j.name for j in robot.joints}
        full = [names for names in groups if wanted <= set(names)]
        if len(full) == 1:
            return self._check_joints(full[0], robot)
        if len(full) > 1:
            shown = "; ".join(f"{len(groups[g])} naming {', '.join(g)}" for g in full[:2])
            raise self.error(f"two publishers name every joint of {robot.name} ({shown}): record one, or choose its topic with --topic")
        together = set().union(*map(set, groups))
        if wanted <= together:
            raise self.error(f"the joints of {robot.name} are split across messages ({'; '.join(', '.join(g) for g in list(groups)[:3])}): "
                             "armid reads one message a cycle with every joint")
        return self._check_joints(max(groups, key=lambda g: len(groups[g])), robot)

    def _check_joints(self, names: tuple[str, ...], robot: Robot) -> tuple[str, ...]:
        """``names`` when they name every joint of ``robot`` once, else the error that says which do not."""
        missing = [j.name for j in robot.joints if j.name not in names]
        if missing:
            raise self.error(f"joint(s) {', '.join(missing)} of {robot.source or robot.name} missing (the messages name "
                             f"{', '.join(names) or 'no joint'})")
        twice = sorted({x for x in names if names.count(x) > 1})
        if twice:
            raise self.error(f"joint {twice[0]} named twice in one message")
        return names


def _storage(path: Path) -> str:
    """The bag's storage, for the notes: by its files' names (``.db3``: sqlite3)."""
    files = [p.name for p in path.iterdir()] if path.is_dir() else [path.name]
    return "sqlite3" if any(".db3" in f for f in files) else "mcap"


def _seconds(sec: NDArray[np.int64], nanosec: NDArray[np.int64]) -> NDArray[np.float64]:
    """A ROS 2 time as seconds, as armid reads every ROS 2 stamp (``sec + 1e-9 * nanosec``)."""
    return sec.astype(float) + 1e-9 * nanosec.astype(float)


def _stamped(bag: _Bag, s: _States, notes: list[str]) -> tuple[_States, NDArray[np.float64]]:
    """The messages kept and their times (see the module docstring: header stamps, zero stamps, order)."""
    zero = (s.sec == 0) & (s.nanosec == 0)
    if zero.all():
        notes.append(f"every header stamp on {bag.topic} is zero: timed by the bag's receive time instead (it carries the "
                     "transport's delay and jitter)")
        t = _seconds(s.received_ns // 1_000_000_000, s.received_ns % 1_000_000_000)
    else:
        if zero.any():
            notes.append(f"{int(zero.sum())} message(s) with a zero header stamp among stamped ones left out (first: message "
                         f"{int(s.index[zero][0]) + 1})")
            s = s.take(~zero)
        t = _seconds(s.sec, s.nanosec)
    step = np.diff(t)
    back = np.flatnonzero(step < 0)
    if back.size:
        k = int(back[0])
        raise bag.error(f"header stamps go back {back.size} time(s) (first at message {int(s.index[k + 1]) + 1}: {t[k]:.9f} -> "
                        f"{t[k + 1]:.9f} s): a second publisher interleaved, or a clock that jumped; record one publisher, "
                        "or choose its topic with --topic")
    same = np.flatnonzero(step == 0)
    if same.size:
        arrays = [a for a in (s.position, s.velocity, s.effort) if a is not None]
        differ = [k for k in same if any(not np.array_equal(a[k], a[k + 1], equal_nan=True) for a in arrays)]
        if differ:
            k = int(differ[0])
            raise bag.error(f"messages {int(s.index[k]) + 1} and {int(s.index[k + 1]) + 1} are both stamped {t[k]:.9f} s with "
                            "different values: a second publisher on the same clock? record one publisher")
        notes.append(f"{same.size} message(s) repeated with their stamp and values: kept once")
        keep = np.ones(t.size, bool)
        keep[same + 1] = False
        s, t = s.take(keep), t[keep]
    return s, t


def read_bag(path: str | Path, robot: Robot, topic: str | None = None) -> Recording:
    """The JointState messages on ``topic`` (default :data:`DEFAULT_TOPIC`) of a rosbag2 bag
    (its folder, or a ``.db3``/``.mcap`` file of it) as a :class:`Recording` of ``robot``'s
    joints: positions, velocities where published, torque (module docstring). ``lines`` are the
    messages' numbers on the topic, from 1. Raises :class:`RecordingError` naming the bag, the
    topic and the problem."""
    path = Path(path)
    bag = _Bag(path, topic or DEFAULT_TOPIC)
    s, notes = bag.states(robot)
    s, t = _stamped(bag, s, notes)
    if s.effort is None:
        raise bag.error(f"effort is empty in every message ({len(s.index)} messages): the publisher sends no effort "
                        "(a joint_state_broadcaster without an effort interface?): nothing to identify from")
    column = [s.names.index(j.name) for j in robot.joints]
    effort = s.effort[:, column]
    dead = [robot.joints[k].name for k in np.flatnonzero(np.isnan(effort).all(axis=0))]
    if dead:
        raise bag.error(f"effort is NaN in every message for joint(s) {', '.join(dead)}: nothing to identify from")
    extra = [x for x in s.names if x not in {j.name for j in robot.joints}]
    said = [f"{bag.topic}: {t.size} {JOINT_STATE_TYPE} messages ({bag.storage}), joints matched by name"]
    if extra:
        said.append(f"joint(s) {', '.join(extra)} on {bag.topic} are not in {robot.name}'s robot file: ignored")
    notes = said + notes
    q = s.position[:, column]
    blind = [robot.joints[k].name for k in np.flatnonzero(np.isnan(q).all(axis=0))]
    if blind:
        raise bag.error(f"position is NaN in every message for joint(s) {', '.join(blind)}")
    qd = None if s.velocity is None else s.velocity[:, column]
    if qd is not None and np.isnan(qd).all(axis=0).any():
        unknown = [robot.joints[k].name for k in np.flatnonzero(np.isnan(qd).all(axis=0))]
        notes.append(f"velocity is NaN in every message for joint(s) {', '.join(unknown)}: velocity from the positions throughout")
        qd = None
    if robot.effort == "current":
        nan = np.full(q.shape, np.nan)
        states, how = with_torque(JointStates.from_columns({
            "sequence": s.index, "cycle": s.index, "t": t, "valid": np.ones(q.shape, bool), "position": q,
            "velocity": nan if qd is None else qd, "commanded_current": nan, "measured_current": effort}), robot)
        tau = states.torque
        notes.append(f"effort read as motor current (the robot file's effort: current); {how}")
    else:
        tau = effort
    return Recording(str(path), t, q, tau, qd, None, s.index + 1, notes, torque_held=False, torque_from_current=robot.effort == "current")
