"""A ROS 2 recording's two message types decoded one by one: ``mcap_ros2``'s generic CDR
decoder against armid's own ``ros2msg`` schemas (:data:`~armid.schema.joint_state.ROS2_MSGDEFS`).

The reader (:mod:`armid.io.recordings`) reads the messages in place as columns where they
share one layout (:func:`~armid.schema.joint_state.ros2_columns`); this is its path for the
rest, which checks each message and names the one that is not its type or whose fields'
counts disagree.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from armid.identify.errors import RecordingError
from armid.schema.joint_state import EXTRA_TOPIC, EXTRA_TYPE, JOINT_STATE_TYPE, JOINT_STATES_TOPIC, ROS2_MSGDEFS


def cdr_decoders() -> dict[str, Any]:
    """CDR decoders of the two message types, built from armid's own ``ros2msg`` schemas."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory

    factory = DecoderFactory()
    out = {}
    for schema_id, (kind, text) in enumerate(ROS2_MSGDEFS.items(), 1):  # the factory keeps one decoder per schema id
        decoder = factory.decoder_for("cdr", Schema(id=schema_id, name=kind, encoding="ros2msg", data=text.encode()))
        assert decoder is not None
        out[kind] = decoder
    return out


_PER_JOINT = ("position", "velocity", "effort", "valid", "velocity_fresh", "commanded_current", "measured_current", "statusword")


def same_length(states: dict[str, Any] | None, extras: dict[str, Any] | None) -> dict[str, Any] | None:
    """Both kinds' columns together when every per-joint field has as many values as the
    positions (else None: the one-by-one path names the field that has not)."""
    if states is None or extras is None:
        return None
    cols = {**states, **{k: v for k, v in extras.items() if k not in ("sec", "nanosec")}}
    return cols if len({cols[name].shape[1] for name in _PER_JOINT}) == 1 else None


def decoded_columns(cdr: dict[str, list[tuple[int, bytes]]], pairs: Any, src: str) -> dict[str, Any]:
    """The paired messages (``pairs``: index in ``cdr``'s extras, in its states; ``cdr`` holds
    each topic's (file offset, whole message record)) decoded one by one
    (``mcap_ros2`` against armid's schemas), as columns; a message that is not its type, or a
    field with a count unlike the others', is refused naming it."""
    decoders = cdr_decoders()
    cols: dict[str, list[Any]] = {name: [] for name in ("sec", "nanosec", "sequence", "cycle", *_PER_JOINT)}
    m: int | None = None

    def decoded(topic: str, kind: str, k: int) -> Any:
        pos, content = cdr[topic][k]
        try:
            return decoders[kind](content[22:])
        except Exception as err:  # the CRC held: the recorder wrote something that is not this type
            raise RecordingError(src, f"{topic} message {k} (in the chunk at byte {pos}): not a {kind} in CDR ({err})") from None

    for ke, ks in pairs:
        s, e = decoded(JOINT_STATES_TOPIC, JOINT_STATE_TYPE, int(ks)), decoded(EXTRA_TOPIC, EXTRA_TYPE, int(ke))
        fields = {"position": s.position, "velocity": s.velocity, "effort": s.effort, "valid": e.valid, "velocity_fresh": e.velocity_fresh,
                  "commanded_current": e.commanded_current, "measured_current": e.measured_current, "statusword": e.statusword}
        m = len(s.position) if m is None else m
        wrong = next((name for name, v in fields.items() if len(v) != m), None)
        if wrong is not None:
            raise RecordingError(src, f"{EXTRA_TOPIC if wrong not in ('position', 'velocity', 'effort') else JOINT_STATES_TOPIC} "
                                      f"(sequence {e.sequence}): '{wrong}' has {len(fields[wrong])} values, the recording's other messages {m}")
        for name, v in fields.items():
            cols[name].append(list(v))
        for name, v in (("sec", s.header.stamp.sec), ("nanosec", s.header.stamp.nanosec), ("sequence", e.sequence), ("cycle", e.cycle)):
            cols[name].append([v])
    floats = ("position", "velocity", "effort", "commanded_current", "measured_current")
    return {name: np.array(v, float if name in floats else np.int64).reshape(len(pairs), -1) for name, v in cols.items()}
