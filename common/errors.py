"""The project's exception hierarchy.

Messages name the value, the limit and what to do about it, so that a user
reading a log line can act on it without opening the code.
"""


class NwrError(Exception):
    """Base of every error this project raises on purpose."""


class ConfigError(NwrError):
    """A profile, robot description or script is missing, malformed or out of range."""


class DecodeError(NwrError):
    """A wire message could not be decoded into its registered type."""


class SafetyError(NwrError):
    """A command or state violates the robot's safety envelope."""


class StudyError(NwrError):
    """A study's answer store or a submission to it is refused (wrong version, out of scale, a duplicate, ...)."""
