"""One job of a batch, run where Ray puts it: the same `sine` command a user would type, parsed
by that command's own parser (so the batch's settings mean what `--set` means), its output in
OUT/OBJECT/logs/, and a record of what happened.

A job whose dependency failed is not run. A stage that keeps its own "already done" rule (recon,
fit, features, edit) is simply run again and reports "skipped" when it found its result done;
the output stages and `sine synth`, which redo their work whenever they are called, are skipped
by the batch's own record OUT/OBJECT/batch/JOB.json (their command, settings and the results
they read, unchanged since they last finished).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import socket
import time
import traceback
from pathlib import Path

from render.errors import SineError

TOKEN = ".sine_batch_token"  # OUT/TOKEN: proves a worker sees the driver's --out
METRICS = {  # the numbers a job reports, read from its result file
    "synth": ("views",),
    "recon": ("registered_views", "silhouette_iou_mean", "verdict"),
    "fit": ("heldout_psnr_object", "heldout_ssim_object", "heldout_psnr", "iterations"),
    "features": ("heldout_cosine", "train_view_cosine", "iterations"),
    "edit": (
        "edited_view_psnr_object",
        "edited_view_silhouette_iou",
        "edited_view_psnr_region",
        "unedited_view_psnr",
        "iterations",
    ),
    "eval": ("psnr_object", "ssim_object", "psnr", "silhouette_iou", "n_views"),
}
HEADLINE = {  # the one number of each stage shown as it finishes
    "recon": "silhouette_iou_mean",
    "fit": "heldout_psnr_object",
    "features": "heldout_cosine",
    "edit": "edited_view_psnr_object",
    "eval": "psnr_object",
}


class _Parser(argparse.ArgumentParser):
    """A command's parser whose errors are SineErrors (a batch job fails, the batch goes on)."""

    def error(self, message: str):
        raise SineError(f"{self.prog}: {message}")


def command_module(name: str):
    """The module of `sine NAME` (its add_arguments and run)."""
    from edit import commands as edit_commands
    from recon import commands as recon_commands

    for module in recon_commands.MODULES + edit_commands.MODULES:
        if module.NAME == name:
            return module
    raise SineError(f"no command {name!r}")


def parse_command(argv: list[str], settings: dict) -> argparse.Namespace:
    """`sine ARGV` with the batch's settings under any given on the command line."""
    from render.configs import resolve_settings

    module = command_module(argv[0])
    parser = _Parser(prog=f"sine {module.NAME}", add_help=False)
    module.add_arguments(parser)
    args = parser.parse_args(argv[1:])
    args.func = module.run
    return resolve_settings(args, settings)


def check_job(job) -> None:
    """Parses the job's command with a stand-in view: unknown settings and wrong types fail
    before any work."""
    parse_command(_with_view(job, 0), job.settings)


def run_job(job, token: str, out: str, cpus: int, *upstream: dict) -> dict:
    """Runs `job` (a batch_file.Job) after its dependencies' records `upstream`; returns its
    record {"job", "object", "stage", "edit", "status", "seconds", "message", "metrics",
    "result", "log"}. Never raises for the job's own errors: they become its record."""
    t0 = time.perf_counter()
    record = failed_record(job, "")
    record["node"] = socket.gethostname()
    failed = [u["job"] for u in upstream if u["status"] == "failed"]
    if failed:
        return {**record, "message": f"not run: {failed[0]} failed"}
    out = Path(out)
    if not _sees(out, token):
        message = (
            f"the worker on {record['node']} does not see {out} (the batch's --out must be a "
            "folder every node mounts)"
        )
        return {**record, "message": message, "storage": False}
    log = job.home / "logs" / f"{job.slug}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    record["log"] = str(log)
    running = marker(job)
    running.parent.mkdir(parents=True, exist_ok=True)
    running.write_text(f"{os.getpid()} {record['node']}\n")
    try:
        with open(log, "a") as stream, _output_to(stream), _threads(cpus):
            print(f"== {job.id}, {time.ctime()}")
            record.update(_execute(job, upstream))
    finally:
        running.unlink(missing_ok=True)
    record["seconds"] = round(time.perf_counter() - t0, 1)
    return record


