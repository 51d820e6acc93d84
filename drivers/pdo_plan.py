"""PDO plans and the CAN bus budget.

At 1 Mbit/s a 2 ms cycle holds 2000 bit times. A classic CAN frame with ``n`` data bytes
and an 11-bit identifier takes ``47 + 8n`` bits, plus up to ``(34 + 8n - 1) // 4`` stuff bits
(one every four bits of the stuffed region, the worst case): 135 bits at 8 bytes. Per axis,
position (4 bytes), velocity (4), current (2) and statusword (2) make 12 bytes: two frames.
Six axes with two TPDOs and a torque RPDO each load the bus to about 95 %, which is too much.
Hence the plans:

- ``alternate_velocity`` (default): TPDO1 = position + current on every SYNC; TPDO2 =
  velocity + statusword on every second SYNC (the counter's even values); RPDO1 = target
  torque on every cycle; RPDO2 = controlword, sent only when it changes. 6 axes, 2 ms,
  1 Mbit/s: 77.9 %.
- ``full``: TPDO1 = position + velocity, TPDO2 = current + statusword, both on every SYNC;
  RPDO1 = target torque; RPDO2 = controlword on change. Fits 6 axes at 4 ms, or 5 axes at
  2.5 ms.
- ``position_current``: TPDO1 = position + current + statusword on every SYNC (8 bytes),
  no velocity on the bus (differentiate position); 6 axes, 2 ms: 66.9 %.

A plan above 80 % is refused with the numbers and the ways out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from armid.schema.errors import BusBudgetError

POSITION = (0x6064, 0, 32)
VELOCITY = (0x606C, 0, 32)
CURRENT = (0x6078, 0, 16)
STATUSWORD = (0x6041, 0, 16)
CONTROLWORD = (0x6040, 0, 16)
TARGET_TORQUE = (0x6071, 0, 16)

MAX_LOAD = 0.80


@dataclass(frozen=True)
class PdoSpec:
    """One PDO of every drive: direction, number (1-4), mapped objects, SYNCs per frame.

    ``every`` is the transmission type of a TPDO (sent when the SYNC counter is a multiple
    of it); 0 marks an RPDO sent only on change (not part of the cyclic load).
    """

    direction: str  # "tpdo" | "rpdo"
    number: int
    entries: tuple[tuple[int, int, int], ...]
    every: int = 1

    @property
    def n_bytes(self) -> int:
        return sum(bits for _, _, bits in self.entries) // 8


PLANS: dict[str, tuple[PdoSpec, ...]] = {
    "alternate_velocity": (
        PdoSpec("tpdo", 1, (POSITION, CURRENT)),
        PdoSpec("tpdo", 2, (VELOCITY, STATUSWORD), every=2),
        PdoSpec("rpdo", 1, (TARGET_TORQUE,)),
        PdoSpec("rpdo", 2, (CONTROLWORD,), every=0),
    ),
    "full": (
        PdoSpec("tpdo", 1, (POSITION, VELOCITY)),
        PdoSpec("tpdo", 2, (CURRENT, STATUSWORD)),
        PdoSpec("rpdo", 1, (TARGET_TORQUE,)),
        PdoSpec("rpdo", 2, (CONTROLWORD,), every=0),
    ),
    "position_current": (
        PdoSpec("tpdo", 1, (POSITION, CURRENT, STATUSWORD)),
        PdoSpec("rpdo", 1, (TARGET_TORQUE,)),
        PdoSpec("rpdo", 2, (CONTROLWORD,), every=0),
    ),
}


def frame_bits(n_bytes: int) -> int:
    """Worst-case bits of a classic CAN frame, 11-bit id, with stuffing and interframe space."""
    return 47 + 8 * n_bytes + (34 + 8 * n_bytes - 1) // 4


@dataclass(frozen=True)
class BusLoad:
    bits_per_cycle: float
    capacity_bits: float
    frames_per_cycle: float

    @property
    def load(self) -> float:
        return self.bits_per_cycle / self.capacity_bits


def bus_load(plan: str, n_axes: int, period_s: float, bitrate: int, heartbeat_ms: int = 100) -> BusLoad:
    """Worst-case load of a plan: SYNC with counter, cyclic PDOs, heartbeats of all nodes."""
    specs = PLANS[plan]
    bits = float(frame_bits(1))  # SYNC with counter
    frames = 1.0
    for spec in specs:
        if spec.every:
            bits += n_axes * frame_bits(spec.n_bytes) / spec.every
            frames += n_axes / spec.every
    heartbeats = (n_axes + 1) * period_s / (heartbeat_ms / 1000.0)
    bits += heartbeats * frame_bits(1)
    frames += heartbeats
    return BusLoad(bits, bitrate * period_s, frames)


PLAN_WORDS = {
    "alternate_velocity": "velocity on alternate cycles",
    "full": "every value on every cycle",
    "position_current": "position and current only, velocity differentiated",
}


def shortest_period_s(plan: str, n_axes: int, bitrate: int, heartbeat_ms: int = 100) -> float:
    """The shortest SYNC period at which ``plan`` stays within :data:`MAX_LOAD` (s): the cyclic
    frames are a fixed count per cycle, the heartbeats a fixed rate (:func:`bus_load`)."""
    fixed = bus_load(plan, n_axes, 0.0, bitrate, heartbeat_ms).bits_per_cycle
    heartbeat_bits_per_s = (n_axes + 1) * frame_bits(1) / (heartbeat_ms / 1000.0)
    return fixed / (MAX_LOAD * bitrate - heartbeat_bits_per_s)


def check_bus_budget(plan: str, n_axes: int, period_s: float, bitrate: int, heartbeat_ms: int = 100) -> BusLoad:
    """:func:`bus_load`, refused above 80 % with the numbers and the ways out: the other plans
    that fit (never the one in use), the shortest period that fits this plan, and the rest."""
    b = bus_load(plan, n_axes, period_s, bitrate, heartbeat_ms)
    if b.load > MAX_LOAD:
        loads = {p: bus_load(p, n_axes, period_s, bitrate, heartbeat_ms).load for p in PLANS if p != plan}
        fitting = [f"pdo_plan: {p} ({PLAN_WORDS[p]}: {load:.0%} here)" for p, load in loads.items() if load <= MAX_LOAD]
        shortest = math.ceil(shortest_period_s(plan, n_axes, bitrate, heartbeat_ms) * 1e5) / 1e5  # up to 10 us
        options = [*fitting, f"a period of at least {shortest * 1000:g} ms with this plan (period_s: {shortest:g})",
                   "two buses", "fewer axes commanded per cycle", "CAN FD"]
        others = ", ".join(f"{p} {load:.0%}" for p, load in loads.items() if load > MAX_LOAD)
        raise BusBudgetError(
            f"PDO plan {plan!r} loads the bus to {b.load:.1%} (worst case with bit stuffing: "
            f"{b.bits_per_cycle:.0f} of {b.capacity_bits:.0f} bits per {period_s * 1000:g} ms cycle, "
            f"{n_axes} axes at {bitrate / 1e6:g} Mbit/s); the limit is {MAX_LOAD:.0%}. Options: {', '.join(options)}"
            + (f". Beyond the limit here too: {others}" if others else "")
        )
    return b
