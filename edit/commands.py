"""`sine` subcommands of the editing side."""

from __future__ import annotations


def register(sub) -> None:
    """Adds this package's subcommands to the `sine` parser."""
