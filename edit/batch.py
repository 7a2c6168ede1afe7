"""`sine batch JOBS.toml --out DIR`: many captures and edits as Ray tasks.

Every stage of every object is one Ray task (edit.batch_stages.run_job), chained by passing the
records of the tasks it depends on as arguments, so Ray starts it when they have finished: recon
after synth, fit after recon, features after fit, an edit after fit (geometry) or features
(texture, hybrid), an edit's outputs after the edit. A local Ray is started in the process when
no --address is given; with one, the same tasks go to that cluster. Ray retries a task whose
worker died (`retries`); a user error (a bad capture, a missing target) is the task's record,
not retried, and the other objects go on. Every stage keeps its own "already done" rules, so a
second run of the same batch does no work and a run after a crash does only what is missing.

Writes DIR/OBJECT/ (run/, logs/, one folder per edit with its outputs), DIR/batch_summary.json
and DIR/batch_summary.html.
"""

from __future__ import annotations

import logging
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from edit.batch_file import plan_jobs, read_batch
from edit.batch_stages import HEADLINE, TOKEN, check_job, failed_record, probe, run_job
from render.configs import option, validate
from render.errors import SineError
from render.io import require_directory, write_text_atomic
from render.locks import lock_folder


@dataclass
class BatchConfig:
    """Options of `sine batch`."""

    jobs: Path = option(Path("batch.toml"), "the batch file (TOML): captures, edits, outputs")
    out: Path = option(Path("runs/batch"), "output folder every Ray node sees")
    address: str | None = option(
        None, "Ray cluster to use ('auto': the one `ray start` joined here); none: a local Ray"
    )
    cpus_per_task: int = option(
        1, "CPUs (torch threads) of each task (one each: the most throughput per machine)", low=1
    )
    memory_per_task: float = option(
        2.0, "memory (GB) Ray keeps for each task: no more tasks run on a node than fit", low=0.0
    )
    gpus_per_task: float | None = option(
        None, "GPUs of each training or rendering task (none: 1 where the cluster has GPUs)"
    )
    retries: int = option(2, "times a task whose worker died is run again", low=0)
    quiet: bool = option(False, "no progress bar")


def run_batch(cfg: BatchConfig) -> dict:
    """Runs the batch; returns the summary (also DIR/batch_summary.json)."""
    from edit.batch_summary import write_summary

    validate(cfg)
    batch = read_batch(cfg.jobs)
    out = Path(cfg.out).resolve()
    require_directory(out, "--out")
    jobs = plan_jobs(batch, out)
    for job in jobs:
        try:
            check_job(job)
        except SineError as exc:
            raise SineError(f"{batch.path}: {job.id}: {exc}") from None
    t0 = time.perf_counter()
    with lock_folder(out, f"the batch output {out}"), _ray(cfg.address) as ray:
        token = uuid.uuid4().hex
        write_text_atomic(out / TOKEN, token + "\n")
        _check_storage(ray, token, out)
        cpus, gpus = _resources(ray, cfg)
        records = _run_tasks(ray, jobs, token, out, cpus, gpus, cfg)
    summary = {
        "batch": str(batch.path),
        "out": str(out),
        "address": cfg.address,
        "cpus_per_task": cpus,
        "gpus_per_task": gpus,
        "seconds": round(time.perf_counter() - t0, 1),
        "jobs": [records[job.id] for job in jobs],
    }
    write_summary(out, summary)
    return summary


# ---- Ray ----------------------------------------------------------------------------------
class _ray:
    """The Ray the batch runs on: already initialised (kept), a cluster (--address), or a local
    one started here; shut down at the end if started here."""

    def __init__(self, address: str | None):
        self.address = address
        self.started = False

    def __enter__(self):
        import ray

        if not ray.is_initialized():
            try:
                ray.init(
                    address=self.address,
                    include_dashboard=False,
                    log_to_driver=False,
                    logging_level=logging.WARNING,
                )
            except ConnectionError as exc:
                raise SineError(
                    f"cannot reach the Ray cluster at {self.address} ({exc}); start it with "
                    "`ray start --head` or drop --address for a local Ray"
                ) from None
            self.started = True
        return ray

    def __exit__(self, *exc):
        import ray

        if self.started:
            ray.shutdown()


