"""Typed errors of the optics engine.

Every error names what the user can act on: the file, the surface (1-based, as
in the prescription tables), the field and the allowed range.
"""
from __future__ import annotations

from ..errors import DcdiError, InputRangeError  # noqa: F401  (InputRangeError: re-exported)


class OpticsError(DcdiError):
    """Base class of the errors of ``dcdi_core.optics`` (lens files, glasses,
    aiming, import); a :class:`dcdi_core.errors.DcdiError`."""


class AfocalLensError(OpticsError, ValueError):
    """A prescription without paraxial power: no focal length, no focus, no
    sensor image (a ValueError too, as it was)."""


class LensFileError(OpticsError, ValueError):
    """A lens prescription (TOML file or dict) that breaks the schema.

    ``path`` is the file (or ``"<dict>"``), ``surface`` the 1-based surface
    number or ``None`` for top-level fields, ``field`` the key, ``value`` what
    was found and ``allowed`` what would have been accepted.
    """

    def __init__(self, path, message, *, surface=None, field=None, value=None, allowed=None):
        self.path = str(path)
        self.surface = surface
        self.field = field
        self.value = value
        self.allowed = allowed
        where = self.path
        if surface is not None:
            where += f", surface {surface}"
        if field is not None:
            where += f", field '{field}'"
        text = f"{where}: {message}"
        if value is not None:
            text += f" (got {value!r})"
        if allowed is not None:
            text += f"; allowed: {allowed}"
        super().__init__(text)


class UnknownGlassError(OpticsError, KeyError):
    """A glass name that is not in the catalogue (never silently substituted)."""

    def __init__(self, name, suggestions=()):
        self.name = name
        self.suggestions = tuple(suggestions)
        text = f"unknown glass {name!r}"
        if self.suggestions:
            text += "; did you mean " + ", ".join(repr(s) for s in self.suggestions) + "?"
        text += " (give model glass as {nd = ..., vd = ...} if it is not catalogued)"
        super().__init__(text)

    def raw(self) -> str:  # KeyError would quote the message
        return self.args[0]


class ZemaxImportError(OpticsError, ValueError):
    """A Zemax .zmx construct that cannot be imported; names file and line."""

    def __init__(self, path, line_number, line, message):
        self.path = str(path)
        self.line_number = line_number
        self.line = line
        if line_number:
            super().__init__(f"{self.path}:{line_number}: {message}: {line.strip()!r}")
        else:                                  # about the file as a whole (it cannot be read)
            super().__init__(f"{self.path}: {message}")


class AimingError(OpticsError, ValueError):
    """A field or depth for which no real chief ray exists (reported per call)."""
