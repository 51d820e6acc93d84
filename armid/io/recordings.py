"""Reading recordings (INTERFACES.md 'Recordings') into arrays: the I/O layer.

CSV with a header: ``t``, ``q1..qn``, optional ``qd1..qdn`` and ``qdd1..qddn``, and
``tau1..taun`` or ``i1..in`` (scaled by each joint's ``torque_constant``). Also NumPy
``.npz`` archives with ``times, positions, velocities[, accelerations], torques`` (the
layout of the shared KUKA LWR4+ data). MCAP recordings from ``armid record``: the ROS 2
layout (``/joint_states`` and ``/armid/joint_state_extra`` in CDR, decoded with
``mcap_ros2`` against armid's own ``ros2msg`` schemas; the torque as the driver recorded it)
and the JSON layout written before it (``/joint_state``; torque = measured current times the
robot's torque constants). Every chunk's CRC is checked, reading resumes after a bad chunk,
and the notes say what was lost (:func:`read_mcap_arrays`).
"""

from __future__ import annotations

import csv
import io
import json
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from armid.identify.errors import RecordingError
from armid.identify.recordings import Recording, recording_of
from armid.identify.robot import Robot
from armid.schema import Array
from armid.schema.joint_state import EXTRA_TOPIC, EXTRA_TYPE, JOINT_STATE_TYPE, JOINT_STATES_TOPIC, ros2_columns
from armid.schema.joint_states import JointStates

from .ros2_cdr import cdr_decoders, decoded_columns, same_length

_JOINT_COLUMN = re.compile(r"(q|qd|qdd|tau|i)(\d+)")


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
RUN_END = "armid.run_end"
"""The metadata record in which the recorder (``armid.daq.recorder``) says how the run ended."""


def _read_mcap(path: Path, robot: Robot) -> Recording:
    """A recording from ``armid record``: positions, drive velocities, measured currents
    times the torque constants; cycles where a joint's frames did not arrive are left out.

    The run's metadata must name ``robot`` (a recording of one arm identified as another is
    refused). Records whose time stamp does not come after every earlier one (a clock step
    back on the bench) are left out and said so: the sequence numbers give the order."""
    arrays, metadata, notes = read_mcap_arrays(path)
    if not arrays:
        raise RecordingError(str(path), "no joint_state record could be read" + (f": {notes[0]}" if notes else ""))
    recorded = metadata.get("robot")
    if recorded is not None and recorded != robot.name:
        raise RecordingError(str(path), f"metadata armid.run: recorded on robot {recorded!r}, but --robot {robot.source} "
                                        f"describes {robot.name!r}")
    if recorded is None:
        notes.append(f"its metadata names no robot (no armid.run record): read as {robot.name}, on the word of --robot "
                     f"{robot.source} alone")
    return recording_of(JointStates.from_columns(arrays), robot, str(path), notes, run_period(metadata), stop_line(metadata))


def stop_line(metadata: dict[str, str]) -> str | None:
    """The line that stopped the run, from its recording's metadata (``armid.run_end``, which
    :func:`read_mcap_arrays` merges in): None when the run completed or the file does not say
    (a recorder killed before it closed the file, a recording made before the record existed)."""
    stop = metadata.get("stop")
    if stop:
        return stop
    if metadata.get("completed") == "false":
        return "stopped (no reason recorded)"
    return None


def run_period(metadata: dict[str, str]) -> float | None:
    """The rig's SYNC period the run's metadata gives (``armid excite`` writes it), else None."""
    try:
        value = float(metadata["period_s"])
    except (KeyError, TypeError, ValueError):
        return None
    return value if np.isfinite(value) and value > 0 else None


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
    return Recording(str(path), data[:, 0], q, tau, qd, qdd, lines, notes, torque_from_current=not use_tau)


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
        try:
            t = np.asarray(archive["times"], dtype=float).reshape(-1)
        except (ValueError, TypeError) as err:
            raise RecordingError(str(path), f"'times' is not an array of numbers ({err})") from None
        arrays = {}
        for key in ("positions", "velocities", "accelerations", "torques"):
            if key in keys:
                try:
                    a = np.asarray(archive[key], dtype=float)
                except (ValueError, TypeError) as err:
                    raise RecordingError(str(path), f"'{key}' is not an array of numbers ({err})") from None
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
        torque_from_current=False,  # 'torques': joint torque as measured (the KUKA LWR4+'s joint torque sensors)
    )


