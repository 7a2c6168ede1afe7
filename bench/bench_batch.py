"""Many objects: the same batch run one command after another through the CLI, and by
`sine batch` on a local Ray, side by side in one run.

Per object: `sine synth` (a 24-view turntable of 128 px with a ground-truth stretch and recolour),
recon, fit (preset fast), features, a geometric and a texture edit (preset fast) and a GLB of
each edit. The sequential run types exactly the commands the batch runs (each with the batch
file's settings as --set), in the batch's order, each in its own process. Prints wall time,
the ratio, peak memory of the whole process tree, the per-stage seconds of the batch and the
disk each object takes, then writes bench/results/batch.json.

    python bench/bench_batch.py [--objects toycar figurine mug chair] [--cpus-per-task 1 2]
    python bench/bench_batch.py --quick     # 2 objects of 64 px, a few steps: checks it runs
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import tomli_w

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from edit.batch_file import plan_jobs, read_batch  # noqa: E402


def batch_file(objects: list[str], quick: bool) -> str:
    size, view = (64, "r_001.png") if quick else (128, "r_007.png")
    steps = {"fit": {"iterations": 40, "detail_steps": 0}, "edit": {"iterations": 10}}
    defaults = {
        "recon": {"width": size},
        "fit": steps["fit"] if quick else {"preset": "fast"},
        "features": {"iterations": 20} if quick else {},
        "edit": steps["edit"] if quick else {"preset": "fast"},
    }
    data = {"defaults": defaults, "capture": [], "edit": []}
    views = 10 if quick else 24
    for name in objects:
        synth = {"procedural": name, "views": views, "width": size, "height": size}
        data["capture"].append({"name": name, "synth": {**synth, "edit": ["geometric", "texture"]}})
        for kind, mode in (("geometric", "geometry"), ("texture", "texture")):
            edit = {"capture": name, "name": kind, "mode": mode, "view": view, "outputs": ["glb"]}
            edit["target"] = f"{{capture}}/edits/{kind}/images/{view}"
            if kind == "geometric":
                edit["mask"] = f"{{capture}}/edits/{kind}/masks/{view}"
            data["edit"].append(edit)
    return tomli_w.dumps(data)


def sequential(jobs_path: Path, out: Path) -> tuple[float, list[str]]:
    """Every job of the batch as its own `sine` command, one after another (a job whose
    dependency failed is left out, as the batch leaves it out); returns the failed jobs too."""
    t0, failed = time.perf_counter(), []
    for job in plan_jobs(read_batch(jobs_path), out):
        if any(d in failed for d in job.deps):
            failed.append(job.id)
            continue
        argv = list(job.argv)
        if job.stage == "edit":
            frames = json.loads((job.home / "run" / "cameras.json").read_text())["frames"]
            argv += ["--view", str([f["name"] for f in frames].index(job.view))]
        for key, value in job.settings.items():
            argv += ["--set", f"{key}={json.dumps(value)}"]  # JSON values are TOML ones
        done = subprocess.run([sys.executable, "-m", "sine_cli", *argv], capture_output=True)
        if done.returncode:
            failed.append(job.id)
            print(f"{job.id} failed: {done.stderr.decode().strip()[-300:]}")
    return time.perf_counter() - t0, failed


def batch(jobs_path: Path, out: Path, cpus: int) -> tuple[float, dict]:
    """`sine batch` of the same file (exit status 1 when a job failed, as the CLI's)."""
    command = [sys.executable, "-m", "sine_cli", "batch", str(jobs_path), "--out", str(out)]
    t0 = time.perf_counter()
    done = subprocess.run([*command, "--cpus-per-task", str(cpus), "--quiet"], capture_output=True)
    seconds = time.perf_counter() - t0
    if done.returncode not in (0, 1):
        raise SystemExit(f"sine batch failed: {done.stderr.decode()[-2000:]}")
    return seconds, json.loads((out / "batch_summary.json").read_text())


class PeakMemory:
    """Peak resident memory of this process's children, all together, sampled every 0.5 s."""

    def __init__(self):
        self.peak, self.stop = 0, threading.Event()
        self.thread = threading.Thread(target=self._watch, daemon=True)

    def _watch(self):
        me = psutil.Process()
        while not self.stop.wait(0.5):
            total = 0
            for child in me.children(recursive=True):
                try:
                    total += child.memory_info().rss
                except psutil.Error:
                    pass
            self.peak = max(self.peak, total)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()


def megabytes(folder: Path) -> float:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", nargs="+", default=["toycar", "figurine", "mug", "chair"])
    parser.add_argument("--cpus-per-task", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_batch"))
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    objects = ["toycar", "mug"] if args.quick else args.objects
    shutil.rmtree(args.out, ignore_errors=True)
    args.out.mkdir(parents=True)
    jobs_path = args.out / "jobs.toml"
    jobs_path.write_text(batch_file(objects, args.quick))

    rows, summaries = [], {}
    with PeakMemory() as memory:
        seconds, failed = sequential(jobs_path, args.out / "sequential")
    rows.append(("CLI, one command after another", seconds, memory.peak, len(failed)))
    for cpus in args.cpus_per_task:
        with PeakMemory() as memory:
            seconds, summaries[cpus] = batch(jobs_path, args.out / f"batch_{cpus}", cpus)
        failed = sum(j["status"] == "failed" for j in summaries[cpus]["jobs"])
        rows.append((f"sine batch, local Ray, {cpus} CPU per task", seconds, memory.peak, failed))

    base = rows[0][1]
    print(f"\n{len(objects)} objects ({', '.join(objects)}); {psutil.cpu_count()} CPUs")
    print("| run | wall s | vs CLI | peak memory GB | failed jobs |\n|---|---|---|---|---|")
    for name, seconds, peak, failed in rows:
        print(f"| {name} | {seconds:.0f} | {base / seconds:.2f}x | {peak / 2**30:.1f} | {failed} |")

    stage_seconds: dict[str, list[float]] = {}
    for job in summaries[args.cpus_per_task[0]]["jobs"]:
        stage_seconds.setdefault(job["stage"], []).append(job["seconds"])
    print(f"\nper-stage seconds in the batch ({args.cpus_per_task[0]} CPU per task; mean, max)")
    print("| stage | tasks | mean s | max s |\n|---|---|---|---|")
    for stage, values in stage_seconds.items():
        print(f"| {stage} | {len(values)} | {sum(values) / len(values):.1f} | {max(values):.1f} |")
    first = args.out / f"batch_{args.cpus_per_task[0]}"
    sizes = {name: megabytes(first / name) for name in objects}
    captures = {name: megabytes(first / name / "capture") for name in objects}
    print("\ndisk per object, MB (all of OUT/NAME; of which the synthetic capture)")
    for name in objects:
        print(f"| {name} | {sizes[name]:.1f} | {captures[name]:.1f} |")
    result = {
        "objects": objects,
        "cpus": psutil.cpu_count(),
        "rows": [{"run": r[0], "seconds": r[1], "peak_bytes": r[2], "failed": r[3]} for r in rows],
        "stage_seconds": stage_seconds,
        "object_megabytes": sizes,
        "capture_megabytes": captures,
    }
    path = REPO / "bench" / "results" / ("batch_quick.json" if args.quick else "batch.json")
    path.write_text(json.dumps(result, indent=1))
    print(f"-> {path}")


if __name__ == "__main__":
    main()
