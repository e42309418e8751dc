"""One signal policy for every long job (the `dcdi` command, the dataset
factory): SIGINT and SIGTERM alike stop the job at the next Python
instruction with :class:`Stopped` (a ``KeyboardInterrupt``, so that no
``except Exception`` swallows it); every ``atomic.atomic_path`` block on the
way out removes its temporary; the front end prints one line and exits 130
(SIGINT) or 143 (SIGTERM), as shells report them.

``timeout``, Slurm and systemd stop a job with SIGTERM; Ctrl-C sends SIGINT.

Two things delay a stop to a safe moment (:func:`deferred`): work that must
not be cut in half (a factory sample's files and its manifest line), and
calls into a host application that runs Python of its own (Blender's
operators, its handlers, Cycles' render engine): an exception raised inside
those is printed and dropped by Blender, so a stop raised there would be
lost and the job would go on.
"""
from __future__ import annotations

import signal
import threading
from contextlib import contextmanager

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Stopped(KeyboardInterrupt):
    """The job was asked to stop by ``signum`` (``exit_code``: 128 + signum)."""

    def __init__(self, signum: int = signal.SIGINT):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.exit_code = 128 + int(signum)
        self.word = "terminated" if signum == signal.SIGTERM else "interrupted"


def _raise(signum, frame):
    raise Stopped(signum)


def _handlers_to_replace(take_over: bool) -> dict:
    """{signal: the handler to put back after the block} of the signals the
    policy takes. An ignored signal (nohup, ``&`` in a script) is the
    user's choice and is left alone. A handler installed outside Python
    (getsignal: None, e.g. Blender's) is left alone too, unless
    ``take_over``; Python cannot put such a handler back, so Python's
    default comes back after the block instead."""
    old = {}
    for s in SIGNALS:
        h = signal.getsignal(s)
        if h is signal.SIG_IGN or (h is None and not take_over):
            continue
        if h is None:
            h = signal.default_int_handler if s == signal.SIGINT else signal.SIG_DFL
        old[s] = h
    return old


@contextmanager
def stop_on_signals(*, take_over: bool = False):
    """SIGINT and SIGTERM raise :class:`Stopped` inside the block (main
    thread only; elsewhere a no-op); the previous handlers come back after.
    A signal that is ignored keeps being ignored. A handler that a host
    application installed outside Python keeps its own handling, unless
    ``take_over``: a batch job that owns its process (the dataset factory
    under ``blender --background``) takes it. Blender's own SIGINT handler
    only sets a break flag, which its render polls (Blender 5.2.2, Cycles
    on two CPU cores, 640 x 480 at 400 samples: a 19.0 s render, stopped
    1.5 s in, returned at 18.6 s and wrote no file) and Python code never
    sees; a second Ctrl-C then kills Blender (exit 2) with nothing cleaned
    up."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = _handlers_to_replace(take_over)
    for s in old:
        signal.signal(s, _raise)
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


@contextmanager
def deferred():
    """Inside the block a SIGINT or SIGTERM that :func:`stop_on_signals`
    handles is only noted; when the block ends (without an exception of its
    own) the first one noted is raised as :class:`Stopped`. For a commit
    that must not be cut in half, and for calls into Blender (which drops
    an exception raised in its Python callbacks: the stop would be lost).
    The stop then waits for the block: a render's seconds. Nested blocks,
    other threads and signals the policy does not handle: no change."""
    ours = ([s for s in SIGNALS if signal.getsignal(s) is _raise]
            if threading.current_thread() is threading.main_thread() else [])
    noted = []
    for s in ours:
        signal.signal(s, lambda signum, frame: noted.append(signum))
    try:
        yield
    finally:
        for s in ours:
            signal.signal(s, _raise)
    if noted:
        raise Stopped(noted[0])


def stop_code(e: KeyboardInterrupt) -> tuple[int, str]:
    """(exit code, 'interrupted' or 'terminated') of a stop."""
    if isinstance(e, Stopped):
        return e.exit_code, e.word
    return 130, "interrupted"
