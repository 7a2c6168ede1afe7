"""The training loop of every training stage (`sine fit`, `sine features`, the editing stages).

A stage supplies its state (modules, ...), its parameter groups and one function
`step(i) -> {name: loss term}`; `Trainer` owns the rest: start / resume, zero_grad, backward,
the optimiser and learning-rate schedule steps, the NaN/inf check, the progress bar, the log,
checkpoints (every `checkpoint_every` steps and every `checkpoint_seconds` of wall time) and the
"already finished with these options" check.

    trainer = Trainer(run.root / "mystage", "mystage", to_dict(cfg), RUNTIME_KEYS,
                      **loop_options(cfg), force=force)  # iterations=cfg.iterations, seed=...
    if (done := trainer.finished()) is not None:  # cheap: before any data is loaded
        return done                                # metrics.json + {"skipped": True}
    model = ...  # the stage's modules and data (caches may go into trainer.work_dir from now on)
    trainer.start({"model": model}, [{"name": "mlp", "params": list(model.parameters()),
                                      "lr": 1e-2}], lr_final_factor=0.1)

    def step(i: int) -> dict[str, torch.Tensor]:
        idx = torch.randint(n, (1024,), generator=trainer.generator)
        return {"rgb": ((model(x[idx]) - y[idx]) ** 2).mean(), "reg": 1e-3 * model.reg()}

    if not trainer.run(step, stop_at=stop_at):     # stopped early on purpose
        return {"step": trainer.step}
    trainer.publish(metrics)  # every other output written into work_dir before

Steps. Before each step the loop zeroes the gradients; it sums the returned terms into the loss
(logged as "loss", each term under its own name), stops with a SineError when the loss is not
finite, back-propagates it and takes one optimiser step and one schedule step. Deferred
back-propagation: with `manual_backward=True` the step calls `backward()` itself, as often as it
needs (e.g. once per image patch rendered with a graph: the gradients accumulate), and returns
the detached terms for the log; the loop then only checks and steps.

A stage's config inherits `LoopOptions` (checkpoint_every, checkpoint_seconds, log_every, device,
threads: RUNTIME_KEYS, they never change the result) and passes `**loop_options(cfg)`.

Parameter groups are torch's dicts, each with a unique "name" and its "lr"; each group's learning
rate is lr x factor(step), factor = `schedules[name]` or, by default, an exponential decay to
`lr_final_factor` at `iterations` (`exponential_decay`). Adam (`adam`: betas 0.9, 0.99, the fused
kernel) unless the stage passes another `optimizer` factory.

State and checkpoints. `start(state)` names everything a checkpoint must hold besides the
optimiser, the schedule, the loop's generator and the torch RNGs, which the trainer adds itself:
objects with `state_dict()` (modules, other optimisers), torch.Generator, tensors, numpy arrays
(stored as tensors) and JSON-able dicts / lists (stored as JSON text). Resuming restores each of
them in place (arrays and tensors keep their shape), so N steps in one go and k steps, an
interruption and N - k more give bit-identical parameters. Checkpoints hold only tensors and
plain values and are written atomically; they load with `torch.load(..., weights_only=True)`.

Files. `directory` (e.g. RUN/template/) holds a finished run only: checkpoint.pt, metrics.json,
log.json and whatever the stage wrote. A run in progress lives in `directory.partial` (its
`work_dir`, with its checkpoint); `publish()` swaps it in once the stage has written its
outputs there. So an interrupted run resumes from the partial checkpoint, and `--force` or
changed options replace the old results only when the new run has finished. A finished run whose
recorded options differ from the given ones (runtime keys such as device and threads aside) is
trained again, and the changed options are named; an interrupted run with other options is
discarded the same way. A stage also names what it is made from (`inputs`: files or folders of
the run, e.g. the template's field.pt for an edit): their digests are recorded with the options,
and a run whose inputs changed since (or were not recorded) is trained again as well. And it
names the torch files it leaves (`outputs`, e.g. field.pt): a finished run one of whose outputs
does not load (truncated, corrupt) is not done, and is trained again.

One process at a time. The stage holds the lock of what it writes (`render.locks`) around the
whole run, and `discard_unstarted` removes the `.partial` folder of a run that failed a check
before its first checkpoint. Holding the lock, a `.partial` folder found at the start is an
interrupted run's: it is resumed ("resuming from step N of M") or removed with a line saying so.
"""

