"""`sine` subcommands of the editing side: masks (semantic masks) and demo."""

from __future__ import annotations

from edit import demo, masks_cli

MODULES = (masks_cli, demo)


def register(sub, selected: str | None = None) -> None:
    """Adds this package's subcommands to the `sine` parser (as `recon.commands.register`)."""
    for module in MODULES:
        if module.NAME == selected:
            module.add_parser(sub)
        else:
            sub.add_parser(module.NAME, help=module.HELP)
