"""Exception classes of DHG.

Every error DHG raises on bad input is a :class:`DhgError`. Input errors also subclass the builtin
a caller would expect (``ValueError``), so ``except ValueError`` keeps working. The native core
(``dhg._bone_sim``) raises these same classes: its error mapping looks them up here by name.
"""

from __future__ import annotations

__all__ = [
    "ERROR_KINDS",
    "CTImportError",
    "DhgError",
    "EngineError",
    "InvalidInputError",
    "ShapeError",
    "TransportError",
    "VolumeFileError",
]


class DhgError(Exception):
    """Base class of every DHG error."""


class InvalidInputError(DhgError, ValueError):
    """A value is out of range, NaN/infinite, or not one of the allowed options."""


class ShapeError(InvalidInputError):
    """Arrays whose shapes or lengths do not fit together."""


class CTImportError(DhgError, ValueError):
    """A file or folder that cannot be read as CT (not DICOM/NIfTI, no pixel data, mixed series)."""


class VolumeFileError(DhgError, ValueError):
    """A prepared volume file that is missing, truncated, corrupt, or of another format/version."""


class TransportError(DhgError, RuntimeError):
    """Zenoh could not open a session, bind an endpoint (e.g. the port is in use) or declare a key."""


class EngineError(DhgError, RuntimeError):
    """The real-time engine refused a request: not running, unknown session, or no free slot."""


#: The exception class of each error kind of the native core (``SimError::kind``), used both for
#: errors raised in-process and for the ``kind`` field of the server's error replies.
ERROR_KINDS: dict[str, type[DhgError]] = {
    "invalid_input": InvalidInputError,
    "shape": ShapeError,
    "transport": TransportError,
    "engine": EngineError,
}