from __future__ import annotations

import contextlib
import json
import os
import pickle
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from recon.formats import version_change
from render.configs import option, write_settings
from render.errors import SineError
from render.io import (
    TORCH_READ_ERRORS,
    artefact_digest,
    load_torch,
    read_json,
    remove_partial_writes,
    save_torch,
    torch_read_problem,
    write_json,
)

StepFn = Callable[[int], dict[str, torch.Tensor]]
# The loop's own options, by the names a stage config gives them (see `loop_options`).
LOOP_OPTIONS = ("iterations", "seed", "log_every", "checkpoint_every", "checkpoint_seconds")


@dataclass
class LoopOptions:
    """Options every training stage's config inherits: when to checkpoint and log, where to run.
    They never change the result (RUNTIME_KEYS): a checkpoint made with other values resumes."""

    checkpoint_every: int = option(250, "steps between checkpoints", low=1)
    checkpoint_seconds: float = option(
        60.0,
        "seconds of training between checkpoints (besides every checkpoint_every steps)",
        low=0.0,
    )
    log_every: int = option(50, "steps between log entries", low=1)
    device: str = option("auto", "torch device: auto, cpu or cuda", choices=["auto", "cpu", "cuda"])
    threads: int = option(0, "torch CPU threads (0: torch's default)", low=0)


RUNTIME_KEYS = ("checkpoint_every", "checkpoint_seconds", "log_every", "device", "threads")
_RESERVED = ("optimizer", "scheduler", "generator")


def progress_bar(**kwargs) -> tqdm:
    """A tqdm bar that, when stderr is not a terminal (a log file, a pipe), updates at most
    every 30 s instead of flooding the log with carriage returns."""
    if not sys.stderr.isatty():
        kwargs.setdefault("mininterval", 30.0)
    return tqdm(**kwargs)


def loop_options(cfg: Any) -> dict:
    """The Trainer keyword arguments a stage config holds under the same names (LOOP_OPTIONS):
    `Trainer(directory, name, to_dict(cfg), RUNTIME_KEYS, **loop_options(cfg), ...)`."""
    return {name: getattr(cfg, name) for name in LOOP_OPTIONS if hasattr(cfg, name)}


def adam(groups: list[dict]) -> torch.optim.Adam:
    """Adam (betas 0.9, 0.99); the fused kernel when every parameter is on the CPU or a CUDA
    device (on the CPU ~10x faster than the per-tensor loop for a hash table's millions of
    rows; same update to float tolerance)."""
    devices = {p.device.type for g in groups for p in g["params"]}
    return torch.optim.Adam(groups, betas=(0.9, 0.99), fused=devices <= {"cpu", "cuda"})


def exponential_decay(final_factor: float, iterations: int) -> Callable[[int], float]:
    """factor(step) = final_factor ** (step / iterations): 1 at the start, final_factor at the end."""
    decay = final_factor ** (1.0 / max(iterations, 1))
    return lambda step: decay**step


def changed_options(old: dict, new: dict, runtime_keys=()) -> list[str]:
    """'name: old -> new' for every option that differs (runtime keys ignored)."""
    names = sorted((set(old) | set(new)) - set(runtime_keys))
    return [
        f"{k}: {old.get(k, '(unset)')} -> {new.get(k, '(unset)')}"
        for k in names
        if old.get(k) != new.get(k)
    ]


