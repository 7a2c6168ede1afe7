"""The format version of each stage's results.

Every stage records `format_version` with what it writes: recon in recon_state.json, the training
stages (fit, features, edit) in their checkpoint.pt and metrics.json, and the torch files a later
stage loads (template/field.pt, features/field.pt, edits/NAME/edit_field.pt). A stage finds a
result of another version out of date and redoes it, saying so in one line; a later stage that
loads such a file refuses it with the command that redoes it.

Bump a stage's number whenever a change alters what its results mean: a default that changes the
behaviour, a file's layout, a network's parameters. A result recorded before format versions
existed counts as version 0.
"""

from __future__ import annotations

from pathlib import Path

from render.errors import SineError

FORMAT_VERSIONS = {"recon": 1, "fit": 1, "features": 1, "edit": 1}


def format_change(found, stage: str) -> str | None:
    """The one-line reason a result recorded with format version `found` (None: not recorded) is
    out of date for `stage`, None when it is current."""
    return version_change(found, FORMAT_VERSIONS[stage])


def version_change(found, current: int) -> str | None:
    """`format_change` against the version `current`."""
    found = 0 if found is None else found
    if found == current:
        return None
    return f"written in format version {found}, this version writes {current}"


def check_format(data: dict, path: Path, stage: str, command: str) -> None:
    """Refuses a loaded torch file `data` (from `path`) of another format version than `stage`'s
    current one, naming the `command` that makes it again."""
    change = format_change(data.get("format_version"), stage)
    if change is not None:
        raise SineError(f"{path} is out of date ({change}); run {command}")
