"""Errors and warnings of the identification core.

One tree, so that a caller can catch everything armid raises, or one branch::

    ArmidError
     +-- RecordingError(ArmidError, ValueError)     unusable recording (file, column, row)
     +-- IdentificationError(ArmidError)            the data cannot give an estimate
     +-- UsageError(ArmidError, ValueError)         arguments that do not fit together
     +-- TrajectoryLimitError(ArmidError, ValueError)   (identify.excitation) a plan beyond a limit
     +-- InputFileError(ArmidError, ValueError)     an input file (trajectory JSON, Zenoh
     |    |                                         configuration): file, field, problem
     |    +-- RobotFileError(InputFileError)        malformed robot description
     +-- OptionError(UsageError)                    one option outside its meaningful range
    ImplausibleDataWarning(UserWarning)             a recording looks odd but may be right
    PoorExcitationWarning(UserWarning)              trajectory not persistently exciting (5.2)

Every message names what is wrong and where (file, field or row), so that the command
line can print it on one line.
"""

from __future__ import annotations


class ArmidError(Exception):
    """Root of every error armid raises on purpose."""


class RecordingError(ArmidError, ValueError):
    """A recording cannot be used: the message names the file and the column or row."""

    def __init__(self, source: str, problem: str) -> None:
        self.source = source
        self.problem = problem
        super().__init__(f"{source}: {problem}")


class IdentificationError(ArmidError):
    """The data, as given, cannot produce an estimate (too few samples, no excitation)."""


class PoorExcitationWarning(UserWarning):
    """The trajectory does not excite what it should (Khosla 5.2: not persistently exciting)."""


class UsageError(ArmidError, ValueError):
    """A command was called with arguments that do not fit together."""


class OptionError(UsageError):
    """One option's value is outside its meaningful range: names the option and the value."""

    def __init__(self, option: str, problem: str) -> None:
        self.option = option
        self.problem = problem
        super().__init__(f"{option}: {problem}")


class InputFileError(ArmidError, ValueError):
    """An input file other than a recording (a trajectory, a Zenoh configuration, a robot)
    cannot be used: names the file, the field or line, and the problem."""

    def __init__(self, source: str, field: str, problem: str) -> None:
        self.source = source
        self.field = field
        self.problem = problem
        where = f"{source}: {field}" if field else source
        super().__init__(f"{where}: {problem}")


class RobotFileError(InputFileError):
    """A robot description is malformed: the message names the file, the field, the problem."""


class ImplausibleDataWarning(UserWarning):
    """A recording looks odd (for instance a velocity column that disagrees with dq/dt)
    but could still be right: the command line prints it and goes on."""
