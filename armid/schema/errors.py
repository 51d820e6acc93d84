"""Every error and warning armid raises on purpose: one tree.

A caller catches everything with :class:`ArmidError`, or one branch. The command line maps
by type: an :class:`InputError` (the user's file, option or data is wrong) exits 2; every
other :class:`ArmidError` (a runtime fault: a drive, the bus, the simulated hardware) exits 1.
Errors that were ``ValueError`` stay catchable as ``ValueError`` (python-can's
``CanTimeoutError(CanError, TimeoutError)`` is the model)::

    ArmidError
     +-- InputError                                     bad input: exit 2
     |    +-- RecordingError(ValueError)                unusable recording (file, column, row)
     |    +-- IdentificationError                       the data cannot give an estimate
     |    +-- UsageError(ValueError)                    arguments that do not fit together
     |    |    +-- OptionError                          one option outside its meaningful range
     |    +-- TrajectoryLimitError(ValueError)          a planned trajectory beyond a joint limit
     |    +-- InputFileError(ValueError)                an input file: file, field, problem
     |    |    +-- RobotFileError                       malformed robot description
     |    |    +-- RigFileError                         malformed rig file
     |    +-- BusBudgetError(ValueError)                the rig's PDO plan does not fit the bus
     |    +-- MissingExtraError(ImportError)            the command needs an extra this install lacks
     +-- RecordFormatError(ValueError)                  bytes that are not a joint-state record
     +-- DriverError                                    runtime: the driver cannot go on
     |    +-- DriveConfigError(InputError, ValueError)  a drive refuses the rig's configuration
     |    |    +-- SerialBudgetError                    the servo cycle does not fit the period
     |    +-- BusOpenError(OSError)                     the bus or serial port will not open: cause, what to do
     |    +-- DriverTimeout(TimeoutError)               no cycle, state or answer within its time
     |    +-- DriveFault                                a drive's fault (EMCY) or silence
     |    |    +-- HeartbeatLost                        no heartbeat within 3 periods
     |    |         +-- ServoLost                       a servo silent for ``silent_cycles``
     |    +-- ProtocolError                             a Dynamixel reply that cannot be used
     |         +-- CrcError
     |         +-- ReplyTimeout(TimeoutError)
     |         |    +-- PartialPacket
     |         +-- MalformedPacket
     |         +-- StatusError                          (drivers.dynamixel_protocol: the servo's error field)
     +-- SimulationError(RuntimeError)                  the simulated hardware failed
    ImplausibleDataWarning(UserWarning)                 a recording looks odd but may be right
    PoorExcitationWarning(UserWarning)                  trajectory not persistently exciting (5.2)

Every message names what is wrong and where (file, field, row, joint or servo), so that the
command line can print it on one line.
"""

from __future__ import annotations

import time


class ArmidError(Exception):
    """Root of every error armid raises on purpose."""


class InputError(ArmidError):
    """The user's input (a file, an option, the data) is wrong: the command line exits 2."""


class RecordingError(InputError, ValueError):
    """A recording cannot be used: the message names the file and the column or row."""

    def __init__(self, source: str, problem: str) -> None:
        self.source = source
        self.problem = problem
        super().__init__(f"{source}: {problem}")


class IdentificationError(InputError):
    """The data, as given, cannot produce an estimate (too few samples, no excitation)."""


class UsageError(InputError, ValueError):
    """A command was called with arguments that do not fit together."""


class OptionError(UsageError):
    """One option's value is outside its meaningful range: names the option and the value."""

    def __init__(self, option: str, problem: str) -> None:
        self.option = option
        self.problem = problem
        super().__init__(f"{option}: {problem}")


class TrajectoryLimitError(InputError, ValueError):
    """A trajectory goes beyond a joint limit: names the joint, the limit, the value and the time."""

    def __init__(self, joint: int, kind: str, value: float, limit: float, time_s: float, unit: str) -> None:
        self.joint, self.kind, self.value, self.limit, self.time_s = joint, kind, value, limit, time_s
        super().__init__(f"joint {joint + 1}: {kind} {value:.4g} {unit} beyond the limit {limit:.4g} {unit} at t = {time_s:.3f} s")


class InputFileError(InputError, ValueError):
    """An input file other than a recording (a trajectory, a Zenoh configuration, a robot,
    a rig) cannot be used: names the file, the field or line, and the problem."""

    def __init__(self, source: str, field: str, problem: str) -> None:
        self.source = source
        self.field = field
        self.problem = problem
        where = f"{source}: {field}" if field else source
        super().__init__(f"{where}: {problem}")


