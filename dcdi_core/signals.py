"""One signal policy for every long job (the `dcdi` command, the dataset
factory): SIGINT and SIGTERM alike stop the job at the next Python
instruction with :class:`Stopped` (a ``KeyboardInterrupt``, so that no
``except Exception`` swallows it); every ``atomic.atomic_path`` block on the
way out removes its temporary; the front end prints one line and exits 130
(SIGINT) or 143 (SIGTERM), as shells report them.

``timeout``, Slurm and systemd stop a job with SIGTERM; Ctrl-C sends SIGINT.
"""
from __future__ import annotations

import signal
from contextlib import contextmanager


class Stopped(KeyboardInterrupt):
    """The job was asked to stop by ``signum`` (``exit_code``: 128 + signum)."""

    def __init__(self, signum: int = signal.SIGINT):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.exit_code = 128 + int(signum)
        self.word = "terminated" if signum == signal.SIGTERM else "interrupted"


def _raise(signum, frame):
    raise Stopped(signum)


@contextmanager
def stop_on_signals():
    """SIGINT and SIGTERM raise :class:`Stopped` inside the block (main
    thread only; elsewhere a no-op); the previous handlers come back after.
    A signal whose handler Python did not install (a host application's,
    such as Blender's) or that is ignored keeps its own handling."""
    import threading
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    # a handler installed outside Python (getsignal: None, Blender's own) or
    # one that ignores the signal is the host's choice: left as it is
    old = {s: h for s in (signal.SIGINT, signal.SIGTERM)
           if (h := signal.getsignal(s)) is not None and h is not signal.SIG_IGN}
    for s in old:
        signal.signal(s, _raise)
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def stop_code(e: KeyboardInterrupt) -> tuple[int, str]:
    """(exit code, 'interrupted' or 'terminated') of a stop."""
    if isinstance(e, Stopped):
        return e.exit_code, e.word
    return 130, "interrupted"