def _check_storage(ray, token: str, out: Path) -> None:
    """Every alive node must see OUT/TOKEN: the runs are read and written by all of them."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    task = ray.remote(probe)
    nodes = [n["NodeID"] for n in ray.nodes() if n.get("Alive")]
    checks = [
        task.options(
            num_cpus=0, scheduling_strategy=NodeAffinitySchedulingStrategy(node, soft=False)
        ).remote(token, str(out))
        for node in nodes
    ]
    for host, sees in ray.get(checks, timeout=300):
        if not sees:
            raise SineError(
                f"the Ray node {host} does not see {out}: give --out a folder on a filesystem "
                "every node mounts (NFS, a cluster filesystem) at the same path"
            )


def _resources(ray, cfg: BatchConfig) -> tuple[int, float]:
    """(CPUs, GPUs) per task, checked against the largest node."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    most_cpus = max(int(r.get("CPU", 0)) for r in nodes)
    if cfg.cpus_per_task > most_cpus:
        raise SineError(
            f"--cpus-per-task {cfg.cpus_per_task}: no Ray node has that many CPUs (the largest "
            f"has {most_cpus})"
        )
    most_memory = max(r.get("memory", 0) for r in nodes) / 2**30
    if cfg.memory_per_task > most_memory:
        raise SineError(
            f"--memory-per-task {cfg.memory_per_task:g}: no Ray node has that much memory for "
            f"tasks (the largest has {most_memory:.1f} GB)"
        )
    any_gpu = any(r.get("GPU", 0) > 0 for r in nodes)
    gpus = cfg.gpus_per_task if cfg.gpus_per_task is not None else (1.0 if any_gpu else 0.0)
    if gpus > 0 and not any_gpu:
        raise SineError(f"--gpus-per-task {gpus}: the Ray cluster has no GPU")
    return cfg.cpus_per_task, gpus


def _run_tasks(ray, jobs, token: str, out: Path, cpus: int, gpus: float, cfg) -> dict:
    """Submits every job (dependencies as arguments) and collects the records as they finish."""
    from tqdm import tqdm

    task = ray.remote(run_job)
    refs: dict[str, object] = {}
    for job in jobs:
        options = {"num_cpus": cpus, "max_retries": cfg.retries, "retry_exceptions": False}
        if cfg.memory_per_task > 0:
            options["memory"] = int(cfg.memory_per_task * 2**30)
        if gpus and job.gpu:
            options["num_gpus"] = gpus
        deps = [refs[d] for d in job.deps]
        refs[job.id] = task.options(name=job.id, **options).remote(
            job, token, str(out), cpus, *deps
        )
    pending = {ref: job for job, ref in zip(jobs, refs.values(), strict=True)}
    slots = _slots(ray, cpus, cfg.memory_per_task)
    records: dict[str, dict] = {}
    bar = tqdm(total=len(jobs), unit="task", desc="batch", disable=cfg.quiet)
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                job = pending.pop(ref)
                records[job.id] = _record(ray, ref, job, records, cfg.retries)
                bar.write(finished_line(records[job.id]))
                bar.update(1)
                if records[job.id].get("storage") is False:
                    raise SineError(records[job.id]["message"])
            started = sum(all(d in records for d in job.deps) for job in pending.values())
            failed = sum(r["status"] == "failed" for r in records.values())
            bar.set_postfix(running=min(started, slots), failed=failed, refresh=False)
    finally:
        bar.close()
        for ref in pending:
            ray.cancel(ref, force=True)
    return records


def _slots(ray, cpus: int, memory: float) -> int:
    """How many tasks of `cpus` CPUs and `memory` GB the cluster runs at once."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    by_memory = [int(r.get("memory", 0) / 2**30 // memory) if memory > 0 else 10**6 for r in nodes]
    return max(
        1, sum(min(int(r.get("CPU", 0)) // cpus, m) for r, m in zip(nodes, by_memory, strict=True))
    )


def _record(ray, ref, job, records: dict, retries: int) -> dict:
    """The job's record; a task Ray gave up on (its worker died every time) becomes one."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayError as exc:
        failed = [d for d in job.deps if records.get(d, {}).get("status") == "failed"]
        message = (
            f"not run: {failed[0]} failed"
            if failed
            else f"its worker died {retries + 1} times ({type(exc).__name__}); see the Ray logs"
        )
        return failed_record(job, message)


def finished_line(record: dict) -> str:
    """One line per finished task: job, status, seconds, its headline number or its error."""
    line = f"{record['job']}: {record['status']} in {record['seconds']:.0f} s"
    key = HEADLINE.get(record["stage"])
    value = record.get("metrics", {}).get(key)
    if isinstance(value, float):
        line += f", {key} {value:.3f}"
    if record["status"] == "failed":
        line += f": {record['message']}"
    return line