def _lines(lines: list[int], most: int = 5) -> str:
    shown = ", ".join(str(x) for x in lines[:most])
    return shown + (f" and {len(lines) - most} more" if len(lines) > most else "")


def write_csv(path: str | Path, t: Array, columns: dict[str, Array]) -> None:
    """Write ``t`` and (n, N) arrays as ``name1..nameN`` columns (the recording layout).

    Each stamp is written as the shortest text that reads back as the same float: a log
    stamped in epoch seconds (1.46e9 s) needs 16 significant digits to keep its
    milliseconds, and a prediction must be found at its input's own stamp."""
    header = ["t"]
    blocks = []
    for prefix, values in columns.items():
        values = np.asarray(values, dtype=float)
        header += [f"{prefix}{j + 1}" for j in range(values.shape[1])]
        blocks.append(values)
    stamps = [repr(x) for x in np.asarray(t, dtype=float).tolist()]
    body = io.StringIO()
    np.savetxt(body, np.hstack(blocks), delimiter=",", fmt="%.10g")
    rows = body.getvalue().splitlines()
    if len(rows) != len(stamps):
        raise ValueError(f"{path}: {len(stamps)} stamps for {len(rows)} rows")
    with open(path, "w") as f:
        f.write(",".join(header) + "\n")
        f.writelines(f"{ts},{row}\n" for ts, row in zip(stamps, rows))


MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x02, 0x03, 0x04, 0x05, 0x06
_OP_CHUNK_INDEX, _OP_STATISTICS, _OP_METADATA, _OP_DATA_END = 0x08, 0x0B, 0x0C, 0x0F
_KNOWN_OPS = set(range(0x01, 0x10))
_JOINT_FIELDS = ("position", "velocity", "commanded_current", "measured_current")


@dataclass
class _Loss:
    """A stretch of the file that could not be read: where, why, and the records around it."""

    offset: int
    end: int
    why: str
    start_time_ns: int | None = None  # the chunk header's own span, when it could be read
    end_time_ns: int | None = None