# ---- checkpoint values ------------------------------------------------------------------------
def pack(value: Any) -> dict:
    """One object of a stage's state as tensors / plain values (see `unpack_into`)."""
    if isinstance(value, torch.Generator):
        return {"generator": value.get_state()}
    if isinstance(value, torch.Tensor):
        return {"tensor": value.detach().cpu().clone()}
    if isinstance(value, np.ndarray):
        return {"array": torch.from_numpy(np.array(value))}
    if hasattr(value, "state_dict") and hasattr(value, "load_state_dict"):
        return {"state_dict": value.state_dict()}
    if isinstance(value, (dict, list)):
        return {"json": json.dumps(value)}
    raise TypeError(f"cannot checkpoint a {type(value).__name__}")


def unpack_into(value: Any, packed: dict, name: str) -> None:
    """Restores `value` in place from what `pack` made of it."""
    if "generator" in packed:
        value.set_state(packed["generator"])
    elif "tensor" in packed or "array" in packed:
        saved = packed.get("tensor", packed.get("array"))
        if tuple(saved.shape) != tuple(value.shape):
            raise SineError(f"checkpoint entry {name!r} has shape {tuple(saved.shape)}")
        if isinstance(value, np.ndarray):
            value[...] = saved.numpy()
        else:
            with torch.no_grad():
                value.copy_(saved)
    elif "state_dict" in packed:
        value.load_state_dict(packed["state_dict"])
    elif isinstance(value, dict):
        value.clear()
        value.update(json.loads(packed["json"]))
    else:
        value[:] = json.loads(packed["json"])


def read_checkpoint_header(path: Path) -> dict | None:
    """{"config": dict, "step": int, "format_version": int | None} of a checkpoint (tensors are
    not read), None when the file is missing or not a checkpoint of this format."""
    if not path.is_file():
        return None
    try:
        data = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except (RuntimeError, OSError, EOFError, ValueError, pickle.UnpicklingError):
        return None  # corrupt, truncated, pickled objects or an older format: not usable
    if not isinstance(data, dict) or data.get("format") != _FORMAT:
        return None
    return {
        "config": json.loads(data["config"]),
        "step": int(data["step"]),
        "format_version": data.get("format_version"),
    }


_FORMAT = "sine-checkpoint-1"


def partial_dir(directory: str | os.PathLike) -> Path:
    """Where a training stage's run in progress lives: DIRECTORY.partial."""
    directory = Path(directory)
    return directory.with_name(directory.name + ".partial")


def folder_megabytes(folder: Path) -> float:
    """Size of a folder's files in MB (0 when it does not exist)."""
    if not folder.is_dir():
        return 0.0
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 1e6


@contextlib.contextmanager
def discard_unstarted(directory: str | os.PathLike):
    """For the block that runs a training stage into `directory`: when it ends on a user error
    (a SineError: a failed check, a bad input) before the stage's first checkpoint, the
    DIRECTORY.partial folder it made is removed (nothing in it could be resumed). Interrupted
    runs and runs with a checkpoint keep their folder."""
    try:
        yield
    except SineError:
        work = partial_dir(directory)
        if work.is_dir() and not (work / "checkpoint.pt").is_file():
            shutil.rmtree(work, ignore_errors=True)
        raise


