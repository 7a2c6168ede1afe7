"""`sine` subcommands of the editing side: masks (semantic masks) and demo (built by
`sine_cli`)."""

from __future__ import annotations

from edit import demo, masks_cli

MODULES = (masks_cli, demo)
