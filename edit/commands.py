"""`sine` subcommands of the editing side."""

from __future__ import annotations


def register(sub) -> None:
    """Adds this package's subcommands to the `sine` parser."""
    # Each subcommand module exposes `add_parser(sub)`; they are filled in as stages land.
    for module_name in ("edit.masks_cli",):
        try:
            module = __import__(module_name, fromlist=["add_parser"])
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            continue
        module.add_parser(sub)
