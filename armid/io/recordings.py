"""Reading recordings (INTERFACES.md 'Recordings') into arrays: the I/O layer.

CSV with a header: ``t``, ``q1..qn``, optional ``qd1..qdn`` and ``qdd1..qddn``, and
``tau1..taun`` or ``i1..in`` (scaled by each joint's ``torque_constant``). Also NumPy
``.npz`` archives with ``times, positions, velocities[, accelerations], torques`` (the
layout of the shared KUKA LWR4+ data). MCAP recordings from ``armid record``: ROS 2
(``/joint_states`` and ``/armid/joint_state_extra`` in CDR, decoded by :mod:`armid.io.ros2_cdr`;
the torque as the driver recorded it). The ``mcap`` library parses the records and checks each
chunk's CRC; reading resumes after a bad chunk, and the notes say what was lost
(:func:`read_mcap_arrays`). The JSON layout armid wrote before its ROS 2 recordings is refused
with its name. rosbag2 bags (a folder, a ``.db3``, an ``.mcap`` a ROS 2 tool wrote): JointState
on one topic, by :mod:`armid.io.ros2_bag`. :func:`recording_kind` decides which reader a path takes."""

from __future__ import annotations

import csv
import io
import re
import struct
import zlib
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Any

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, Footer, Metadata, Statistics
from mcap.stream_reader import CRCValidationError, StreamReader, get_chunk_data_stream

from armid.identify.errors import RecordingError
from armid.identify.recordings import Recording, recording_of
from armid.identify.robot import Robot
from armid.schema import Array
from armid.schema.joint_state import EXTRA_TOPIC, EXTRA_TYPE, JOINT_STATE_TYPE, JOINT_STATES_TOPIC
from armid.schema.joint_states import JointStates

from .ros2_bag import is_rosbag2_mcap, read_bag
from .ros2_cdr import decoded_columns, kind_of, ros2_columns, same_length

_JOINT_COLUMN = re.compile(r"(q|qd|qdd|tau|i)(\d+)")


def recording_kind(path: str | Path) -> str:
    """Which reader a recording takes, the one place that decides: ``bag`` (a rosbag2 bag: a
    folder, a ``.db3``, an ``.mcap`` a ROS 2 tool wrote: :mod:`armid.io.ros2_bag`), ``mcap``
    (armid's own recording), ``npz``, else ``csv``."""
    path = Path(path)
    suffix = path.suffix.lower()
    if path.is_dir() or suffix == ".db3":
        return "bag"
    if suffix == ".mcap":
        return "bag" if is_rosbag2_mcap(path) else "mcap"
    return "npz" if suffix == ".npz" else "csv"


def read_recording(path: str | Path, robot: Robot, topic: str | None = None) -> Recording:
    """Read one recording for ``robot`` by :func:`recording_kind`; ``topic``: a bag's JointState
    topic (default ``/joint_states``; other recordings have none). Raises
    :class:`RecordingError` naming what is wrong."""
    path = Path(path)
    if not path.exists():
        raise RecordingError(str(path), "no such file")
    kind = recording_kind(path)
    if kind == "bag":
        return read_bag(path, robot, topic)
    if kind == "npz":
        return _read_npz(path, robot)
    if kind == "mcap":
        return _read_mcap(path, robot)
    return _read_csv(path, robot)


RUN_END = "armid.run_end"
"""The metadata record in which the recorder (``armid.daq.recorder``) says how the run ended."""


