"""`sine` subcommands of the editing side: masks (semantic masks) and demo."""

from __future__ import annotations

from edit import demo, masks_cli


def register(sub) -> None:
    """Adds this package's subcommands to the `sine` parser."""
    masks_cli.add_parser(sub)
    demo.add_parser(sub)
