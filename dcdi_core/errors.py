"""The error family of dcdi: one root, :class:`DcdiError`.

Every error a user can cause (a bad file, option, value, folder, or work too
large for this machine) is a ``DcdiError`` with a message that says what to
change: which file or option, what was found, what is allowed. The ``dcdi``
command and the dataset factory catch the root, print its message on one
line and exit 2; any other exception is a bug.

Below the root (each subclass also derives from the builtin a caller would
expect, so ``except ValueError`` keeps working where it did):

- ``optics.errors.OpticsError``: lens files, glasses, ray aiming, Zemax import;
- :class:`InputRangeError`: an argument outside its allowed range;
- ``io.images.ImageFileError``: an image or depth file;
- ``psf.spectral.SpectralFileError``: a sensor response file;
- :class:`RenderError`: simulation and bokeh inputs (depth maps, images);
- :class:`OutputError`: a file or folder that cannot be written;
- :class:`MemoryLimitError`: work that would not fit in memory;
- :class:`DatasetError`: a dataset folder (the factory's) that does not match;
- :class:`ModelError`: the networks (weights, configs, checkpoints).
"""
from __future__ import annotations

import errno
import os
import re

# A request's field named inside a message: ``field("method")``. Each front
# end shows it in its own words (``DcdiError.in_words``: the CLI's options,
# the add-on's panel labels); plain ``str()`` shows the field's own name.
_FIELD = re.compile("\u2039([A-Za-z_][A-Za-z0-9_.]*)\u203a")


def field(name: str) -> str:
    """The marker of the request field ``name`` in an error message."""
    return f"\u2039{name}\u203a"


def in_words(text: str, words=None) -> str:
    """``text`` with each field marker replaced by ``words[name]`` (default: the name itself)."""
    words = words or {}
    return _FIELD.sub(lambda m: words.get(m.group(1)) or m.group(1), text)


class DcdiError(Exception):
    """The root of every error meant for the user. Its message may name the
    fields of the request (:func:`field`); :meth:`in_words` shows them in a
    front end's words."""

    def raw(self) -> str:
        return Exception.__str__(self)

    def in_words(self, words=None) -> str:
        return in_words(self.raw(), words)

    def __str__(self):
        return self.in_words()


class InputRangeError(DcdiError, ValueError):
    """An argument outside its allowed range (names the argument and range).

    ``value=None`` means the argument is missing: the message then says what
    is needed instead of calling None out of range. A ``name`` that is an
    identifier is a request's field (shown in a front end's words)."""

    def __init__(self, name, value, allowed):
        if isinstance(name, str) and _FIELD.fullmatch(name):
            name = name[1:-1]                   # given as a field marker: the field's name
        self.name = name
        self.value = value
        self.allowed = allowed
        if isinstance(name, str) and name.isidentifier():
            name = field(name)
        if value is None:
            text = f"{name} is missing; needed: {allowed}"
        else:
            text = f"{name} = {value!r} is out of range; allowed: {allowed}"
        super().__init__(text)


class RenderError(DcdiError, ValueError):
    """Simulation or bokeh input that cannot be rendered (a depth map with
    no valid pixel, negative light, ...)."""


class OutputError(DcdiError, OSError):
    """A file or folder that cannot be written (read-only, not a folder,
    disk full); ``path`` is what could not be written."""

    def __init__(self, path, message):
        self.path = str(path)
        DcdiError.__init__(self, f"{self.path}: {message}")

    def raw(self) -> str:
        return self.args[0]


class MemoryLimitError(DcdiError, MemoryError):
    """Work that would not fit in this machine's memory (estimated before it
    starts, or a MemoryError caught while it ran)."""


class DatasetError(DcdiError, ValueError):
    """A dataset folder whose contents do not match the run (another run's
    settings, a file where a folder should be)."""


class ModelError(DcdiError, ValueError):
    """A network's weights, configuration or checkpoint that cannot be used."""


def output_error(path, exc: OSError, what: str = "cannot write here") -> OutputError:
    """An :class:`OutputError` for an OSError met while writing ``path``."""
    reason = {errno.EACCES: "permission denied (read-only folder?)", errno.EPERM: "permission denied",
              errno.EROFS: "read-only file system", errno.ENOSPC: "no space left on the device",
              errno.ENOTDIR: "a file stands where a folder is needed",
              errno.EEXIST: "a file stands where a folder is needed",
              errno.EISDIR: "a folder stands where a file is needed"}.get(exc.errno, exc.strerror or str(exc))
    at = getattr(exc, "filename", None)
    at = f" (at {at})" if at and os.path.abspath(os.fspath(at)) != os.path.abspath(os.fspath(path)) else ""
    return OutputError(path, f"{what}: {reason}{at}")


def check_writable_folder(folder, what: str) -> None:
    """Refuse, before any work, a folder that cannot be created or written.

    ``what`` names the option or setting it comes from (``-o``, the PSF
    cache). The folder is not created: only its nearest existing ancestor is
    checked (it must be a folder and writable)."""
    folder = os.path.abspath(os.fspath(folder))
    probe = folder
    while not os.path.exists(probe):
        parent = os.path.dirname(probe)
        if parent == probe:
            break
        probe = parent
    if not os.path.isdir(probe):
        raise OutputError(folder, f"{what}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise OutputError(folder, f"{what}: the folder {probe} is not writable (read-only?)")


# --- the networks' and model files' errors (below ModelError)
class TorchMissingError(ModelError, ImportError):
    """PyTorch is needed (training, export) but not installed."""


class ModelFileError(ModelError, ValueError):
    """An exported model or checkpoint file that cannot be used (names the file and field)."""

    def __init__(self, path, message, *, field=None, allowed=None):
        self.path = str(path)
        self.field = field
        self.allowed = allowed
        text = self.path + (f", field '{field}'" if field is not None else "") + f": {message}"
        if allowed is not None:
            text += f"; allowed: {allowed}"
        super().__init__(text)


class LensMismatchError(ModelError, ValueError):
    """A lens whose prescription differs from the one a model learned (or a lens it never learned)."""


class CheckpointMismatchError(ModelError, ValueError):
    """A checkpoint written with other settings than the run that would resume it."""

    def __init__(self, path, differences: dict):
        self.path = str(path)
        self.differences = dict(differences)
        lines = "; ".join(f"{k}: checkpoint {a!r}, now {b!r}" for k, (a, b) in sorted(self.differences.items()))
        super().__init__(f"{self.path}: written with other settings, not resumed ({lines}); "
                         "run with the checkpoint's settings, or use another run folder to start afresh")


class OutsideTrainedRangeError(InputRangeError, ModelError):
    """A request outside the ranges a model was trained on (names the file, the input and the range)."""

    def __init__(self, path, name, value, allowed):
        super().__init__(name, value, allowed)
        self.path = str(path)
        self.args = (f"{self.path}: {self.args[0]} (the range this model was trained on; "
                     "trace the PSF instead)",)