class _McapScan:
    """Every record of an MCAP file that can be trusted, read past bad chunks.

    Each chunk's CRC is checked; a chunk that fails it, or whose records do not parse, is
    left out whole. Reading resumes at the next chunk: at the offset the summary's chunk
    index gives when the file has an intact summary, else at the next byte position that
    holds a whole chunk with a matching CRC.
    """

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.channels: dict[int, str] = {}
        self.messages: list[tuple[int, bytes]] = []  # (file offset of the chunk or record, payload)
        self.cdr: dict[str, list[tuple[int, bytes]]] = {JOINT_STATES_TOPIC: [], EXTRA_TOPIC: []}  # (offset, whole message record)
        self.metadata: dict[str, str] = {}
        self.end: dict[str, str] = {}  # armid.run_end: how the run ended
        self.losses: list[_Loss] = []
        self.data_end = False  # the data section ended as written (DataEnd record reached)
        self.cut_at: int | None = None  # the file ends inside a record at this offset
        self.expected_messages: int | None = None  # from the summary's statistics
        self.chunk_starts: list[int] = []  # from the summary's chunk index
        self.summary = False
        self.orphans: dict[int, list[tuple[int, bytes]]] = {}  # messages (whole records) of a channel whose record was not read
        self.adopted: int | None = None
        self._read_summary()
        self._read_data()
        self._adopt_orphans()

    # -- framing -------------------------------------------------------------------------
    def _record(self, pos: int) -> tuple[int, int] | None:
        """(opcode, content length) of a whole record at ``pos``, or None past the end."""
        if pos + 9 > len(self.data):
            return None
        op = self.data[pos]
        (length,) = struct.unpack_from("<Q", self.data, pos + 1)
        if pos + 9 + length > len(self.data):
            return None
        return op, length

    def _read_summary(self) -> None:
        """Chunk offsets and the message count from the summary, if the footer and its CRC hold."""
        import zlib

        d = self.data
        tail = len(d) - len(MCAP_MAGIC) - 29  # footer: opcode, length 20, two u64 and a u32
        if tail < len(MCAP_MAGIC) or not d.endswith(MCAP_MAGIC) or d[tail] != _OP_FOOTER:
            return
        summary_start, _, crc = struct.unpack_from("<QQI", d, tail + 9)
        if not len(MCAP_MAGIC) <= summary_start <= tail:
            return
        if crc and zlib.crc32(d[summary_start : tail + 9 + 16]) != crc:
            return
        pos = summary_start
        starts, count = [], None
        while pos < tail:
            rec = self._record(pos)
            if rec is None:
                return
            op, length = rec
            body = pos + 9
            if op == _OP_CHUNK_INDEX and length >= 32:
                starts.append(struct.unpack_from("<Q", d, body + 16)[0])
            elif op == _OP_STATISTICS and length >= 46:
                count = struct.unpack_from("<Q", d, body)[0]
            elif op == _OP_CHANNEL:
                self._channel(d[body : body + length])
            pos = body + length
        self.summary = True
        self.chunk_starts = sorted(s for s in starts if s < len(d))
        self.expected_messages = count

    def _channel(self, content: bytes) -> None:
        from io import BytesIO

        from mcap.data_stream import ReadDataStream
        from mcap.records import Channel

        try:
            ch = Channel.read(ReadDataStream(BytesIO(content)))
        except Exception:  # a garbled channel record: its messages stay unread, and are counted lost
            return
        self.channels[ch.id] = ch.topic

    def _read_data(self) -> None:
        d = self.data
        pos = len(MCAP_MAGIC)
        while pos < len(d):
            rec = self._record(pos)
            if rec is None or rec[0] not in _KNOWN_OPS:
                nxt = self._next_chunk(pos + 1)
                if nxt is not None:
                    self.losses.append(_Loss(pos, nxt, "unreadable record framing"))
                    pos = nxt
                    continue
                if rec is None and (pos + 9 > len(d) or d[pos] in _KNOWN_OPS):
                    self._cut(pos)  # the file ends inside this record: written no further
                else:
                    self.losses.append(_Loss(pos, len(d), "unreadable record framing"))
                return
            op, length = rec
            body = pos + 9
            if op == _OP_CHUNK:
                self._chunk(pos, body, length)
            elif op == _OP_CHANNEL:
                self._channel(d[body : body + length])
            elif op == _OP_MESSAGE:
                self._message(pos, d[body : body + length])
            elif op == _OP_METADATA:
                self._metadata(body, length)
            elif op == _OP_DATA_END:
                self.data_end = True
                return
            elif op == _OP_FOOTER:
                return
            pos = body + length

    def _cut(self, pos: int) -> None:
        """The file ends inside the record at ``pos``: note it, with a cut chunk's time span."""
        self.cut_at = pos
        loss = _Loss(pos, len(self.data), "the file ends inside a record")
        if self.data[pos] == _OP_CHUNK and pos + 9 + 16 <= len(self.data):
            loss.why = "the file ends inside a chunk"
            loss.start_time_ns, loss.end_time_ns = struct.unpack_from("<QQ", self.data, pos + 9)
        self.losses.append(loss)

    def _chunk_fields(self, pos: int) -> tuple[int, int, int, int, str, int, int] | None:
        """(start, end, uncompressed size, CRC, compression, records offset, records length) of
        a whole chunk at ``pos`` whose framing is consistent, else None."""
        rec = self._record(pos)
        if rec is None or rec[0] != _OP_CHUNK or rec[1] < 40:
            return None
        body, length = pos + 9, rec[1]
        t0, t1, size, crc, clen = struct.unpack_from("<QQQII", self.data, body)
        if clen > 16 or 36 + clen + 8 > length:
            return None
        try:
            compression = self.data[body + 32 : body + 32 + clen].decode()
        except UnicodeDecodeError:
            return None
        (rlen,) = struct.unpack_from("<Q", self.data, body + 32 + clen)
        if 40 + clen + rlen != length or compression not in ("", "lz4", "zstd"):
            return None
        return t0, t1, size, crc, compression, body + 40 + clen, rlen

    def _next_chunk(self, after: int) -> int | None:
        """Where reading resumes: the next chunk the summary lists, or the next whole chunk
        with a consistent frame found byte by byte."""
        if self.summary:
            return next((s for s in self.chunk_starts if s >= after), None)
        pos = after
        while True:
            pos = self.data.find(bytes([_OP_CHUNK]), pos)
            if pos < 0:
                return None
            fields = self._chunk_fields(pos)
            if fields is not None and (fields[3] == 0 or self._crc_ok(fields)):
                return pos
            pos += 1

    def _crc_ok(self, fields: tuple[int, int, int, int, str, int, int]) -> bool:
        import zlib

        _, _, _, crc, compression, off, rlen = fields
        raw = self._decompress(compression, self.data[off : off + rlen], fields[2])
        return raw is not None and (crc == 0 or zlib.crc32(raw) == crc)

    @staticmethod
    def _decompress(compression: str, data: bytes, size: int) -> bytes | None:
        try:
            if compression == "zstd":
                import zstandard

                return bytes(zstandard.decompress(data, size))
            if compression == "lz4":
                import lz4.frame

                return bytes(lz4.frame.decompress(data))
        except Exception:  # a corrupt compressed chunk: its records are lost
            return None
        return data

    def _chunk(self, pos: int, body: int, length: int) -> None:
        import zlib

        fields = self._chunk_fields(pos)
        if fields is None:
            self.losses.append(_Loss(pos, body + length, "a chunk whose header is garbled"))
            return
        t0, t1, size, crc, compression, off, rlen = fields
        raw = self._decompress(compression, self.data[off : off + rlen], size)
        if raw is None or (crc and zlib.crc32(raw) != crc):
            self.losses.append(_Loss(pos, body + length, "a chunk that fails its CRC" if raw is not None else "a chunk that does not decompress",
                                     t0, t1))
            return
        inner: list[tuple[int, bytes]] = []
        k = 0
        while k < len(raw):
            if k + 9 > len(raw):
                break
            op = raw[k]
            (n,) = struct.unpack_from("<Q", raw, k + 1)
            if k + 9 + n > len(raw):
                break
            if op == _OP_MESSAGE:
                inner.append((pos, raw[k + 9 : k + 9 + n]))
            elif op == _OP_CHANNEL:
                self._channel(raw[k + 9 : k + 9 + n])
            k += 9 + n
        if k != len(raw):
            self.losses.append(_Loss(pos, body + length, "a chunk whose records do not parse", t0, t1))
            return
        for _, payload in inner:
            self._message(pos, payload)

    def _message(self, pos: int, content: bytes) -> None:
        if len(content) < 22:
            return
        (channel,) = struct.unpack_from("<H", content, 0)
        topic = self.channels.get(channel)
        if topic == MCAP_TOPIC:
            self.messages.append((pos, content[22:]))
        elif topic in self.cdr:
            self.cdr[topic].append((pos, content))
        elif topic is None:
            self.orphans.setdefault(channel, []).append((pos, content))

    def _adopt_orphans(self) -> None:
        """The channel records went down with a bad chunk (they are written once, in the first
        chunk, and again only in the summary). A JSON recording: when no ``/joint_state``
        channel was seen and every message belongs to one unknown channel, those are taken as
        ``/joint_state``. A ROS 2 recording: when neither of its channels was seen, the two
        unknown channels are told apart by which message type their first message decodes as."""
        known = set(self.channels.values())
        if MCAP_TOPIC in known or JOINT_STATES_TOPIC in known or EXTRA_TOPIC in known:
            return
        if len(self.orphans) == 1:
            channel, messages = next(iter(self.orphans.items()))
            self.messages = [(pos, content[22:]) for pos, content in messages]
            self.adopted = channel
        elif len(self.orphans) == 2:
            decoders = cdr_decoders()
            found: dict[str, int] = {}
            for channel, messages in self.orphans.items():
                for topic, kind in ((JOINT_STATES_TOPIC, JOINT_STATE_TYPE), (EXTRA_TOPIC, EXTRA_TYPE)):
                    try:
                        m = decoders[kind](messages[0][1][22:])
                        sizes = ({len(m.name), len(m.position), len(m.velocity), len(m.effort)} if kind == JOINT_STATE_TYPE else
                                 {len(m.valid), len(m.measured_current), len(m.commanded_current), len(m.statusword)})
                    except Exception:  # not this type
                        continue
                    if len(sizes) == 1 and 0 not in sizes:
                        found.setdefault(topic, channel)
                        break
            if len(set(found.values())) == 2 and len(found) == 2:
                for topic, channel in found.items():
                    self.cdr[topic] = self.orphans[channel]
                self.adopted = found[EXTRA_TOPIC]

    def _metadata(self, body: int, length: int) -> None:
        from io import BytesIO

        from mcap.data_stream import ReadDataStream
        from mcap.records import Metadata

        try:
            rec = Metadata.read(ReadDataStream(BytesIO(self.data[body : body + length])))
        except Exception:
            self.losses.append(_Loss(body - 9, body + length, "an unreadable metadata record"))
            return
        if rec.name == "armid.run":
            self.metadata = dict(rec.metadata)
        elif rec.name == RUN_END:
            self.end = dict(rec.metadata)

    def run_metadata(self) -> dict[str, str]:
        """``armid.run`` with ``armid.run_end``'s keys (``completed``, ``stop``, ``stop_cycle``,
        ``records``) when the recorder wrote how the run ended."""
        return {**self.metadata, **self.end}


