"""Write files so that a failed run never leaves a half-written output."""
from __future__ import annotations

import contextvars
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

from .errors import DcdiError, OutputError, output_error

# the job (``outputs.JobFiles``) whose declared outputs are renamed together, set by its ``together`` block
_ACTIVE: contextvars.ContextVar = contextvars.ContextVar("dcdi_job_files", default=None)


def _host_tag() -> str:
    import hashlib
    import socket
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


# who writes a temporary: a process (its pid, taken at each write: forks differ) on a
# host (a cluster's nodes share folders)
_HOST = _host_tag()
_OWNED = None                     # compiled on first use


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:        # another user's live process
        return True
    return True


def remove_dead_temporaries(path, *, foreign_after_s: float = 86400.0) -> list[Path]:
    """Remove the temporaries that runs killed while writing ``path`` left
    beside it: those of a process of this host that is gone, and those of
    other hosts (or of the older unowned form) untouched for
    ``foreign_after_s`` seconds. A live run's temporary is never touched.
    Returns what was removed."""
    import re
    import time
    global _OWNED
    if _OWNED is None:
        _OWNED = re.compile(r"\.p(\d+)_h([0-9a-f]{8})_[A-Za-z0-9_]+\.tmp(\.[A-Za-z0-9]+)?$")
    path = Path(path)
    folder, lead = path.parent, f".{path.name}."
    if not folder.is_dir():
        return []
    me, now, gone = _HOST, time.time(), []
    try:
        names = [e.name for e in os.scandir(folder) if e.name.startswith(lead) and ".tmp" in e.name]
    except OSError:
        return []
    for name in names:
        m = _OWNED.match(name[len(path.name) + 1:])
        p = folder / name
        try:
            if m and m.group(2) == me:
                dead = int(m.group(1)) != os.getpid() and not _alive(int(m.group(1)))
            else:
                dead = now - p.stat().st_mtime >= foreign_after_s
            if dead and p.is_file():
                p.unlink()
                gone.append(p)
        except OSError:
            continue
    return gone


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if
    the block succeeds (the temporary is removed otherwise).

    The temporary is ``.<name>.p<pid>_h<host>_<random>.tmp<suffix>`` in the
    target's folder: whose it is, so that a later run can remove it once its
    process is gone (:func:`remove_dead_temporaries`,
    :func:`remove_stale_temporaries`). An OSError (a read-only folder, a
    file where a folder should be, a full disk) becomes an
    :class:`~dcdi_core.errors.OutputError` naming ``path``.

    Inside a job's ``outputs.JobFiles.together`` block, a declared output's
    temporary is kept and renamed with the job's other outputs when the job
    succeeds (``outputs``)."""
    path = Path(path)
    job = active()
    later = job is not None and job.admit(path)      # a declared output: renamed with the job's others
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.p{os.getpid()}_h{_HOST}_", suffix=".tmp" + path.suffix, dir=path.parent)
        os.close(fd)
        yield Path(tmp)
        os.chmod(tmp, 0o644)  # mkstemp makes files owner-only
        if later:
            job.stage(tmp, path)
            tmp = None
        else:
            os.replace(tmp, path)
    except DcdiError:
        raise
    except OSError as e:
        raise output_error(path, e) from None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


TEMPORARY_PATTERN = ".*.*.tmp*"     # what atomic_path's temporaries look like


def remove_stale_temporaries(folder, *, older_than_s: float = 0.0, recursive: bool = True) -> list[Path]:
    """Remove the temporaries that :func:`atomic_path` left in ``folder`` when
    its process was killed between creating and renaming them; returns them.

    Only names of atomic_path's form (``.<name>.<random>.tmp[<suffix>]``)
    are touched, and only those last modified more than ``older_than_s``
    seconds ago (so that a concurrent writer's live temporary survives when
    given a margin)."""
    import re
    import time

    folder = Path(folder)
    if not folder.is_dir():
        return []
    form = re.compile(r"^\..+\.[A-Za-z0-9_]{6,}\.tmp(\.[A-Za-z0-9]+)?$")
    now = time.time()
    gone = []
    for p in (folder.rglob(".*") if recursive else folder.glob(".*")):
        try:
            if form.match(p.name) and p.is_file() and now - p.stat().st_mtime >= older_than_s:
                p.unlink()
                gone.append(p)
        except OSError:
            continue
    return gone


def backup_name(path) -> Path:
    """A name beside ``path`` for its previous version while a job's outputs
    are renamed together (a temporary's form: removed by the next run once
    this process is gone)."""
    import secrets
    path = Path(path)
    return path.with_name(f".{path.name}.p{os.getpid()}_h{_HOST}_{secrets.token_hex(4)}.tmp.bak")


def remove_file(path) -> None:
    """Remove ``path`` if it exists (a stale sidecar); inside a job's
    ``outputs.JobFiles.together`` block, when the job's outputs are renamed."""
    job = active()
    if job is not None:
        if os.path.lexists(path):
            job.remove_later(path)
        return
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    except OSError as e:
        raise output_error(path, e, "cannot remove the stale file") from None


def write_text(path, text: str) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)


def save_figure(fig, path, dpi: int = 100, **savefig) -> None:
    """Save a matplotlib figure atomically (PNG, or ``savefig``'s
    ``format``), read back whole before it is renamed into place; the
    figure is closed whatever happens."""
    import matplotlib.pyplot as plt

    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, **{"format": "png", **savefig})
            read_back_picture(tmp, path)
    finally:
        plt.close(fig)


def read_back_picture(tmp, path) -> None:
    """A picture just written to ``tmp`` (for ``path``), decoded whole
    (PIL, matplotlib's own writer): a writer that reported success on a full
    disk is an error here, not a file that cannot be opened."""
    from PIL import Image
    try:
        with Image.open(tmp) as im:
            im.load()
    except (OSError, ValueError, SyntaxError) as e:
        raise OutputError(path, f"the written picture cannot be read back (is the disk full?): {e}") from None


def active():
    """The job whose outputs are being written together, if any."""
    return _ACTIVE.get()
