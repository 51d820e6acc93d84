"""A recording as arrays (:class:`Recording`): what the preprocessing takes.

Reading files (CSV, NPZ, MCAP) into a :class:`Recording` is the I/O layer's job
(:mod:`armid.io.recordings`); this package never opens a file.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .spatial import Array


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
    cycle: Array | None = None  # each sample's cycle counter (a drive recording), else None
    period_s: float | None = None  # the cycle's nominal period, where the recording says it (its metadata), else None
    # where the torque comes from: True, a measured current times a torque constant (a drive's
    # gain is in question); False, joint torque given directly (a torque sensor: no drive gain
    # between it and the model); None, not said (arrays made in memory, a simulated drive's)
    torque_from_current: bool | None = None
    # the line that stopped the run the recording holds (a drive fault, lost frames, a safety
    # stop: what its metadata says), None for a run that completed or a file that does not say
    stopped: str | None = None

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])
