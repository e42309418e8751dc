"""The shared training loop (models.common.loop) on a toy network: a killed
run resumes to the uninterrupted weights and history, checkpoints and
validation records fall where the config says, other settings or other data
are refused by name, and the training time is kept per session or over
sessions as the network says."""
import json
from dataclasses import asdict, dataclass, replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import Killed, kill_at  # noqa: E402

from dcdi_core.models import CheckpointMismatchError  # noqa: E402
from dcdi_core.models.common.config import OPERATIONAL, JSONConfig  # noqa: E402
from dcdi_core.models.common.loop import Network, train_network  # noqa: E402


@dataclass(frozen=True)
class ToyConfig(JSONConfig):
    data_seed: int = 0
    iters: int = 6
    lr: float = 0.05
    checkpoint_every: int = 3
    validate_every: int = 2
    # fixed here (not fields): what the loop reads besides
    batch, ema_decay, seed, threads = 4, 0.5, 0, 1

    def as_dict(self) -> dict:
        return asdict(self)

    def result_settings(self) -> dict:
        # data_seed picks the data as the DACN's folder does: not a setting, the data key judges it
        return {k: v for k, v in self.as_dict().items() if k not in OPERATIONAL + ("data_seed",)}

    def lr_at(self, step: int) -> float:
        return self.lr / (1 + step)


class Toy(Network):
    """Least squares of y = x @ w on 32 seeded samples, batches drawn at random."""

    stream = 99
    data_what = "toy data"

    def __init__(self, config, session_seconds=True):
        super().__init__(config)
        self.session_seconds = session_seconds

    def open_data(self, run_dir, say):
        rng = np.random.default_rng(self.config.data_seed)
        x = rng.normal(size=(32, 3)).astype(np.float32)
        return x, (x @ np.array([1.0, -2.0, 0.5], np.float32))[:, None]

    def data_key(self, data) -> str:
        return str(self.config.data_seed)

    def build(self, data):
        return torch.nn.Linear(3, 1)

    def optimizer(self, model):
        return torch.optim.SGD(model.parameters(), lr=self.config.lr)

    def batches(self, data):
        x, y = data

        def draw(rng, rows, device):
            i = rng.integers(0, len(x), self.config.batch)[rows]
            return torch.from_numpy(x[i]).to(device), torch.from_numpy(y[i]).to(device)
        return draw

    def loss(self, model, x, y):
        return ((model(x) - y) ** 2).mean()

    def final(self, model, ema, data):
        x, y = (torch.from_numpy(a) for a in data)
        with torch.no_grad():
            scores = {"mse_ema": float(((ema(x) - y) ** 2).mean()), "mse": float(((model(x) - y) ** 2).mean())}
        return scores, scores

    def checkpoint_extra(self) -> dict:
        return {"kind": "toy"}


def _records(run):
    return [json.loads(s) for s in (run / "log.jsonl").read_text().splitlines()]


def _without_times(records):
    return [{k: v for k, v in r.items() if k not in ("seconds", "it_per_s")} for r in records]


def test_a_killed_run_resumes_to_the_uninterrupted_weights_and_history(tmp_path):
    torch.set_num_threads(1)
    config = ToyConfig()
    saved, seen = [], []
    straight = train_network(Toy(config), tmp_path / "a", progress=lambda s, n, loss: seen.append((s, n)))
    assert seen == [(s, 6) for s in range(1, 7)] and straight.step == 6
    assert [r["step"] for r in _records(tmp_path / "a")] == [2, 4, 6] and _records(tmp_path / "a")[-1]["final"]
    assert straight.validation == {k: v for k, v in _records(tmp_path / "a")[-1].items() if k.startswith("mse")}
    # killed after step 4: the checkpoint at 3 holds the record of step 2; 4 is redone
    with pytest.raises(Killed):
        train_network(Toy(config), tmp_path / "b", on_step=kill_at(4))
    ck = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)
    saved.append(ck["step"])
    assert saved == [3] and ck["kind"] == "toy" and "seconds" not in ck
    said = []
    resumed = train_network(Toy(config), tmp_path / "b", log=said.append)
    assert said[0].endswith("at iteration 3 of 6")
    for a, b in ((straight.model, resumed.model), (straight.ema, resumed.ema)):
        assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    assert _without_times(resumed.history) == _without_times(straight.history)
    assert resumed.seconds < straight.seconds + 60 and resumed.where == {"device": "cpu", "world_size": 1}
    # a finished run, started again: nothing to do, the same weights
    again = train_network(Toy(config), tmp_path / "a")
    assert again.step == 6 and torch.equal(again.model.weight, straight.model.weight)


def test_other_settings_or_data_are_refused_and_time_may_span_sessions(tmp_path):
    torch.set_num_threads(1)
    config = ToyConfig(iters=3)
    with pytest.raises(Killed):
        train_network(Toy(config, session_seconds=False), tmp_path / "run", on_step=kill_at(3))
    ck = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert ck["step"] == 3 and ck["seconds"] > 0
    with pytest.raises(CheckpointMismatchError, match="lr"):
        train_network(Toy(replace(config, lr=0.01)), tmp_path / "run")
    with pytest.raises(CheckpointMismatchError, match="toy data"):
        train_network(Toy(replace(config, data_seed=1)), tmp_path / "run")
    # how often to checkpoint or validate decides nothing: resumed, and the time of before counted
    done = train_network(Toy(replace(config, checkpoint_every=1, validate_every=0), session_seconds=False),
                         tmp_path / "run")
    assert done.step == 3 and done.seconds >= ck["seconds"]
