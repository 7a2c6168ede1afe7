"""`sine` subcommands of the editing side: masks (semantic masks), snapshot and target (a view
to edit, 2D editing targets) and demo (built by `sine_cli`)."""

from __future__ import annotations

from edit import demo, masks_cli, snapshot_cli, target_cli

MODULES = (masks_cli, snapshot_cli, target_cli, demo)
