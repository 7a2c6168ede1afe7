"""The shared training loop: exact resume, per-group schedules, deferred back-propagation,
finished / changed-options checks, time-based checkpoints and the NaN stop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from recon.training import Trainer, changed_options, progress_bar
from render.errors import SineError
from render.io import read_json

CONFIG = {"iterations": 12, "lr": 0.01, "seed": 5, "device": "cpu"}


class Toy:
    """A tiny regression stage with every kind of checkpointed state."""

    def __init__(self, root, config=CONFIG, **kwargs):
        torch.manual_seed(0)
        self.model = torch.nn.Sequential(
            torch.nn.Linear(3, 16), torch.nn.ReLU(), torch.nn.Linear(16, 1)
        )
        g = torch.Generator().manual_seed(1)
        self.x = torch.randn(256, 3, generator=g)
        self.y = self.x.sum(1, keepdim=True).sin()
        self.seen = np.zeros(4)  # a numpy array the stage updates
        self.notes = {"steps": 0}  # a JSON-able dict
        kwargs = {"checkpoint_every": 4, "progress": False, "format_version": 3, **kwargs}
        self.trainer = Trainer(
            root / "toy",
            "toy",
            config,
            ("device",),
            iterations=config["iterations"],
            seed=config["seed"],
            **kwargs,
        )

    def start(self):
        lr = CONFIG["lr"]
        groups = [
            {"name": "first", "params": list(self.model[0].parameters()), "lr": lr},
            {"name": "second", "params": list(self.model[2].parameters()), "lr": lr / 2},
        ]
        state = {"model": self.model, "seen": self.seen, "notes": self.notes}
        self.trainer.start(state, groups, schedules={"second": lambda k: 1.0})

    def step(self, i):
        idx = torch.randint(256, (32,), generator=self.trainer.generator)
        noise = 0.01 * torch.randn(32, 1)  # the global torch RNG
        self.seen[i % 4] += 1
        self.notes["steps"] += 1
        err = self.model(self.x[idx]) - self.y[idx] - noise
        return {"mse": (err**2).mean(), "l1": 0.1 * err.abs().mean()}


def _params(model):
    return [p.detach().clone() for p in model.parameters()]


def test_resume_after_an_interruption_is_bit_exact(tmp_path):
    a = Toy(tmp_path / "a")
    a.start()
    assert a.trainer.run(a.step)
    b = Toy(tmp_path / "b")
    b.start()
    assert not b.trainer.run(b.step, stop_at=5)  # "interrupted" after step 5
    assert not (tmp_path / "b" / "toy").exists()  # results appear only when published
    c = Toy(tmp_path / "b")  # a new process: everything rebuilt, then resumed
    c.start()
    assert c.trainer.step == 5 and c.notes == {"steps": 5}
    assert c.trainer.run(c.step)
    for p, q in zip(_params(a.model), _params(c.model), strict=True):
        assert torch.equal(p, q)
    assert np.array_equal(a.seen, c.seen) and a.seen.sum() == 12 and c.notes == {"steps": 12}
    strip = [{k: v for k, v in e.items() if k != "seconds"} for e in a.trainer.log]
    assert strip == [{k: v for k, v in e.items() if k != "seconds"} for e in c.trainer.log]
    assert [e["step"] for e in strip] == [1, 12] and set(strip[0]) == {"step", "loss", "mse", "l1"}
    assert strip[0]["loss"] == pytest.approx(strip[0]["mse"] + strip[0]["l1"])
    # plain tensors and values only: loads without unpickling objects
    data = torch.load(c.trainer.checkpoint_path, weights_only=True)
    assert data["step"] == 12 and isinstance(data["config"], str)


def test_each_group_follows_its_own_schedule(tmp_path):
    t = Toy(tmp_path)
    t.start()
    t.trainer.run(t.step)
    first, second = t.trainer.optimizer.param_groups
    assert first["lr"] == pytest.approx(0.01 * 0.1)  # default: decayed to lr_final_factor
    assert second["lr"] == pytest.approx(0.005)  # constant schedule


def test_deferred_backward_accumulates_patches_into_one_step(tmp_path):
    full, deferred = Toy(tmp_path / "f"), Toy(tmp_path / "d", manual_backward=True)
    for t in (full, deferred):
        t.start()
    x, y = full.x[:64], full.y[:64]
    full.trainer.run(lambda i: {"mse": ((full.model(x) - y) ** 2).sum() / 64}, stop_at=3)

    def patches(i):
        total = 0.0
        for part in range(4):  # four patches, one backward each, one optimiser step
            sl = slice(16 * part, 16 * part + 16)
            loss = ((deferred.model(x[sl]) - y[sl]) ** 2).sum() / 64
            loss.backward()
            total += loss.detach()
        return {"mse": total}

    deferred.trainer.run(patches, stop_at=3)
    for p, q in zip(_params(full.model), _params(deferred.model), strict=True):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
    assert deferred.trainer.log[0]["mse"] == pytest.approx(full.trainer.log[0]["mse"], rel=1e-5)


def test_finished_run_is_skipped_and_changed_options_train_again(tmp_path, capsys):
    t = Toy(tmp_path)
    t.start()
    t.trainer.run(t.step)
    t.trainer.publish({"score": 1.0})
    assert not t.trainer.work_dir.exists()
    assert read_json(tmp_path / "toy" / "log.json")[-1]["step"] == 12
    done = {"score": 1.0, "format_version": 3, "skipped": True}
    assert Toy(tmp_path).trainer.finished() == done
    # a runtime key (device) does not matter; a real option does, and is named
    assert Toy(tmp_path, {**CONFIG, "device": "cuda"}).trainer.finished() is not None
    capsys.readouterr()
    other = Toy(tmp_path, {**CONFIG, "lr": 0.02})
    assert other.trainer.finished() is None
    assert "lr: 0.01 -> 0.02" in capsys.readouterr().out
    # --force trains again, keeping the old results until the new run is published
    forced = Toy(tmp_path, force=True)
    assert forced.trainer.finished() is None
    forced.start()
    assert forced.trainer.step == 0
    forced.trainer.run(forced.step, stop_at=3)
    assert read_json(tmp_path / "toy" / "metrics.json")["score"] == 1.0
    # an option added after the run was recorded: at its default the run stays finished
    newer = {**CONFIG, "extra": 0.0}
    assert Toy(tmp_path, newer, defaults={"extra": 0.0}).trainer.finished() is not None
    assert (
        Toy(tmp_path, {**newer, "extra": 0.5}, defaults={"extra": 0.0}).trainer.finished() is None
    )
    assert Toy(tmp_path, newer).trainer.finished() is None  # no defaults given: a change
    assert changed_options({"a": 1, "d": 0}, {"a": 2, "d": 1, "b": 3}, ("d",)) == [
        "a: 1 -> 2",
        "b: (unset) -> 3",
    ]


def test_a_run_whose_inputs_changed_is_trained_again(tmp_path, capsys):
    (tmp_path / "views").mkdir()
    (tmp_path / "views" / "a.png").write_bytes(b"one")
    (tmp_path / "field.pt").write_bytes(b"weights")
    inputs = {"views": tmp_path / "views", "field.pt": tmp_path / "field.pt"}
    t = Toy(tmp_path, inputs=inputs)
    t.start()
    t.trainer.run(t.step)
    t.trainer.publish({"score": 1.0})
    assert Toy(tmp_path, inputs=inputs).trainer.finished() is not None
    # the same content written again (a stage re-run that changed nothing) is the same input
    (tmp_path / "field.pt").write_bytes(b"weights")
    assert Toy(tmp_path, inputs=inputs).trainer.finished() is not None
    capsys.readouterr()
    (tmp_path / "field.pt").write_bytes(b"weights fitted again")
    assert Toy(tmp_path, inputs=inputs).trainer.finished() is None
    said = capsys.readouterr().out
    assert "field.pt is not the one it was made from" in said and "views" not in said
    (tmp_path / "field.pt").write_bytes(b"weights")
    (tmp_path / "views" / "b.png").write_bytes(b"two")  # a folder: a file more is a change
    assert Toy(tmp_path, inputs=inputs).trainer.finished() is None
    assert "views is not the one" in capsys.readouterr().out
    (tmp_path / "views" / "b.png").unlink()
    assert Toy(tmp_path, inputs=inputs).trainer.finished() is not None
    assert Toy(tmp_path).trainer.finished() is not None  # a stage that names no inputs
    plain = Toy(tmp_path, force=True)
    plain.start()
    plain.trainer.run(plain.step)
    plain.trainer.publish({"score": 3.0})
    capsys.readouterr()
    # a run made without inputs, for a stage that now names some: trained again
    assert Toy(tmp_path, inputs=inputs).trainer.finished() is None
    assert "views is not the one" in capsys.readouterr().out


def test_a_run_of_another_format_version_is_trained_again_with_one_line(tmp_path, capsys):
    t = Toy(tmp_path)
    t.start()
    t.trainer.run(t.step)
    t.trainer.publish({"score": 1.0})
    assert read_json(tmp_path / "toy" / "metrics.json")["format_version"] == 3
    assert Toy(tmp_path).trainer.finished() is not None
    capsys.readouterr()
    assert Toy(tmp_path, format_version=4).trainer.finished() is None
    said = capsys.readouterr().out.strip().splitlines()
    assert said == [
        f"toy: the finished run in {tmp_path / 'toy'} is out of date (written in format version "
        "3, this version writes 4): training again (the old results stay until it finishes)"
    ]


def test_interrupted_run_with_other_options_is_discarded(tmp_path, capsys):
    t = Toy(tmp_path)
    t.start()
    t.trainer.run(t.step, stop_at=4)
    other = Toy(tmp_path, {**CONFIG, "seed": 6})
    other.start()
    assert other.trainer.step == 0 and "seed: 5 -> 6" in capsys.readouterr().out


def test_nan_loss_stops_with_advice_and_keeps_a_time_based_checkpoint(tmp_path):
    t = Toy(tmp_path, checkpoint_every=1000, checkpoint_seconds=0.0, advice="--lr 0.001")
    t.start()

    def step(i):
        out = t.step(i)
        return {**out, "mse": out["mse"] * (float("nan") if i == 2 else 1.0)}

    with pytest.raises(SineError, match=r"toy diverged at step 3 .*diverge again.*--lr 0.001"):
        t.trainer.run(step)
    assert torch.load(t.trainer.checkpoint_path, weights_only=True)["step"] == 2


def test_progress_bar_updates_rarely_without_a_terminal():
    import io

    bar = progress_bar(total=3, file=io.StringIO())  # pytest's captured stderr is not a TTY
    assert bar.mininterval == 30.0
    bar.close()