def _check_message(msg: Any, k: int, n: int | None, source: str) -> int:
    """Refuse a ``/joint_state`` message (CRC intact, so written so) without the fields and
    lengths identification reads; returns its joint count."""

    def bad(problem: str) -> RecordingError:
        seq = msg.get("sequence") if isinstance(msg, dict) else None
        return RecordingError(source, f"/joint_state message {k}" + (f" (sequence {seq})" if isinstance(seq, int) else "") + f": {problem}")

    if not isinstance(msg, dict):
        raise bad(f"must be a JSON object, got {type(msg).__name__}")
    for key in ("sequence", "cycle"):
        if key not in msg:
            raise bad(f"'{key}' missing")
        if isinstance(msg[key], bool) or not isinstance(msg[key], int):
            raise bad(f"'{key}' must be an integer, got {msg[key]!r}")
    stamp = msg.get("header", {}).get("stamp") if isinstance(msg.get("header"), dict) else None
    if not isinstance(stamp, dict) or not all(isinstance(stamp.get(x), int) and not isinstance(stamp.get(x), bool) for x in ("sec", "nsec")):
        raise bad("'header.stamp' must hold integers 'sec' and 'nsec'")
    position = msg.get("position")
    if not isinstance(position, list):
        raise bad(f"'position' must be a list of numbers, got {position!r}"[:200])
    m = len(position) if n is None else n
    for key in _JOINT_FIELDS:
        v = msg.get(key)
        if v is None:
            raise bad(f"'{key}' missing")
        if not isinstance(v, list) or any(isinstance(x, bool) or not isinstance(x, int | float) for x in v):
            raise bad(f"'{key}' must be a list of numbers")
        if len(v) != m:
            raise bad(f"'{key}' has {len(v)} values, the recording's other messages {m}")
    for key, kind in (("valid", bool), ("velocity_fresh", bool), ("status", int)):
        v = msg.get(key)
        if v is None and key != "valid":
            continue
        if not isinstance(v, list) or len(v) != m or any(not isinstance(x, kind) for x in v):
            raise bad(f"'{key}' must be a list of {m} {kind.__name__}s")
    return m


