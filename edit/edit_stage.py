"""What every edit stage (geometry, texture, hybrid) shares: the edit's folder and its lock, the
user's files recorded by content, the trainer, the saved editing field and the published result.

    run, out = open_edit(run_dir, view, name)
    with editing(out), torch_threads(cfg.threads):
        trainer = edit_trainer(out, settings, runtime_keys, loop_options(cfg), defaults, inputs,
                               force=force, progress=progress, advice="...")
        if (done := trainer.finished()) is not None:
            return done
        ...  # prepare, train
        save_edit_field(trainer.work_dir, "ours", editing=..., band_width=...)
        return publish_edit(trainer, metrics, t_start, cfg)
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from recon.formats import FORMAT_VERSIONS
from recon.rundir import RunDir
from recon.training import LoopOptions, Trainer, discard_unstarted
from render.configs import option
from render.errors import SineError
from render.io import file_sha256, save_torch
from render.locks import lock_entry

# what an edit is made from besides the user's files: an edit of a template fitted again since
# (or of a run whose recon changed) is learnt again
EDIT_INPUTS = ("cameras.json", "proxy_mesh.ply", "template/field.pt")

# the user's files' paths: recorded, but an edit is compared by their content (the same target
# under another spelling of its path is the same edit; an image edited in place is a new one)
PATH_KEYS = ("target", "mask", "region", "reference", "texture_target", "texture_region")
EDIT_OUTPUTS = ("edit_field.pt",)  # a finished edit whose field does not load is learnt again


# the training steps of each edit phase by preset (`sine edit --preset`, unless iterations is set)
EDIT_PRESETS = {"fast": 300, "default": 600, "quality": 1200}


@dataclass
class EditLoopOptions(LoopOptions):
    """The loop settings of every edit: its length, by preset unless given."""

    preset: str = option(
        "default",
        "time/quality trade-off: the training steps of each phase, unless iterations is set "
        "(fast 300, default 600, quality 1200)",
        choices=list(EDIT_PRESETS),
    )
    iterations: int | None = option(None, "training steps (None: the preset's)", low=1)


def with_preset(cfg):
    """`cfg` (a geometry or texture edit config) with its iterations taken from its preset when
    left at None."""
    if cfg.preset not in EDIT_PRESETS:
        raise SineError(f"--preset must be one of {', '.join(EDIT_PRESETS)} (got {cfg.preset!r})")
    if cfg.iterations is not None:
        return cfg
    return dataclasses.replace(cfg, iterations=EDIT_PRESETS[cfg.preset])


def pick_view(run: RunDir, view: int):
    """The camera of view `view` (a SineError naming the run's range when out of it)."""
    frames = run.load_cameras().frames
    if not 0 <= view < len(frames):
        raise SineError(f"--view {view} is out of range: the run has views 0..{len(frames) - 1}")
    return frames[view]


def open_edit(run_dir, view: int, name: str) -> tuple[RunDir, Path]:
    """(the run, its edit folder RUN/edits/NAME) after checking the run has cameras, the view
    exists and the edit's path is free for a folder."""
    run = RunDir(run_dir)
    run.require("cameras")
    pick_view(run, view)
    out = run.edit(name)
    if out.exists() and not out.is_dir():
        raise SineError(f"{out} exists and is not a folder")
    return run, out


@contextlib.contextmanager
def editing(out: Path):
    """For the block that learns the edit RUN/edits/NAME (`out`): holds the edit's lock (a second
    process on the same edit is refused) and removes the .partial folder of an edit that fails
    a check before its first checkpoint."""
    with lock_entry(out, f"edit {out.name} of {out.parent.parent}"), discard_unstarted(out):
        yield


def input_digests(target, mask, region) -> dict:
    """The user's files by path and content (PATH_KEYS: only the content is compared)."""
    out = {}
    for key, path in (("target", target), ("mask", mask), ("region", region)):
        if path is not None and not Path(path).is_file():
            raise SineError(f"--{key} {path} does not exist")
        out[key] = None if path is None else str(path)
        out[f"{key}_sha256"] = None if path is None else file_sha256(path)
    return out


def edit_trainer(
    out: Path,
    settings: dict,
    runtime_keys: tuple[str, ...],
    loop: dict,
    defaults: dict,
    inputs: tuple[str, ...],
    **options: Any,
) -> Trainer:
    """The trainer of the edit in `out`: `settings` (what the edit depends on), `loop`
    (`loop_options` of its config), `defaults` (the config's defaults), `inputs` (run files it
    is made from); `options`: force, progress, advice, manual_backward."""
    return Trainer(
        out,
        f"edit {out.name}",
        settings,
        runtime_keys,
        **loop,
        format_version=FORMAT_VERSIONS["edit"],
        defaults=defaults,
        inputs=RunDir(out.parent.parent).inputs(*inputs),
        outputs=EDIT_OUTPUTS,
        **options,
    )


def save_edit_field(work: Path, method: str, **parts: Any) -> None:
    """Writes work/edit_field.pt: the edit's `method` and its modules' state (`parts`)."""
    save_torch(
        work / "edit_field.pt",
        {"format_version": FORMAT_VERSIONS["edit"], "method": method, **parts},
    )


def loop_metrics(trainer: Trainer, device) -> dict:
    """The metrics every edit reports of its training loop."""
    return {"iterations": trainer.step, "train_seconds": trainer.seconds, "device": str(device)}


def publish_edit(trainer: Trainer, metrics: dict, t_start: float, settings: Any) -> dict:
    """Publishes the edit with its metrics (and the total time since `t_start`) and its
    `settings` (the config in effect, saved as config.toml); returns the metrics."""
    metrics["total_seconds"] = time.perf_counter() - t_start
    trainer.publish(metrics, settings=settings)
    return metrics
