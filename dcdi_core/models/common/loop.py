"""The training loop every network here shares: open or resume a run folder,
step with the learning-rate schedule and the EMA of the weights, checkpoint
atomically, validate, log, report progress; under ``torchrun``, share each
global batch among the processes.

A network brings only what is its own, as a :class:`Network`: its data, its
model and optimiser, how a batch is drawn, its loss, its validation scores
and which extra fields its checkpoint carries. :func:`train_network` does the
rest, the same way for all:

- the run folder: ``config.json`` (the settings), the network's own records
  (``Network.write_records``), ``checkpoint.pt`` and ``log.jsonl``;
- the checkpoint (``checkpoint.training_state``), written atomically every
  ``checkpoint_every`` iterations and at the end: weights, EMA weights,
  optimiser state, iteration, validation history, torch's RNG state and the
  batch generator's state (numpy PCG64 seeded ``[seed, Network.stream]``);
- resume: a checkpoint written with other result settings, or on other data
  (``Network.data_key``), is refused naming them; otherwise everything a step
  depends on is either in the checkpoint or rebuilt from the config and the
  data in the same order as a fresh run, so a run killed at any point and
  started again ends bit for bit where an uninterrupted one would (same
  thread count, same device kind);
- each step: the network's batch, its loss, the optimiser step at
  ``config.lr_at(step)``, then the EMA with ``config.ema_decay``;
- ``log.jsonl``: a record every ``validate_every`` iterations (0: none) and a
  final one, each with the step, the loss, the training seconds, this
  session's iterations per second, the network's scores and where it ran.

``device`` and the number of processes are not settings (a checkpoint
resumes on another device or world size); rank 0 alone writes the folder.
"""
from __future__ import annotations

import json
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...atomic import write_text
from .. import require_torch
from .checkpoint import check_data, make_ema, open_run, restore, save_checkpoint, training_state, update
from .distributed import Context, LossModule, resolve_device

torch = require_torch()


class Network(ABC):
    """What one network brings to the loop; subclass it and fill in the
    abstract methods. ``config`` is its training config: ``seed``, ``iters``,
    ``batch``, ``ema_decay``, ``checkpoint_every``, ``threads``,
    ``lr_at(step)``, ``result_settings()`` and ``to_json()``."""

    stream: int                     # second word of the batch generator's seed: each network its own draws
    data_what: str = "data"         # what a refused resume on other data names
    # False: ``seconds`` counts the training time of every session so far (kept in the checkpoint)
    session_seconds: bool = True

    def __init__(self, config):
        self.config = config

    @property
    def validate_every(self) -> int:
        """Iterations between validation records (0: only the final one)."""
        return self.config.validate_every

    @abstractmethod
    def open_data(self, run_dir: Path, say):
        """The run's data (rank 0 first, the others after it: it may write shared files)."""

    @abstractmethod
    def data_key(self, data) -> str:
        """A hash of what the data holds; a checkpoint resumes only on data with its key."""

    def write_records(self, run_dir: Path, data) -> None:
        """Files beside ``config.json`` that say what the run trained on (rank 0)."""

    @abstractmethod
    def build(self, data):
        """The model, on the CPU (torch has just been seeded with ``config.seed``)."""

    @abstractmethod
    def optimizer(self, model):
        """The optimiser of ``model``'s parameters (the loop sets its learning rate each step)."""

    @abstractmethod
    def batches(self, data):
        """``draw(rng, rows, device)``: this rank's ``rows`` of the next global
        batch of ``config.batch`` as a tuple of the loss's arguments."""

    @abstractmethod
    def loss(self, model, *batch):
        """The mean loss of ``batch`` (a scalar tensor)."""

    def unused_parameters(self, data) -> bool:
        """Whether a rank's share may leave some parameters unused (DistributedDataParallel must know)."""
        return False

    def checkpoint_extra(self) -> dict:
        """Fields a checkpoint carries besides the training state (what export reads)."""
        return {}

    def validate(self, model, ema, data) -> dict:
        """The periodic log record's scores (rank 0); by default the final record's."""
        return self.final(model, ema, data)[1]

    @abstractmethod
    def final(self, model, ema, data) -> tuple[dict, dict]:
        """(the result's validation, the final log record's scores) (rank 0)."""


@dataclass
class Trained:
    """What a finished (or already finished) run hands back; models on the CPU."""

    model: object
    ema: object
    data: object
    step: int
    seconds: float                  # training time, s (data excluded; see Network.session_seconds)
    history: list = field(default_factory=list)     # the periodic log records
    validation: dict = field(default_factory=dict)  # Network.final's; rank 0 only
    where: dict = field(default_factory=dict)       # device and world size of this session


def train_network(net: Network, run_dir, *, device: str = "cpu", distributed: bool = True, progress=None,
                  on_step=None, log=None) -> Trained:
    """Train (or resume) ``net`` in ``run_dir``. ``progress(step, iters,
    loss)`` after each step; ``on_step(step)`` too (an exception there stops
    the run as a kill would: after the step and any checkpoint due at it).
    ``log(text)``: what the run says (resumed where, validation). ``device``:
    auto, cpu, cuda or cuda:N; ``distributed``: join torchrun's processes
    when it started several (False: this process alone)."""
    ctx = Context.from_environment(device) if distributed else Context(device=resolve_device(device))
    try:
        result = _Run(net, run_dir, ctx, log).train(progress if ctx.main else None, on_step)
    except BaseException:
        ctx.close(clean=False)      # a failed rank must not wait for the others at a barrier
        raise
    ctx.close()
    return result


