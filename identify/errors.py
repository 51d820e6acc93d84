"""The identification core's errors and warnings: the branch of armid's one exception tree
(drawn in :mod:`armid.schema.errors`) that this package raises."""

from __future__ import annotations

from armid.schema.errors import (
    ArmidError,
    IdentificationError,
    ImplausibleDataWarning,
    InputError,
    InputFileError,
    OptionError,
    PoorExcitationWarning,
    RecordingError,
    RobotFileError,
    TrajectoryLimitError,
    UsageError,
)

__all__ = ["ArmidError", "IdentificationError", "ImplausibleDataWarning", "InputError", "InputFileError", "OptionError",
           "PoorExcitationWarning", "RecordingError", "RobotFileError", "TrajectoryLimitError", "UsageError"]
