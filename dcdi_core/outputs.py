"""Every path a job writes: declared before any work, checked in one place,
written together.

A job (a `dcdi` verb; the add-on's and the factory's jobs may use it too)
names what it reads and what it writes in a :class:`JobFiles` before it
starts. :meth:`JobFiles.check` then refuses, before any work:

- an output that is one of the inputs, by any path: the same name, a
  symbolic link to it, or a hard link (the same device and inode);
- two outputs that are one file (``-o`` and ``--confidence`` alike);
- a file output where a folder stands, or whose folder cannot be created
  or written (read-only, or a file in its place);

and removes the temporaries a killed earlier run left beside each output
(``atomic.remove_dead_temporaries``: never a live run's).

Inside :meth:`JobFiles.together` every ``atomic.atomic_path`` block whose
target is a declared output file writes its temporary as usual but does
not rename it: the renames happen together when the job has succeeded
(none happens when it fails or is stopped), and an image's sidecar goes
with its image. A rename that fails half-way puts back what the earlier
renames replaced. Writes into a declared output folder (a training run's
checkpoints, a report's pages) and into the PSF cache happen at once, as
before: they are the job's progress, not its result. A write to any other
path is a bug of the job's declaration: it is recorded
(``JobFiles.undeclared``), and raises where ``DCDI_CHECK_OUTPUTS=1`` (the
test suite sets it), so that a new option cannot skip the declaration.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from .atomic import _ACTIVE, active, backup_name, remove_dead_temporaries
from .errors import DcdiError, InputRangeError, OutputError, check_writable_folder, output_error
from .shipped import is_shipped_file



class UndeclaredOutputError(AssertionError):
    """A job wrote a path it did not declare (a bug of the job, not the user's)."""


@dataclass(frozen=True)
class Named:
    """A path and how the user named it (``-o out.exr``, ``--save-intermediates DIR: depth.exr``)."""
    path: Path
    label: str


def _identity(path: Path):
    """(device, inode) of an existing file or folder, else None."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def _real(path: Path) -> str:
    return os.path.realpath(os.path.abspath(os.fspath(path)))


@dataclass
class JobFiles:
    """What a job reads (``inputs``: files or folders) and writes
    (``outputs``: files; ``folders``: folders it writes into; ``updated``:
    input folders it records a file in)."""
    inputs: list = field(default_factory=list)
    outputs: list = field(default_factory=list)
    folders: list = field(default_factory=list)
    updated: list = field(default_factory=list)
    undeclared: list = field(default_factory=list)

    # ------------------------------------------------------------ declaring
    def read(self, path, label: str) -> "JobFiles":
        if path is not None and str(path):
            self.inputs.append(Named(Path(path), label))
        return self

    def write(self, path, label: str) -> "JobFiles":
        if path is not None and str(path):
            self.outputs.append(Named(Path(path), label))
        return self

    def write_into(self, folder, label: str) -> "JobFiles":
        if folder is not None and str(folder):
            self.folders.append(Named(Path(folder), label))
        return self

    def add_to(self, folder, label: str) -> "JobFiles":
        """An input folder the job also records a file in (a training run
        records the split by scene in its pairs folder): writes there happen
        at once; only the named inputs themselves are never written."""
        if folder is not None and str(folder):
            self.updated.append(Named(Path(folder), label))
        return self

    # ------------------------------------------------------------ the check
    def check(self) -> None:
        """Refuse (before any work) what :mod:`this module <dcdi_core.outputs>`
        lists; then remove dead runs' temporaries beside the outputs."""
        by_real, by_id = {}, {}
        for i in self.inputs:
            by_real.setdefault(_real(i.path), i)
            ident = _identity(i.path)
            if ident is not None:
                by_id.setdefault(ident, i)
        seen_real, seen_id = {}, {}
        for o in self.outputs:
            real, ident = _real(o.path), _identity(o.path)
            hit = by_real.get(real) or (by_id.get(ident) if ident is not None else None)
            if hit is not None:
                raise InputRangeError(o.label, str(o.path), f"a file other than the input {hit.label} "
                                      f"{hit.path} (writing it would replace what this command reads)")
            other = seen_real.get(real) or (seen_id.get(ident) if ident is not None else None)
            if other is not None:
                raise InputRangeError(o.label, str(o.path), f"a file other than {other.label} {other.path} (both "
                                      "would be written to one file)")
            seen_real[real] = o
            if ident is not None:
                seen_id[ident] = o
            if o.path.is_dir():
                raise OutputError(o.path, f"{o.label}: a folder stands where the file is to be written")
            if is_shipped_file(o.path):     # a shipped store is every job's input, whether named or not
                raise InputRangeError(o.label, str(o.path), "a file other than one the engine ships (its ray "
                                      "maps, PSF bases, weights and lenses are read by every job: writing one "
                                      "would replace it)")
            check_writable_folder(Path(os.path.abspath(o.path)).parent, f"{o.label} {o.path}")
        for f in self.folders:
            ident = _identity(f.path)
            hit = by_real.get(_real(f.path)) or (by_id.get(ident) if ident is not None else None)
            if hit is not None:
                raise InputRangeError(f.label, str(f.path), f"a folder other than the input {hit.label} {hit.path}")
            if f.path.exists() and not f.path.is_dir():
                raise OutputError(f.path, f"{f.label}: a file stands where the folder is to be written")
            check_writable_folder(f.path, f"{f.label} {f.path}")
        for o in self.outputs:
            remove_dead_temporaries(o.path)

    # ------------------------------------------------------------ writing together
    def _output(self, path: Path) -> Named | None:
        real = _real(path)
        return next((o for o in self.outputs if _real(o.path) == real), None)

    def _inside_folder(self, path: Path) -> bool:
        real = _real(path)
        roots = [_real(f.path) for f in (*self.folders, *self.updated)]
        try:
            roots.append(_real(default_cache_dir()))
        except Exception:           # no cache configured: nothing to allow
            pass
        return any(real == r or real.startswith(r.rstrip(os.sep) + os.sep) for r in roots)

    def _refuse_input(self, path: Path) -> None:
        """At the moment of writing: never onto an input (a derived name the
        check could not foresee, such as a file inside an output folder)."""
        real, ident = _real(path), _identity(path)
        for i in self.inputs:
            if real == _real(i.path) or (ident is not None and ident == _identity(i.path)):
                raise OutputError(path, f"refused: it is the input {i.label} {i.path}; nothing was written")

    def admit(self, path) -> bool:
        """Called by ``atomic.atomic_path`` for each file it writes: True
        when the rename waits for :meth:`commit` (a declared output)."""
        path = Path(path)
        self._refuse_input(path)
        if self._output(path) is not None:
            return True
        if not self._inside_folder(path):
            self.undeclared.append(path)
            if os.environ.get("DCDI_CHECK_OUTPUTS") == "1":
                raise UndeclaredOutputError(f"the job writes {path}, which it did not declare (JobFiles)")
        return False

    def stage(self, tmp, path) -> None:
        """A finished temporary ``tmp`` that becomes ``path`` at the commit."""
        self._staged.append((Path(tmp), Path(path)))

    def remove_later(self, path) -> None:
        """A file to remove at the commit (a stale sidecar): a declared output too."""
        path = Path(path)
        self._refuse_input(path)
        if self._output(path) is None and not self._inside_folder(path):
            self.undeclared.append(path)
            if os.environ.get("DCDI_CHECK_OUTPUTS") == "1":
                raise UndeclaredOutputError(f"the job removes {path}, which it did not declare (JobFiles)")
        self._removals.append(path)

    @contextmanager
    def together(self):
        """The block's declared outputs are renamed into place together when
        it succeeds; when it fails (or is stopped) none is, and every
        temporary is removed."""
        self._staged, self._removals = [], []
        token = _ACTIVE.set(self)
        try:
            yield self
        except BaseException:
            _ACTIVE.reset(token)
            self._discard()
            raise
        _ACTIVE.reset(token)
        self._commit()                   # a stop during the renames puts back what they replaced

    def _discard(self) -> None:
        for tmp, _ in self._staged:
            _unlink(tmp)
        self._staged, self._removals = [], []

    def _commit(self) -> None:
        """Rename every staged temporary onto its output, and remove the
        stale files; on a failure half-way, put back what was replaced."""
        done = []                     # (path, its backup or None)
        current = None
        try:
            moves = list(self._staged) + [(None, p) for p in self._removals]
            for tmp, path in moves:
                current = path
                existed = os.path.lexists(path) and not os.path.isdir(path)
                backup = _link_aside(path, backup_name(path)) if existed else None
                done.append((path, backup, existed))
                if tmp is not None:
                    os.replace(tmp, path)
                elif os.path.lexists(path):
                    os.unlink(path)
        except BaseException as e:
            for path, backup, existed in reversed(done):
                try:
                    if backup is not None:
                        os.replace(backup, path)
                    elif not existed and os.path.lexists(path):
                        os.unlink(path)
                except OSError:
                    pass
            self._discard()
            if isinstance(e, OSError) and not isinstance(e, DcdiError):
                raise output_error(current, e) from None
            raise
        for _, backup, _ in done:
            if backup is not None:
                _unlink(backup)
        self._staged, self._removals = [], []


def _link_aside(path, backup):
    """A second name for the file at ``path`` (a hard link: the file stays
    in place, and removing the link later loses nothing), or None where the
    file system has no hard links (then no putting back for it)."""
    try:
        os.link(path, backup, follow_symlinks=False)
        return backup
    except OSError:
        return None


def _unlink(path) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass




@contextmanager
def scratch_folder():
    """A temporary folder for a job's own intermediate files (a bench's
    inputs), removed afterwards; the job may write there without declaring
    each file."""
    import tempfile
    with tempfile.TemporaryDirectory(prefix="dcdi-") as d:
        job = active()
        if job is not None:
            job.folders.append(Named(Path(d), "scratch"))
        yield d


def size_of(path) -> int:
    """Bytes of the file written to ``path``: its staged temporary while the
    job's outputs wait to be renamed together, else the file itself."""
    job = active()
    if job is not None:
        real = _real(Path(path))
        for tmp, target in reversed(job._staged):
            if _real(target) == real:
                return os.path.getsize(tmp)
    return os.path.getsize(path)


def default_cache_dir() -> Path:
    """The PSF libraries' cache folder: $DCDI_CACHE_DIR, else $XDG_CACHE_HOME/dcdi/psflib (~/.cache); a job may
    write there without declaring it."""
    env = os.environ.get("DCDI_CACHE_DIR")
    base = Path(env) if env else Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "dcdi"
    return base / "psflib"