def _quiet(text: str) -> None:
    pass


def append_record(path: Path, record: dict) -> None:
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(record) + "\n")


class _Run:
    """One session of a run: its objects after opening or resuming it."""

    def __init__(self, net: Network, run_dir, ctx: Context, log):
        self.net, self.ctx, self.config = net, ctx, net.config
        self.say = (log or _quiet) if ctx.main else _quiet
        self.rows = ctx.part(self.config.batch)             # refused before any work
        ck = self._open(run_dir)
        self._build(ck)
        self.where = ctx.record()
        self.t0 = time.perf_counter()

    def _open(self, run_dir) -> dict | None:
        """The folder, the data and the checkpoint to resume (None: a fresh run), both checked."""
        net, ctx = self.net, self.ctx
        self.dir, self.ckpt_path, self.settings, ck = open_run(run_dir, self.config)
        with ctx.main_first():
            self.data = net.open_data(self.dir, self.say)
        self.key = net.data_key(self.data)
        check_data(ck, self.ckpt_path, self.key, net.data_what)
        if ctx.main:
            write_text(self.dir / "config.json", self.config.to_json() + "\n")
            net.write_records(self.dir, self.data)
        return ck

    def _build(self, ck: dict | None) -> None:
        """Model, EMA, optimiser and batch generator, as a fresh run makes
        them (torch seeded once, then the model drawn), then all a
        checkpoint carries put back."""
        net, config = self.net, self.config
        torch.manual_seed(config.seed)
        self.model = net.build(self.data).to(self.ctx.device)
        self.ema = make_ema(self.model)
        self.opt = net.optimizer(self.model)
        self.rng = np.random.default_rng([config.seed, net.stream])
        self.draw = net.batches(self.data)
        self.step, self.history = restore(ck, self.model, self.ema, self.opt, self.rng, say=self.say,
                                          path=self.ckpt_path, iters=config.iters)
        self.first_step = self.step
        self.prior_s = 0.0 if ck is None or net.session_seconds else float(ck.get("seconds", 0.0))
        self.step_loss = self.ctx.wrap(LossModule(self.model, net.loss),
                                       find_unused_parameters=net.unused_parameters(self.data))

    def seconds(self) -> float:
        """Training time so far, s: this session's, plus the earlier ones' unless session_seconds."""
        return self.prior_s + time.perf_counter() - self.t0

    def train(self, progress, on_step) -> Trained:
        config, iters = self.config, self.config.iters
        self.model.train()
        loss = float("nan")
        while self.step < iters:
            batch = self.draw(self.rng, self.rows, self.ctx.device)
            value = self.step_loss(*batch)
            update(self.opt, value, config.lr_at(self.step), self.model, self.ema, config.ema_decay)
            self.step += 1
            loss = self.ctx.mean(value.detach())
            every = self.net.validate_every
            if self.ctx.main and every and self.step % every == 0 and self.step < iters:
                self.validate(loss)
            if self.step % config.checkpoint_every == 0 or self.step == iters:
                self.checkpoint()
            if progress:
                progress(self.step, iters, loss)
            if on_step:
                on_step(self.step)
        return self.finish(loss)

    def record(self, loss: float, seconds: float, scores: dict, **extra) -> dict:
        """A log record; ``seconds`` taken before the scores, which are not training time."""
        rate = (self.step - self.first_step) / max(seconds - self.prior_s, 1e-9)
        return {"step": self.step, "loss": loss, "seconds": seconds, "it_per_s": rate, **scores, **extra,
                **self.where}

    def validate(self, loss: float) -> None:
        seconds = self.seconds()
        scores = self.net.validate(self.model, self.ema, self.data)
        rec = self.record(loss, seconds, scores)
        self.history.append(rec)
        append_record(self.dir / "log.jsonl", rec)
        self.say(f"iteration {self.step}: loss {loss:.4g}, " + ", ".join(f"{k} {v}" for k, v in scores.items()))

    def checkpoint(self) -> None:
        if self.ctx.main:
            extra = self.net.checkpoint_extra()
            if not self.net.session_seconds:
                extra["seconds"] = self.seconds()
            save_checkpoint(self.ckpt_path, training_state(
                step=self.step, settings=self.settings, config_json=self.config.to_json(), data_key=self.key,
                model=self.model, ema=self.ema, opt=self.opt, rng=self.rng, history=self.history, **extra))
        self.ctx.barrier()          # the others go on only once the checkpoint is on disk

    def finish(self, loss: float) -> Trained:
        seconds = self.seconds()
        validation = {}
        if self.ctx.main:
            validation, scores = self.net.final(self.model, self.ema, self.data)
            append_record(self.dir / "log.jsonl", self.record(loss, seconds, scores, final=True))
        return Trained(self.model.cpu(), self.ema.cpu(), self.data, self.step, seconds, self.history, validation,
                       self.where)