def read_mcap_arrays(path: str | Path) -> tuple[dict[str, Array], dict[str, str], list[str]]:
    """Arrays of the ``/joint_state`` messages, the run metadata (``armid.run``, with
    ``armid.run_end``'s ``completed``, ``stop``, ``stop_cycle`` and ``records`` where the
    recorder said how the run ended: :func:`stop_line`), and notes on what was lost.

    Chunks that fail their CRC are left out and reading goes on after them (see
    :class:`_McapScan`); the notes say how many records and seconds each loss cost and where.
    A message that passed its CRC but lacks a field is refused (:class:`RecordingError`).
    """
    path = Path(path)
    src = str(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise RecordingError(src, f"cannot read ({err.strerror or err})") from None
    if not data.startswith(MCAP_MAGIC):
        raise RecordingError(src, "not an MCAP file (its first bytes are not the MCAP magic)")
    scan = _McapScan(data)
    if scan.cdr[JOINT_STATES_TOPIC] or scan.cdr[EXTRA_TOPIC]:
        return _cdr_arrays(scan, src, len(data))
    rows: list[dict[str, Any]] = []
    offsets: list[int] = []
    n: int | None = None
    for k, (pos, payload) in enumerate(scan.messages):
        try:
            msg = json.loads(payload)
        except (ValueError, RecursionError):
            raise RecordingError(src, f"/joint_state message {k} (in the chunk at byte {pos}): not valid JSON") from None
        n = _check_message(msg, k, n, src)
        rows.append(msg)
        offsets.append(pos)
    seq = np.array([r["sequence"] for r in rows], dtype=np.int64)
    t = np.array([r["header"]["stamp"]["sec"] + 1e-9 * r["header"]["stamp"]["nsec"] for r in rows])
    notes = _loss_notes(scan, seq, t, offsets, len(data))
    if scan.adopted is not None and rows:
        notes.append(f"the /joint_state channel record was lost: the {len(rows)} messages of channel {scan.adopted}, "
                     "the only channel left, were read as /joint_state")
    if not rows:
        if not notes:
            notes.append("no /joint_state record in the file")
        return {}, scan.run_metadata(), notes
    arrays = {
        "sequence": seq,
        "cycle": np.array([r["cycle"] for r in rows]),
        "t": t,
        "valid": np.array([r["valid"] for r in rows], bool),
        "position": np.array([r["position"] for r in rows], float),
        "velocity": np.array([r["velocity"] for r in rows], float),
        "velocity_fresh": np.array([r.get("velocity_fresh", [True] * len(r["position"])) for r in rows], bool),
        "commanded_current": np.array([r["commanded_current"] for r in rows], float),
        "measured_current": np.array([r["measured_current"] for r in rows], float),
        "status": np.array([r.get("status", [0] * len(r["position"])) for r in rows], np.int64),
    }
    return arrays, scan.run_metadata(), notes


def _cdr_arrays(scan: _McapScan, src: str, size: int) -> tuple[dict[str, Array], dict[str, str], list[str]]:
    """A ROS 2 recording: each cycle's ``/joint_states`` and ``/armid/joint_state_extra``
    messages, paired by their MCAP log time and sequence number. A cycle with one of its
    two messages lost is lost (said among the gaps)."""
    header = struct.Struct("<HIQ")  # channel id, sequence, log time of a message record

    def by_key(topic: str) -> dict[tuple[int, int], int]:  # the last message of a key, in the order keys first came
        index = {}
        for k, (_, content) in enumerate(scan.cdr[topic]):
            _, seq, log_time = header.unpack_from(content)
            index[(log_time, seq)] = k
        return index

    states, extras = by_key(JOINT_STATES_TOPIC), by_key(EXTRA_TOPIC)
    pairs = np.array([(extras[key], states[key]) for key in extras if key in states], np.int64).reshape(-1, 2)
    s_msgs = [scan.cdr[JOINT_STATES_TOPIC][k][1][22:] for k in pairs[:, 1]]
    e_msgs = [scan.cdr[EXTRA_TOPIC][k][1][22:] for k in pairs[:, 0]]
    offsets = np.array([scan.cdr[EXTRA_TOPIC][k][0] for k in pairs[:, 0]], np.int64)
    cols = same_length(ros2_columns(s_msgs, JOINT_STATE_TYPE), ros2_columns(e_msgs, EXTRA_TYPE))
    if cols is None:  # messages of different layouts: one by one, each checked
        cols = decoded_columns(scan.cdr, pairs, src)
    t = cols["sec"][:, 0] + 1e-9 * cols["nanosec"][:, 0]
    notes = _loss_notes(scan, cols["sequence"][:, 0].astype(np.int64), t, offsets, size)
    if scan.adopted is not None and len(t):
        notes.append(f"the channel record was lost for both {JOINT_STATES_TOPIC} and {EXTRA_TOPIC}: the {len(t)} cycles of "
                     "the two channels left were read by the message types they decode as")
    if not len(t):
        if not notes:
            notes.append(f"no {JOINT_STATES_TOPIC} record in the file")
        return {}, scan.run_metadata(), notes
    arrays = {
        "sequence": cols["sequence"][:, 0].astype(np.int64),
        "cycle": cols["cycle"][:, 0].astype(np.int64),
        "t": t,
        "valid": cols["valid"].astype(bool),
        "position": cols["position"].astype(float),
        "velocity": cols["velocity"].astype(float),
        "velocity_fresh": cols["velocity_fresh"].astype(bool),
        "commanded_current": cols["commanded_current"].astype(float),
        "measured_current": cols["measured_current"].astype(float),
        "status": cols["statusword"].astype(np.int64),
        "torque": cols["effort"].astype(float),
    }
    return arrays, scan.run_metadata(), notes


def _loss_notes(scan: _McapScan, seq: Any, t: Any, offsets: Any, size: int) -> list[str]:
    """What was lost, in records and seconds, and where: one note per unreadable stretch,
    one per gap in the sequence numbers that no unreadable stretch explains. ``seq``, ``t``
    and ``offsets`` (in the file) are the records read, in file order."""
    notes: list[str] = []
    seq, t = np.asarray(seq, np.int64), np.asarray(t, float)
    pos = np.asarray(offsets, dtype=np.int64)
    period = float(np.median(np.diff(t))) if t.size > 2 else float("nan")
    explained: set[int] = set()
    for loss in scan.losses:
        before = int(np.searchsorted(pos, loss.offset)) - 1  # last record read before the stretch
        after = before + 1
        where = f"bytes {loss.offset}..{loss.end} of {size}"
        if after < seq.size and loss.end < size:
            explained.add(before)
            if before >= 0:
                lost = int(seq[after] - seq[before] - 1)
                if lost == 0:
                    notes.append(f"{loss.why} ({where}): no record lost")
                    continue
                seconds = float(t[after] - t[before]) - (period if np.isfinite(period) else 0.0)
                span = f"sequence {seq[before] + 1}..{seq[after] - 1}, between t {t[before]:.4f} and {t[after]:.4f} s"
            else:
                lost = int(seq[after] - 0)
                seconds = lost * period if np.isfinite(period) else float("nan")
                span = f"sequence 0..{seq[after] - 1}, before t {t[after]:.4f} s"
            notes.append(f"{loss.why} ({where}): {lost} records ({seconds:.3f} s; {span}) lost; reading resumed after it")
        else:
            tail = f"after sequence {seq[-1]} (t {t[-1]:.4f} s)" if seq.size else "from the start"
            if scan.expected_messages is not None:
                lost = scan.expected_messages - seq.size - sum(int(seq[i + 1] - seq[i] - 1) for i in range(seq.size - 1))
                amount = f"{lost} records ({lost * period:.3f} s)" if np.isfinite(period) else f"{lost} records"
            elif loss.start_time_ns is not None and np.isfinite(period):
                seconds = max(0.0, (loss.end_time_ns - loss.start_time_ns) * 1e-9) + period  # type: ignore[operator]
                amount = f"a cut chunk of about {int(round(seconds / period))} records ({seconds:.3f} s)"
            else:
                amount = "an unknown number of records (no summary)"
            notes.append(f"{loss.why} ({where}): {amount} {tail} lost; the rest of the run is lost")
    if not scan.data_end and scan.cut_at is None and not any(lo.end >= size for lo in scan.losses):
        notes.append(f"the file ends after its last complete chunk without a summary (the recorder did not close it): "
                     f"records after sequence {seq[-1] if seq.size else '-'} may never have been written; the rest of the run is lost")
    if seq.size > 1:
        d = np.diff(seq)
        gaps = [i for i in np.flatnonzero(d != 1) if i not in explained]
        if gaps:
            missing = int(sum(d[i] - 1 for i in gaps))
            i = gaps[0]
            notes.append(f"{missing} records missing in {len(gaps)} gap(s) of the sequence numbers "
                         f"(first after sequence {seq[i]}, t {t[i]:.4f} s)")
    return notes