def _read_mcap(path: Path, robot: Robot) -> Recording:
    """A recording from ``armid record``: positions, drive velocities, the torque the driver
    recorded; cycles where a joint's frames did not arrive are left out.

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


def _plain_numbers(text: str, n_columns: int) -> Array | None:
    """The rows after the header line as one array, parsed in C (``numpy.loadtxt``, the same
    correctly rounded conversion as ``float``): a tenth of the time of a cell at a time. None
    where the text is anything but one number in each of ``n_columns`` fields on every line
    (a blank line, a quote, a field that is not a number, a row of another length, a lone CR):
    those files take the cell-by-cell reading, which keeps such rows as garbage to report."""
    body = text[text.find("\n") + 1 :] if "\n" in text else ""
    n_lines = body.count("\n") + (not body.endswith("\n"))
    if not body or '"' in body or "\n\n" in body or body.count("\r") != body.count("\r\n"):
        return None
    try:
        data = np.loadtxt(io.StringIO(body), delimiter=",", comments=None, ndmin=2, dtype=float)
    except ValueError:
        return None
    return data if data.shape == (n_lines, n_columns) else None


def _read_csv(path: Path, robot: Robot) -> Recording:
    n = robot.n_joints
    try:
        with path.open(newline="") as handle:
            text = handle.read()
    except UnicodeDecodeError as err:
        raise RecordingError(str(path), f"not a text CSV file ({err.reason})") from err
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = next(reader, None)
        if header is None:
            raise RecordingError(str(path), "empty file (no header line)")
        header = [h.strip() for h in header]
        plain = _plain_numbers(text, len(header))
        rows = list(reader) if plain is None else []
    except csv.Error as err:  # a field beyond the reader's limit (a line of megabytes), a NUL byte
        raise RecordingError(str(path), f"line {reader.line_num}: not a CSV row ({err})") from None
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
    n_rows = len(rows) if plain is None else plain.shape[0]
    data = np.full((n_rows, len(wanted)), np.nan) if plain is None else plain[:, index]
    lines = np.arange(2, n_rows + 2)
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
    if n_rows == 0:
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
LEGACY_TOPIC = "/joint_state"
"""The one JSON channel of the layout armid wrote before its ROS 2 recordings: no longer read."""


McapMessage = tuple[int, int, int, bytes]
"""A message record of a recording: (file offset of the chunk or record that held it, MCAP
sequence number, log time, CDR bytes); a plain tuple, as there are two a cycle."""

_MESSAGE_HEADER = struct.Struct("<HIQQ")  # a message record's channel id, sequence, log time, publish time


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

    The ``mcap`` library parses the records (chunk headers, channels, metadata, the summary),
    decompresses each chunk and checks its CRC; its readers stop at the first record they cannot
    read and say nothing of where records lie, so this walk keeps the byte offsets and resumes: a chunk that fails its CRC, or whose records
    do not parse, is left out whole, and reading goes on at the next chunk the summary's chunk
    index gives when the file has an intact summary, else at the next byte position that
    holds a whole chunk with a matching CRC.
    """

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.channels: dict[int, Channel] = {}
        self.cdr: dict[str, list[McapMessage]] = {JOINT_STATES_TOPIC: [], EXTRA_TOPIC: []}
        self.metadata: dict[str, str] = {}
        self.end: dict[str, str] = {}  # armid.run_end: how the run ended
        self.losses: list[_Loss] = []
        self.data_end = False  # the data section ended as written (DataEnd record reached)
        self.cut_at: int | None = None  # the file ends inside a record at this offset
        self.statistics: Statistics | None = None  # from the summary
        self.chunk_starts: list[int] = []  # from the summary's chunk index
        self.summary = False
        self.orphans: dict[int, list[McapMessage]] = {}  # messages of a channel whose record was not read
        self.adopted: int | None = None
        self.unchecked: list[int] = []  # offsets of chunks whose CRC is 0 ("not computed"): read, but not verified
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

    def _stream(self, body: int, length: int) -> ReadDataStream:
        return ReadDataStream(BytesIO(self.data[body : body + length]))

    def _read_summary(self) -> None:
        """Chunk offsets, channels and statistics from the summary, if the footer and its CRC hold."""
        d = self.data
        tail = len(d) - len(MCAP_MAGIC) - 29  # footer: opcode, length 20, two u64 and a u32
        if tail < len(MCAP_MAGIC) or not d.endswith(MCAP_MAGIC) or d[tail] != Opcode.FOOTER:
            return
        footer = Footer.read(self._stream(tail + 9, 20))
        if not len(MCAP_MAGIC) <= footer.summary_start <= tail:
            return
        if footer.summary_crc and zlib.crc32(d[footer.summary_start : tail + 9 + 16]) != footer.summary_crc:
            return
        found: list[Any] = []
        try:
            for rec in StreamReader(BytesIO(d[footer.summary_start :]), skip_magic=True).records:
                if isinstance(rec, Footer):
                    break
                found.append(rec)
        except Exception:  # a summary that does not parse: read as if there were none
            return
        for rec in found:
            if isinstance(rec, ChunkIndex):
                self.chunk_starts.append(rec.chunk_start_offset)
            elif isinstance(rec, Statistics):
                self.statistics = rec
            elif isinstance(rec, Channel):
                self.channels[rec.id] = rec
        self.summary = True
        self.chunk_starts = sorted(s for s in self.chunk_starts if s < len(d))

    def expected_cycles(self) -> int | None:
        """How many cycles the summary's statistics say were written (messages on the extra channel)."""
        extra = next((c.id for c in self.channels.values() if c.topic == EXTRA_TOPIC), None)
        if self.statistics is None or extra is None:
            return None
        return self.statistics.channel_message_counts.get(extra)

    def _read_data(self) -> None:
        d = self.data
        pos = len(MCAP_MAGIC)
        while pos < len(d):
            rec = self._record(pos)
            if rec is None or not Opcode.HEADER <= rec[0] <= Opcode.DATA_END:
                nxt = self._next_chunk(pos + 1)
                if nxt is not None:
                    self.losses.append(_Loss(pos, nxt, "unreadable record framing"))
                    pos = nxt
                    continue
                if rec is None and (pos + 9 > len(d) or Opcode.HEADER <= d[pos] <= Opcode.DATA_END):
                    self._cut(pos)  # the file ends inside this record: written no further
                else:
                    self.losses.append(_Loss(pos, len(d), "unreadable record framing"))
                return
            op, length = rec
            body = pos + 9
            try:
                if op == Opcode.CHUNK:
                    self._chunk(pos, body, length)
                elif op == Opcode.CHANNEL:
                    self._channel(Channel.read(self._stream(body, length)))
                elif op == Opcode.MESSAGE:
                    self._message(pos, self.data[body : body + length])
                elif op == Opcode.METADATA:
                    self._metadata(Metadata.read(self._stream(body, length)))
                elif op in (Opcode.DATA_END, Opcode.FOOTER):
                    self.data_end = op == Opcode.DATA_END
                    return
            except Exception:  # a record outside the chunks that does not parse: its content is lost
                self.losses.append(_Loss(pos, body + length, f"an unreadable record (opcode {op:#04x})"))
            pos = body + length

    def _cut(self, pos: int) -> None:
        """The file ends inside the record at ``pos``: note it, with a cut chunk's time span."""
        self.cut_at = pos
        loss = _Loss(pos, len(self.data), "the file ends inside a record")
        if self.data[pos] == Opcode.CHUNK and pos + 9 + 16 <= len(self.data):  # the span is the header's first 16 bytes
            loss.why = "the file ends inside a chunk"
            loss.start_time_ns, loss.end_time_ns = struct.unpack_from("<QQ", self.data, pos + 9)
        self.losses.append(loss)

    def _chunk_at(self, pos: int) -> Chunk | None:
        """The whole chunk at ``pos`` when its framing is consistent (its fields fill its record exactly), else None."""
        rec = self._record(pos)
        if rec is None or rec[0] != Opcode.CHUNK:
            return None
        stream = self._stream(pos + 9, rec[1])
        try:
            chunk = Chunk.read(stream)
        except Exception:  # fields that run past the record
            return None
        return chunk if stream.count == rec[1] and chunk.compression in ("", "lz4", "zstd") else None

    def _next_chunk(self, after: int) -> int | None:
        """Where reading resumes: the next chunk the summary lists, or the next whole chunk
        with a consistent frame and a matching CRC found byte by byte."""
        if self.summary:
            return next((s for s in self.chunk_starts if s >= after), None)
        pos = after
        while True:
            pos = self.data.find(bytes([Opcode.CHUNK]), pos)
            if pos < 0:
                return None
            chunk = self._chunk_at(pos)
            if chunk is not None and _readable(chunk, validate_crc=True):
                return pos
            pos += 1

    def _chunk(self, pos: int, body: int, length: int) -> None:
        chunk = self._chunk_at(pos)
        if chunk is None:
            self.losses.append(_Loss(pos, body + length, "a chunk whose header is garbled"))
            return
        why = "a chunk whose records do not parse"
        try:
            stream, size = get_chunk_data_stream(chunk, validate_crc=True)
            records = _split_records(stream.read(size))
        except CRCValidationError:
            why, records = "a chunk that fails its CRC", None
        except Exception:  # a corrupt compressed frame
            why, records = "a chunk that does not decompress", None
        if records is None:
            self.losses.append(_Loss(pos, body + length, why, chunk.message_start_time, chunk.message_end_time))
            return
        if chunk.uncompressed_crc == 0:  # MCAP's "not computed": nothing says its bytes are the ones written
            self.unchecked.append(pos)
        for op, content in records:
            if op == Opcode.CHANNEL:
                self._channel(Channel.read(ReadDataStream(BytesIO(content))))
        for op, content in records:
            if op == Opcode.MESSAGE:
                self._message(pos, content)

    def _channel(self, channel: Channel) -> None:
        self.channels[channel.id] = channel

    def _message(self, pos: int, content: bytes) -> None:
        if len(content) < _MESSAGE_HEADER.size:
            return
        channel_id, sequence, log_time, _ = _MESSAGE_HEADER.unpack_from(content)
        message = (pos, sequence, log_time, content[_MESSAGE_HEADER.size :])
        channel = self.channels.get(channel_id)
        if channel is None:
            self.orphans.setdefault(channel_id, []).append(message)
        elif channel.topic in self.cdr:
            self.cdr[channel.topic].append(message)

    def _adopt_orphans(self) -> None:
        """The channel records went down with a bad chunk (they are written once, in the first
        chunk, and again only in the summary). When neither of a ROS 2 recording's channels was
        seen, the two unknown channels are told apart by which message type their first
        message decodes as."""
        if any(c.topic in (JOINT_STATES_TOPIC, EXTRA_TOPIC, LEGACY_TOPIC) for c in self.channels.values()) or len(self.orphans) != 2:
            return
        found: dict[str, int] = {}
        for channel, messages in self.orphans.items():
            kind = kind_of(messages[0][3])
            if kind is not None:
                found.setdefault(JOINT_STATES_TOPIC if kind == JOINT_STATE_TYPE else EXTRA_TOPIC, channel)
        if len(found) == 2 and len(set(found.values())) == 2:
            for topic, channel in found.items():
                self.cdr[topic] = self.orphans[channel]
            self.adopted = found[EXTRA_TOPIC]

    def _metadata(self, rec: Metadata) -> None:
        if rec.name == "armid.run":
            self.metadata = dict(rec.metadata)
        elif rec.name == RUN_END:
            self.end = dict(rec.metadata)

    def run_metadata(self) -> dict[str, str]:
        """``armid.run`` with ``armid.run_end``'s keys (``completed``, ``stop``, ``stop_cycle``,
        ``records``) when the recorder wrote how the run ended."""
        return {**self.metadata, **self.end}


