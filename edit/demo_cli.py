"""`sine demo`: the command over `edit.demo.run_demo` (its description is edit/demo.py's)."""

from __future__ import annotations

import argparse
from pathlib import Path

from edit import demo
from edit.demo import DemoConfig, run_demo
from edit.demo_summary import summary_lines
from render.configs import add_options, from_args

DESCRIPTION = demo.__doc__
NAME = "demo"
HELP = "run the whole pipeline on a built-in procedural object, with a geometric and a texture edit"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, DemoConfig, shown=("out", "fast", "procedural", "device", "force"))


def run(args: argparse.Namespace) -> int:
    summary = run_demo(from_args(DemoConfig, args))
    out = Path(args.out)
    print("\n== sine demo: summary ==")
    for line in summary_lines(summary):
        print(f"  {line}")
    print(f"  seconds per stage: {summary['seconds']} (total {summary['seconds_total']})")
    if summary["seconds_work_total"] != summary["seconds_total"]:
        print(f"  (with the skipped stages' own time: {summary['seconds_work_total']} s)")
    print(f"\nLook at: {out / 'summary.png'} (views x template | each edit | its ground truth)")
    print(f"         {out / 'summary.html'} (everything below, with the videos)")
    print(f"         {out / 'compare.mp4'} (orbit: template | geometric edit | texture edit)")
    if "viewer" in summary["files"]:
        print(f"         {out / 'viewer.png'} (template and edited mesh, cameras)")
    print(f"         {out / 'edited.glb'}, {out / 'texture_edited.glb'} (the edited meshes)")
    print(f"         {out / 'run' / 'recon_contact_sheet.png'} (reconstruction)")
    print(f"Numbers: {out / 'demo_summary.json'}")
    return 0