def failed_record(job, message: str) -> dict:
    """The record of a job that did not finish (the batch's schema, see `run_job`)."""
    return {
        "job": job.id,
        "object": job.object,
        "stage": job.stage,
        "edit": job.edit,
        "status": "failed",
        "seconds": 0.0,
        "message": message,
        "metrics": {},
        "result": str(job.result),
    }


def marker(job) -> Path:
    """OUT/OBJECT/batch/JOB.running: the PID and host of the worker running the job."""
    return job.home / "batch" / f"{job.slug}.running"


def probe(token: str, out: str) -> tuple[str, bool]:
    """(host, whether it sees OUT/TOKEN with the driver's token): run once on every node."""
    return socket.gethostname(), _sees(Path(out), token)


# ---- the work -----------------------------------------------------------------------------
def _execute(job, upstream: tuple[dict, ...]) -> dict:
    from render.io import WRITE_ERRORS, read_json, write_error, write_json

    try:
        argv = _with_view(job, _view_index(job))
        print(command_line(argv, job.settings))  # the same, by hand
        args = parse_command(argv, job.settings)
        inputs = [_mtime(u["result"]) for u in upstream]  # a redone dependency: redo this too
        key = {"argv": argv, "settings": job.settings, "inputs": inputs}
        record_path = job.home / "batch" / f"{job.slug}.json"
        done = (
            job.recorded
            and record_path.is_file()
            and read_json(record_path).get("key") == key
            and Path(job.result).exists()
        )
        before = _mtime(job.result)
        if not done:
            args.func(args)
        if job.recorded and not done:
            write_json(record_path, {"key": key})
        skipped = done or (not job.recorded and _mtime(job.result) == before)
        status = "skipped" if skipped else "done"
        return {"status": status, "metrics": _metrics(job)}
    except SineError as exc:
        print(f"error: {exc}")
        return {"message": str(exc)}
    except OSError as exc:
        if exc.errno not in WRITE_ERRORS:
            return _internal(exc)
        message = write_error(exc.filename or "a file", exc)
        print(f"error: {message}")
        return {"message": message}
    except Exception as exc:  # a bug: the traceback goes to the log, the batch goes on
        return _internal(exc)


def command_line(argv: list[str], settings: dict) -> str:
    """The job as one `sine` command line (its settings as --set NAME=VALUE)."""
    import json
    import shlex

    sets = [f"{k}={json.dumps(v)}" for k, v in settings.items()]  # JSON values are TOML ones
    return shlex.join(["sine", *argv, *(a for s in sets for a in ("--set", s))])


def _internal(exc: Exception) -> dict:
    traceback.print_exc()
    return {"message": f"internal error {type(exc).__name__}: {exc} (traceback in the log)"}


def _with_view(job, view) -> list[str]:
    return list(job.argv) + (["--view", str(view)] if job.stage == "edit" else [])


def _view_index(job) -> int | None:
    """The edit's view as an index in the run's cameras (a file name is looked up)."""
    if job.stage != "edit":
        return None
    if isinstance(job.view, int):
        return job.view
    from recon.rundir import RunDir

    names = [c.name for c in RunDir(job.home / "run").load_cameras().frames]
    if job.view not in names:
        raise SineError(
            f"view {job.view!r} is not among the run's {len(names)} registered views "
            f"({', '.join(names[:4])}, ...)"
        )
    return names.index(job.view)


def _metrics(job) -> dict:
    from render.io import read_json

    result = Path(job.result)
    if job.stage in ("video", "mesh"):
        return {"file": str(result), "megabytes": round(result.stat().st_size / 2**20, 2)}
    data = read_json(result)
    if job.stage == "eval":
        data = data.get("mean", {})
    return {k: data[k] for k in METRICS.get(job.stage, ()) if data.get(k) is not None}


def _mtime(path) -> int:
    """The modification time of a result file in ns (0 when missing)."""
    return Path(path).stat().st_mtime_ns if Path(path).exists() else 0


def _sees(out: Path, token: str) -> bool:
    try:
        return (out / TOKEN).read_text().strip() == token
    except OSError:
        return False


@contextlib.contextmanager
def _output_to(stream):
    with contextlib.redirect_stdout(stream), contextlib.redirect_stderr(stream):
        yield


@contextlib.contextmanager
def _threads(cpus: int):
    """torch's threads = the CPUs Ray gave the task."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(max(1, int(cpus)))
    try:
        yield
    finally:
        torch.set_num_threads(before)