def _split_records(raw: bytes) -> list[tuple[int, bytes]] | None:
    """The (opcode, content) records of a decompressed, CRC-checked chunk; None when they do not
    fill it exactly. The ``mcap`` library's own split (``breakup_chunk``) reads each field through
    a stream object: at two messages a cycle it made reading a 10-minute recording at 2 ms take
    2.7 times as long (4.6 s -> 12.5 s); here a record's frame is one slice."""
    out = []
    k = 0
    while k + 9 <= len(raw):
        op = raw[k]
        (n,) = struct.unpack_from("<Q", raw, k + 1)
        if k + 9 + n > len(raw):
            return None
        out.append((op, raw[k + 9 : k + 9 + n]))
        k += 9 + n
    return out if k == len(raw) else None


def _readable(chunk: Chunk, validate_crc: bool) -> bool:
    """Whether ``chunk`` decompresses (and, with ``validate_crc``, matches its CRC)."""
    try:
        get_chunk_data_stream(chunk, validate_crc=validate_crc)
    except Exception:  # a corrupt compressed frame, or a CRC that does not match
        return False
    return True


def read_mcap_arrays(path: str | Path) -> tuple[dict[str, Array], dict[str, str], list[str]]:
    """Arrays of a ROS 2 recording's cycles, the run metadata (``armid.run``, with
    ``armid.run_end``'s ``completed``, ``stop``, ``stop_cycle`` and ``records`` where the
    recorder said how the run ended: :func:`stop_line`), and notes on what was lost.

    Chunks that fail their CRC are left out and reading goes on after them (see
    :class:`_McapScan`); the notes say how many records and seconds each loss cost and where.
    A message that passed its CRC but is not its type is refused (:class:`RecordingError`), and
    so is a file in the JSON layout armid wrote before its ROS 2 recordings.

    Each cycle's ``/joint_states`` and ``/armid/joint_state_extra`` messages are paired by
    their MCAP log time and sequence number; a cycle with one of its two messages lost is
    lost (said among the gaps).
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
    if any(c.topic == LEGACY_TOPIC for c in scan.channels.values()) and not any(scan.cdr.values()):
        raise RecordingError(src, f"an MCAP in the JSON layout (channel {LEGACY_TOPIC}) that armid wrote before its ROS 2 "
                                  f"recordings: this layout is no longer read (armid reads {JOINT_STATES_TOPIC} and {EXTRA_TOPIC} in CDR)")

    def by_key(topic: str) -> dict[tuple[int, int], int]:  # the last message of a key, in the order keys first came
        return {(m[2], m[1]): k for k, m in enumerate(scan.cdr[topic])}

    states, extras = by_key(JOINT_STATES_TOPIC), by_key(EXTRA_TOPIC)
    pairs = [(scan.cdr[JOINT_STATES_TOPIC][states[key]], scan.cdr[EXTRA_TOPIC][k]) for key, k in extras.items() if key in states]
    if not pairs:
        notes = _loss_notes(scan, [], [], [], len(data))
        return {}, scan.run_metadata(), notes or [_unpaired(states, extras)]
    s_msgs, e_msgs = [s[3] for s, _ in pairs], [e[3] for _, e in pairs]
    offsets = np.array([e[0] for _, e in pairs], np.int64)
    cols = same_length(ros2_columns(s_msgs, JOINT_STATE_TYPE), ros2_columns(e_msgs, EXTRA_TYPE))
    if cols is None:  # messages of different layouts: one by one, each checked
        cols = decoded_columns([(s[0], s[3]) for s, _ in pairs], [(e[0], e[3]) for _, e in pairs], src)
    t = cols["sec"][:, 0] + 1e-9 * cols["nanosec"][:, 0]
    notes = _loss_notes(scan, cols["sequence"][:, 0].astype(np.int64), t, offsets, len(data))
    if scan.unchecked:
        more = len(scan.unchecked) - 1
        notes.append(f"chunk at offset {scan.unchecked[0]} has no CRC: not verified"
                     + (f" (nor {more} more chunk{'s' if more > 1 else ''} without one)" if more else ""))
    if scan.adopted is not None:
        notes.append(f"the channel record was lost for both {JOINT_STATES_TOPIC} and {EXTRA_TOPIC}: the {len(t)} cycles of "
                     "the two channels left were read by the message types they decode as")
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


def _unpaired(states: dict[tuple[int, int], int], extras: dict[tuple[int, int], int]) -> str:
    """Why no cycle could be read from the two channels' messages (none lost to corruption)."""
    if not states:
        return f"no {JOINT_STATES_TOPIC} record in the file" + (f" ({len(extras)} {EXTRA_TOPIC} messages alone)" if extras else "")
    if not extras:
        return (f"{len(states)} {JOINT_STATES_TOPIC} messages but no {EXTRA_TOPIC} channel: armid reads a cycle from the two "
                "together, as armid record writes them")
    return (f"none of the {len(states)} {JOINT_STATES_TOPIC} messages has its {EXTRA_TOPIC} message (the same log time and "
            "sequence number)")


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
            else:  # before the first record read: the recording need not start at sequence 0
                count = _lost_before(scan, loss, seq, period)
                if count is None:
                    notes.append(f"{loss.why} ({where}): an unknown number of records before sequence {seq[after]} (t {t[after]:.4f} s) "
                                 "lost (neither the chunk's time span nor the file's counts could be read); reading resumed after it")
                    continue
                if count == 0:
                    notes.append(f"{loss.why} ({where}): no record lost")
                    continue
                lost = count
                seconds = lost * period if np.isfinite(period) else float("nan")
                span = f"sequence {seq[after] - lost}..{seq[after] - 1}, before t {t[after]:.4f} s"
            notes.append(f"{loss.why} ({where}): {lost} records ({seconds:.3f} s; {span}) lost; reading resumed after it")
        else:
            tail = f"after sequence {seq[-1]} (t {t[-1]:.4f} s)" if seq.size else "from the start"
            lost_or_none = _unaccounted(scan, seq)
            if lost_or_none is not None:
                lost = lost_or_none
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
        gaps = [i for i in np.flatnonzero(d > 1) if i not in explained]
        if gaps:
            missing = int(sum(d[i] - 1 for i in gaps))
            i = gaps[0]
            notes.append(f"{missing} records missing in {len(gaps)} gap(s) of the sequence numbers "
                         f"(first after sequence {seq[i]}, t {t[i]:.4f} s)")
        back = np.flatnonzero(d < 1)  # a number repeated or going back: not a gap, and no record missing
        if back.size:
            k = int(back[0])
            notes.append(f"{back.size} record(s) numbered no higher than the record before (first: sequence {seq[k + 1]} after "
                         f"{seq[k]}): put in sequence order")
    return notes


