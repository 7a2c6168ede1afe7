"""`sine batch JOBS.toml --out DIR`: the command over `edit.batch.run_batch`."""

from __future__ import annotations

import argparse
from pathlib import Path

from render.configs import add_options, from_args

NAME = "batch"
HELP = "run many captures and edits from a batch file, as Ray tasks (local or a cluster)"
DESCRIPTION = """\
Runs every stage of every capture and edit listed in JOBS.toml (recon, fit, features, edits,
videos, meshes, scores) as Ray tasks: on a local Ray started here, or on a cluster with
--address auto (after `ray start --head` on one machine and `ray start --address HEAD:6379` on
the others; --out must be a folder every machine sees). Finished stages are skipped, so a second
run does only what is missing. A capture or edit that fails reports its error; the others go on.
Writes DIR/OBJECT/ per capture, DIR/batch_summary.json and DIR/batch_summary.html. The batch
file's format: datasets/batch_example.toml.

example:
  sine batch datasets/batch_example.toml --out runs/batch
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from edit.batch import BatchConfig

    parser.add_argument("jobs", type=Path, help="the batch file (TOML)")
    add_options(parser, BatchConfig, skip=("jobs",))


def run(args: argparse.Namespace) -> int:
    from edit.batch import BatchConfig, run_batch
    from edit.batch_summary import summary_line

    summary = run_batch(from_args(BatchConfig, args))
    print(summary_line(summary))
    return 1 if any(j["status"] == "failed" for j in summary["jobs"]) else 0
