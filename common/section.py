"""The base of every profile section: a strict msgspec Struct decoded from TOML.

A section lives beside the code it configures (the task's in
:mod:`nwr.common.task`, the others in :mod:`nwr.common.config` for now) and
is assembled into the one :class:`nwr.common.config.Profile`: unknown fields
and out-of-range values are errors that name the field. This module imports
nothing of the project, so that any module may define its section.
"""

from __future__ import annotations

import msgspec


class Section(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """A profile section: fields with bounds (``msgspec.Meta``) and a comment each."""