# ---- the loop ---------------------------------------------------------------------------------
class Trainer:
    """One resumable training run of a stage; see the module docstring.

    directory: the stage's results folder; name: the stage as the user knows it (messages, the
    progress bar); config: the stage's resolved options (to_dict(cfg)); runtime_keys: options
    that do not change the result (device, threads, ...). `advice`: what to change when the loss
    diverges (resuming as is would repeat the same steps). `format_version`: the stage's entry in
    `recon.formats.FORMAT_VERSIONS`, recorded with the run and in its metrics.json: a run of
    another version is trained again. `defaults`: the options' default values: an option added
    after a run was recorded counts, for that run, as its default (an option added with a default
    that changes the behaviour comes with a new format version). `inputs`: files or folders
    the stage is made from; `outputs`: torch files of `directory` that must load for the run to
    count as done.
    """

    def __init__(
        self,
        directory: str | os.PathLike,
        name: str,
        config: dict,
        runtime_keys: tuple[str, ...] = (),
        *,
        iterations: int,
        seed: int = 0,
        log_every: int = 50,
        checkpoint_every: int = 250,
        checkpoint_seconds: float = 60.0,
        force: bool = False,
        progress: bool = True,
        manual_backward: bool = False,
        advice: str = "lower learning rates",
        format_version: int,
        defaults: dict | None = None,
        inputs: dict[str, str | os.PathLike] | None = None,
        outputs: tuple[str, ...] = (),
    ):
        self.directory = Path(directory)
        self.work_dir = partial_dir(self.directory)
        self.name, self.runtime_keys = name, tuple(runtime_keys)
        # what the stage is made from (name -> file / folder): their digests are recorded with
        # the options, so a finished run whose inputs changed since is trained again
        self.inputs = {key: artefact_digest(path) for key, path in (inputs or {}).items()}
        self.config = {**config, "inputs": self.inputs} if inputs is not None else config
        self.format_version = format_version
        self.iterations, self.seed, self.log_every = iterations, seed, log_every
        self.checkpoint_every, self.checkpoint_seconds = checkpoint_every, checkpoint_seconds
        self.force, self.progress, self.manual_backward = force, progress, manual_backward
        self.defaults = dict(defaults or {})
        self.advice = advice
        self.outputs = tuple(outputs)
        self.step, self.seconds, self.log = 0, 0.0, []
        self.optimizer = self.scheduler = self.generator = None
        self.state: dict[str, Any] = {}
        self._resumable: bool | None = None  # decided by finished() or start()

    @property
    def checkpoint_path(self) -> Path:
        return self.work_dir / "checkpoint.pt"

    # ---- before loading anything -----------------------------------------------------------
    def finished(self) -> dict | None:
        """metrics.json (+ "skipped": True) of a run finished with these options, else None.

        Says why it trains again when the finished run had other options. When it returns None,
        work_dir holds only a resumable checkpoint (or nothing): the stage may write into it."""
        metrics = self.directory / "metrics.json"
        done = read_checkpoint_header(self.directory / "checkpoint.pt")
        if self.force or done is None or not metrics.is_file():
            if self.force and metrics.is_file():
                self._say(f"--force: training again; {self.directory} stays until it finishes")
            elif metrics.is_file():
                self._say(f"{self.directory} has no readable checkpoint: training again")
            self._prepare_work_dir()
            return None
        changes = self._changes(done)
        if not changes and done["step"] >= self.iterations:
            broken = self._unreadable_output()
            if broken is None:
                return {**read_json(metrics), "skipped": True}
            self._say(f"the finished run in {self.directory} is damaged ({broken}): training again")
            self._prepare_work_dir()
            return None
        self._say(
            f"the finished run in {self.directory} is out of date "
            f"({'; '.join(changes)}): training again (the old results stay until it finishes)"
        )
        self._prepare_work_dir()
        return None

    def _unreadable_output(self) -> str | None:
        """What is wrong with the finished run's files (`outputs` that do not load, metrics.json
        that is not JSON), None when they are sound."""
        try:
            read_json(self.directory / "metrics.json")
        except SineError:
            return "metrics.json is not valid JSON"
        for name in self.outputs:
            try:
                torch.load(self.directory / name, map_location="cpu", weights_only=True, mmap=True)
            except FileNotFoundError:
                return f"{name} is missing"
            except TORCH_READ_ERRORS as exc:
                return f"{name} does not load: {torch_read_problem(exc)}"
        return None

    def _changes(self, header: dict) -> list[str]:
        """Why the run of a checkpoint `header` is out of date: its format version, else the
        options that differ from its options (see `defaults`), then the inputs that changed
        since it was made."""
        change = version_change(header["format_version"], self.format_version)
        if change is not None:
            return [change]
        recorded = dict(header["config"])
        made_from = recorded.pop("inputs", {})
        options = {k: v for k, v in self.config.items() if k != "inputs"}
        changes = changed_options({**self.defaults, **recorded}, options, self.runtime_keys)
        changes += [
            f"{key} is not the one it was made from"
            for key, digest in self.inputs.items()
            if made_from.get(key) != digest
        ]
        return changes

    def _prepare_work_dir(self) -> None:
        """Keeps work_dir when its checkpoint resumes with these options, else empties it."""
        header = None if self.force else read_checkpoint_header(self.checkpoint_path)
        self._resumable = False
        size = f"{folder_megabytes(self.work_dir):.0f} MB"
        if header is not None:
            changes = self._changes(header)
            if not changes:
                self._resumable = True
                remove_partial_writes(self.work_dir)  # a write the interruption cut short
                return
            self._say(
                f"discarding the interrupted run in {self.work_dir}, {size} ({'; '.join(changes)})"
            )
        elif self.force and self.work_dir.exists():
            self._say(f"--force: removing the interrupted run in {self.work_dir} ({size})")
        elif self.checkpoint_path.is_file():
            self._say(
                f"{self.checkpoint_path} is unreadable: starting over "
                f"(removing {self.work_dir}, {size})"
            )
        elif self.work_dir.exists() and any(self.work_dir.iterdir()):
            self._say(
                f"removing {self.work_dir}, left by a run stopped before its first "
                f"checkpoint ({size})"
            )
        shutil.rmtree(self.work_dir, ignore_errors=True)

    def saved(self, name: str) -> Any:
        """The JSON-able (dict / list) state entry `name` of the checkpoint `start` will resume
        from; None when training starts afresh or the checkpoint has no such entry. Lets a
        stage rebuild, before `start`, data whose shape the checkpoint fixed."""
        if self._resumable is None:
            self._prepare_work_dir()
        if not self._resumable:
            return None
        checkpoint = load_torch(self.checkpoint_path, rebuild="the same command with --force")
        packed = checkpoint["state"].get(name) or {}
        return json.loads(packed["json"]) if "json" in packed else None

    # ---- setup -------------------------------------------------------------------------------
    def start(
        self,
        state: dict[str, Any],
        groups: list[dict],
        schedules: dict[str, Callable[[int], float]] | None = None,
        lr_final_factor: float = 0.1,
        optimizer: Callable[[list[dict]], torch.optim.Optimizer] | None = None,
    ) -> None:
        """Builds the optimiser and schedules, seeds the generator, then resumes from work_dir's
        checkpoint when it was made with these options (see the module docstring)."""
        clash = [k for k in state if k in _RESERVED]
        if clash:
            raise ValueError(f"state names {clash} are reserved for the trainer")
        names = [g.get("name") for g in groups]
        if None in names or len(set(names)) != len(names):
            raise ValueError(f"every parameter group needs a unique 'name' (got {names})")
        self.optimizer = (optimizer or adam)(groups)
        schedules = schedules or {}
        default = exponential_decay(lr_final_factor, self.iterations)
        factors = [schedules.get(n, default) for n in names]
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, factors)
        self.generator = torch.Generator().manual_seed(self.seed)
        self.state = {
            **state,
            "optimizer": self.optimizer,
            "scheduler": self.scheduler,
            "generator": self.generator,
        }
        if self._resumable is None:  # finished() was not called
            self._prepare_work_dir()
        if self._resumable:
            self._load(self.checkpoint_path)
            self._say(f"resuming from step {self.step} of {self.iterations}")

    def _load(self, path: Path) -> None:
        data = load_torch(path, rebuild="the same command with --force")
        for name, value in self.state.items():
            if name not in data["state"]:
                raise SineError(f"{path} has no {name!r}; delete it or re-run with --force")
            unpack_into(value, data["state"][name], name)
        torch.set_rng_state(data["torch_rng"])
        cuda = data.get("cuda_rng") or []
        if cuda and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
            torch.cuda.set_rng_state_all(cuda)
        self.step, self.seconds = int(data["step"]), float(data["seconds"])
        self.log = json.loads(data["log"])

    def checkpoint(self) -> None:
        """Writes the whole state to work_dir/checkpoint.pt (atomically)."""
        data = {
            "format": _FORMAT,
            "stage": self.name,
            "config": json.dumps(self.config, sort_keys=True),
            "format_version": self.format_version,
            "step": self.step,
            "seconds": self.seconds,
            "log": json.dumps(self.log),
            "state": {name: pack(value) for name, value in self.state.items()},
            "torch_rng": torch.get_rng_state(),
        }
        if torch.cuda.is_available():
            data["cuda_rng"] = torch.cuda.get_rng_state_all()
        save_torch(self.checkpoint_path, data)

    # ---- the pieces of one step (for stages that need them separately) ---------------------
    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def optimizer_step(self) -> None:
        """One optimiser step and one learning-rate schedule step."""
        self.optimizer.step()
        self.scheduler.step()

    def check_finite(self, loss: torch.Tensor) -> None:
        """A readable SineError when the loss is NaN/inf (the last checkpoint stays)."""
        if not bool(torch.isfinite(loss)):
            raise SineError(
                f"{self.name} diverged at step {self.step + 1} (the loss is {loss.item()}); its "
                f"last checkpoint in {self.work_dir} is kept, but resuming would repeat the same "
                f"steps and diverge again: re-run with {self.advice}"
            )

    # ---- the loop ----------------------------------------------------------------------------
    def run(self, step: StepFn, stop_at: int | None = None) -> bool:
        """Trains from the current step to `iterations` (or to `stop_at`, as if interrupted there,
        with a checkpoint); True when training has reached `iterations`."""
        last = self.iterations if stop_at is None else min(self.iterations, stop_at)
        bar = progress_bar(
            total=self.iterations,
            initial=self.step,
            disable=not self.progress,
            desc=self.name,
            unit="step",
        )
        saved_at = time.perf_counter()
        while self.step < last:
            t0 = time.perf_counter()
            self.zero_grad()
            terms = step(self.step)
            if not terms:
                raise ValueError("a training step must return at least one loss term")
            loss = sum(terms.values())
            self.check_finite(loss)
            if not self.manual_backward:
                loss.backward()
            self.optimizer_step()
            self.step += 1
            self.seconds += time.perf_counter() - t0
            if self.step % self.log_every == 0 or self.step in (1, self.iterations):
                entry = {"step": self.step, "loss": loss.item()}
                entry.update({k: v.item() for k, v in terms.items()})
                self.log.append({**entry, "seconds": self.seconds})
            if self.step % 10 == 0 or self.step == last:
                values = {"loss": loss, **terms}
                bar.set_postfix({k: f"{v.item():.4f}" for k, v in values.items()}, refresh=False)
            bar.update(1)
            now = time.perf_counter()
            if (
                self.step % self.checkpoint_every == 0
                or self.step == last
                or now - saved_at >= self.checkpoint_seconds
            ):
                self.checkpoint()
                saved_at = now
        bar.close()
        return self.step >= self.iterations

    def skip_to_end(self) -> None:
        """Ends training here, as if the remaining steps had been taken (a stage that has
        decided they would teach nothing), with a checkpoint."""
        self.step = self.iterations
        self.checkpoint()

    # ---- after training ----------------------------------------------------------------------
    def publish(self, metrics: dict, settings: Any = None) -> None:
        """Writes metrics.json (`metrics`, given the format version), log.json, the stage's
        `settings` (its config in effect) as config.toml (`--config` of it reproduces the run),
        and moves work_dir to `directory`, replacing the old results."""
        metrics["format_version"] = self.format_version
        write_json(self.work_dir / "metrics.json", metrics)
        write_json(self.work_dir / "log.json", self.log)
        if settings is not None:
            write_settings(self.work_dir / "config.toml", settings)
        remove_partial_writes(self.work_dir)
        old = self.directory.with_name(self.directory.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        if self.directory.exists():
            os.replace(self.directory, old)
        os.replace(self.work_dir, self.directory)
        shutil.rmtree(old, ignore_errors=True)

    def _say(self, text: str) -> None:
        print(f"{self.name}: {text}", flush=True)
