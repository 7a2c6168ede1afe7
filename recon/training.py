"""Checkpointed training state shared by `sine fit` and `sine features` (`Training`).

A checkpoint holds the resolved config, every module's and the optimizer's / scheduler's state,
the RNG states, the step, the log and the training seconds, so an interrupted run resumes to the
same parameters as an uninterrupted one. Settings listed as runtime keys (device, threads, ...)
do not change the result: a checkpoint made with other values of those still resumes.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from render.errors import SineError
from render.io import atomic_path, read_json


def same_settings(a: dict, b: dict, runtime_keys: tuple[str, ...]) -> bool:
    """Whether two resolved configs give the same result (runtime keys ignored)."""

    def strip(d: dict) -> dict:
        return {k: v for k, v in d.items() if k not in runtime_keys}

    return strip(a) == strip(b)


def finished_metrics(
    checkpoint: Path,
    final: Path,
    metrics: Path,
    config: dict,
    runtime_keys: tuple[str, ...],
    iterations: int,
) -> dict | None:
    """The metrics of a run already trained to `iterations` with these settings, else None."""
    if not (metrics.is_file() and final.is_file() and checkpoint.is_file()):
        return None
    done = torch.load(checkpoint, map_location="cpu", weights_only=False)
    if done["step"] >= iterations and same_settings(done["config"], config, runtime_keys):
        return read_json(metrics)
    return None


def save_state(
    path: Path, config: dict, modules: dict, optimizer, scheduler, generator, step, log, seconds
) -> None:
    """Writes the training state atomically (`modules`: name -> nn.Module)."""
    state = {name: module.state_dict() for name, module in modules.items()}
    state.update(
        config=config,
        optimizer=optimizer.state_dict(),
        scheduler=scheduler.state_dict(),
        generator=generator.get_state(),
        torch_rng=torch.get_rng_state(),
        step=step,
        log=log,
        train_seconds=seconds,
    )
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def restore_state(
    path: Path,
    config: dict,
    runtime_keys: tuple[str, ...],
    modules: dict,
    optimizer,
    scheduler,
    generator,
) -> tuple[int, list, float]:
    """Loads `path` into the modules / optimizer / RNGs; returns (step, log, train seconds).

    Without a checkpoint: (0, [], 0.0). One made with other settings is an error (use --force).
    """
    if not path.exists():
        return 0, [], 0.0
    state = torch.load(path, map_location="cpu", weights_only=False)
    if not same_settings(state["config"], config, runtime_keys):
        raise SineError(f"{path} was made with other settings; re-run with --force to start over")
    for name, module in modules.items():
        module.load_state_dict(state[name])
    optimizer.load_state_dict(state["optimizer"])
    scheduler.load_state_dict(state["scheduler"])
    generator.set_state(state["generator"])
    torch.set_rng_state(state["torch_rng"])
    return state["step"], state["log"], state["train_seconds"]


class Training:
    """One resumable training stage (`sine fit`, `sine features`): Adam over `param_groups` with
    a learning rate decaying exponentially to `lr_final_factor` at `iterations`, the seeded
    generator for batches, and the step / log / seconds counters, restored from `path` when a
    checkpoint with the same settings exists (else an error, see `restore_state`)."""

    def __init__(
        self,
        path: Path,
        config: dict,
        runtime_keys: tuple[str, ...],
        modules: dict,
        param_groups: list,
        iterations: int,
        lr_final_factor: float,
        seed: int,
    ):
        self.path, self.config, self.modules = path, config, modules
        self.optimizer = torch.optim.Adam(param_groups, betas=(0.9, 0.99))
        decay = lr_final_factor ** (1.0 / max(iterations, 1))
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, lambda k: decay**k)
        self.generator = torch.Generator().manual_seed(seed)
        self.step, self.log, self.seconds = restore_state(
            path, config, runtime_keys, modules, self.optimizer, self.scheduler, self.generator
        )

    def update(self, loss: torch.Tensor, started: float) -> None:
        """One optimiser step on `loss`; the step began at time.perf_counter() == `started`."""
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.scheduler.step()
        self.step += 1
        self.seconds += time.perf_counter() - started

    def checkpoint(self) -> None:
        save_state(
            self.path,
            self.config,
            self.modules,
            self.optimizer,
            self.scheduler,
            self.generator,
            self.step,
            self.log,
            self.seconds,
        )
