"""The gaitflow exception hierarchy.

Every error gaitflow raises on purpose is a :class:`GaitflowError`. Subclasses carry the
offending value and where it came from (stage, stream, file, key) in their message, so the
CLI can print one clear line and a supervisor can count it.
"""

from __future__ import annotations


class GaitflowError(Exception):
    """Root of all gaitflow errors."""


class ConfigError(GaitflowError):
    """A configuration file or value is missing or invalid."""


class ParameterError(ConfigError):
    """A declared stage parameter failed validation."""

    def __init__(self, stage: str, name: str, value: object, reason: str) -> None:
        self.stage, self.name, self.value, self.reason = stage, name, value, reason
        super().__init__(f"stage {stage!r}: parameter {name}={value!r} {reason}")


class SchemaError(GaitflowError):
    """A bus message could not be encoded or decoded.

    Carries the stream name and the field at fault.
    """

    def __init__(self, stream: str, field: str, reason: str) -> None:
        self.stream, self.field, self.reason = stream, field, reason
        super().__init__(f"stream {stream!r}: field {field!r}: {reason}")


class SchemaVersionError(SchemaError):
    """A message carries a schema version this build cannot read."""


class InputError(GaitflowError):
    """Bad input data: a file, a frame, a recording. Names the path and the problem."""

    def __init__(self, path: object, reason: str) -> None:
        self.path, self.reason = path, reason
        super().__init__(f"{path}: {reason}")


class FrameError(InputError):
    """A single frame is bad; the source skips it and counts it."""


class BusError(GaitflowError):
    """The Zenoh bus could not be opened or used."""


class StageError(GaitflowError):
    """A stage failed to start or to process a message."""

    def __init__(self, stage: str, reason: str) -> None:
        self.stage, self.reason = stage, reason
        super().__init__(f"stage {stage!r}: {reason}")


class DriverError(GaitflowError):
    """A live camera driver is missing or failed."""