def _unaccounted(scan: _McapScan, seq: Any) -> int | None:
    """Records the file says were written (its summary's count of cycles, else the recorder's
    ``armid.run_end`` count) less those read and those in the gaps between them: the records
    lost outside the records read. None when the file does not say, or says fewer than were read."""
    expected = scan.expected_cycles()
    if expected is None:
        try:
            expected = int(scan.end["records"])
        except (KeyError, ValueError):
            return None
    unique = np.unique(np.asarray(seq, np.int64))
    inside = int(unique[-1] - unique[0] + 1) if unique.size else 0  # the records read and the gaps between them
    lost = expected - inside
    return lost if lost >= 0 else None


def _lost_before(scan: _McapScan, loss: _Loss, seq: Any, period: float) -> int | None:
    """How many records a stretch before the first record read held: by the lost chunk's own
    time span where its header could be read, else what the file's counts leave unaccounted
    (a recording that starts at sequence 47 lost nothing before it started)."""
    if loss.start_time_ns is not None and loss.end_time_ns is not None and np.isfinite(period) and period > 0:
        span = (loss.end_time_ns - loss.start_time_ns) * 1e-9
        if 0 <= span < 1e6:  # no more than the sequence numbers leave room for (a header's times may be garbled too)
            return min(int(round(span / period)) + 1, int(np.min(seq)))
    return _unaccounted(scan, seq)