class RobotFileError(InputFileError):
    """A robot description is malformed: the message names the file, the field, the problem."""


class RigFileError(InputFileError):
    """A rig file is malformed: names the file, the field and the problem."""


class BusBudgetError(InputError, ValueError):
    """The PDO plan does not fit the bus: the message has the numbers and the options."""


class MissingExtraError(InputError, ImportError):
    """The command needs an extra this install lacks (``armid.extras``): names the extra and
    what installs it. Exit 2, as bad usage: nothing failed at run time, and the same command
    fails the same way until the user installs the extra (``armid fleet``'s Ray did so first)."""


class RecordFormatError(ArmidError, ValueError):
    """Bytes that are not a joint-state record of a schema and version this code reads."""


class DriverError(ArmidError):
    """The driver cannot go on (configuration refused, bus gone, timeout)."""


class DriveConfigError(DriverError, InputError, ValueError):
    """A drive refused or disagrees with the configuration: names node, object, problem."""


class SerialBudgetError(DriveConfigError):
    """The cycle does not fit the period at this baud rate: the message gives the numbers."""


class BusOpenError(DriverError, OSError):
    """A CAN bus or a serial port would not open (``drivers.port_errors`` words it): names the
    interface (``socketcan``, ``pcan``, ``serial``, ...), the channel or port, the cause and what
    to do. A runtime fault (exit 1): the rig may be right and the hardware not ready."""

    def __init__(self, interface: str, channel: str, cause: str) -> None:
        self.interface, self.channel, self.cause = interface, channel, cause
        super().__init__(cause)

    def __str__(self) -> str:
        return self.cause

    def __reduce__(self) -> tuple[type[BusOpenError], tuple[str, str, str]]:
        return (type(self), (self.interface, self.channel, self.cause))


class DriverTimeout(DriverError, TimeoutError):
    """A cycle, a drive's state or an answer did not come within its time: a ``TimeoutError``
    as python-can's ``CanTimeoutError`` is, and a driver error the command line prints on one line."""


class DriveFault(DriverError):
    """A drive reported a fault (EMCY) or went silent; ``joint`` is 0-based."""

    def __init__(self, joint: int, node_id: int, code: int, meaning: str, time_s: float | None = None) -> None:
        self.joint, self.node_id, self.code, self.meaning = joint, node_id, code, meaning
        self.time_s = time.time() if time_s is None else time_s
        super().__init__(f"joint {joint + 1} (node {node_id}): fault 0x{code:04X}: {meaning}")


class HeartbeatLost(DriveFault):
    """No heartbeat from a drive within 3 of its periods; ``silent_s``, where known, is how
    long it had been silent in bus time when the loss was declared."""

    def __init__(self, joint: int, node_id: int, code: int, meaning: str, silent_s: float | None = None) -> None:
        super().__init__(joint, node_id, code, meaning)
        self.silent_s = silent_s


class ServoLost(HeartbeatLost):
    """A servo has not answered for ``silent_cycles`` cycles in a row."""


class NotOperational(DriveFault):
    """A drive that was operational reports another NMT state in its heartbeat: stopped by an
    NMT command, or reset (its boot-up message). It sends no PDOs and takes no commands."""

    def __init__(self, joint: int, node_id: int, state: int, meaning: str) -> None:
        super().__init__(joint, node_id, 0, meaning)
        self.state = state
        self.args = (f"joint {joint + 1} (node {node_id}): {meaning}",)


class ProtocolError(DriverError):
    """A reply that cannot be used: names the servo and what was wrong with the bytes."""

    def __init__(self, message: str, servo_id: int | None = None) -> None:
        self.servo_id = servo_id
        super().__init__(message)


class CrcError(ProtocolError):
    """The CRC does not match the bytes: corrupted on the line."""


class ReplyTimeout(ProtocolError, TimeoutError):
    """No reply (or not all of it) within the reply timeout."""


class PartialPacket(ReplyTimeout):
    """The reply started but stopped before its last byte."""


class MalformedPacket(ProtocolError):
    """Bytes that are not a packet of the kind expected (length, id, instruction)."""


class SimulationError(ArmidError, RuntimeError):
    """The simulated hardware (a servo chain in its own process, the simulated arm) failed."""


class PoorExcitationWarning(UserWarning):
    """The trajectory does not excite what it should (Khosla 5.2: not persistently exciting)."""


class ImplausibleDataWarning(UserWarning):
    """A recording looks odd (for instance a velocity column that disagrees with dq/dt)
    but could still be right: the command line prints it and goes on."""
