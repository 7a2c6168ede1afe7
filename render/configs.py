"""Typed dataclass configs that become command-line options.

Every config field is declared with `option(default, "help text")`; the help text is the field's
documentation and the CLI's `--help`. `add_options` turns a dataclass into argparse options,
`from_args` builds the dataclass back from parsed arguments (and checks it with `validate`),
`to_dict` is what gets saved in the run directory's `config.yaml`; `from_dict` / `to_json` /
`from_json` are the one (de)serialiser of configs, nested ones included (field configs in
checkpoints are JSON text). `option(..., low=, high=)` declares a numeric range that `validate`
checks before any work starts.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


def option(
    default: Any = dataclasses.MISSING,
    help: str = "",
    *,
    choices=None,
    flag=None,
    low: float | None = None,
    high: float | None = None,
):
    """A dataclass field with its help text (and optional choices / explicit flag name / the
    range [low, high] its value, or each item of a list value, must lie in)."""
    metadata = {"help": help, "choices": choices, "flag": flag, "low": low, "high": high}
    if isinstance(default, (list, dict, set)):
        value = default
        return dataclasses.field(default_factory=lambda: type(value)(value), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def _base_type(tp: Any) -> tuple[Any, bool]:
    """Strips Optional[...] and returns (type, is_optional)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0], True
    return tp, False


def add_options(parser: argparse.ArgumentParser, cls: type, skip: tuple[str, ...] = ()) -> None:
    """Adds one `--name` option per dataclass field of `cls` (except those in `skip`)."""
    hints = typing.get_type_hints(cls)
    group = parser.add_argument_group(f"{cls.__name__} options")
    own = cls.__dict__.get("__annotations__", {})  # the class's own options first, then inherited
    for f in sorted(dataclasses.fields(cls), key=lambda f: f.name not in own):
        if f.name in skip:
            continue
        tp, _ = _base_type(hints[f.name])
        flag = _flag(f)
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        help_text = f.metadata.get("help", "")
        kwargs: dict[str, Any] = {"dest": f.name, "help": f"{help_text} (default: {default})"}
        if f.metadata.get("choices"):
            kwargs["choices"] = f.metadata["choices"]
        if tp is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
            kwargs["default"] = default
        elif typing.get_origin(tp) in (list, tuple):
            item = typing.get_args(tp)[0]
            kwargs.update(nargs="+", type=item, default=default)
        else:
            kwargs.update(type=Path if tp is Path else tp, default=default)
        group.add_argument(flag, **kwargs)


def add_training_arguments(parser: argparse.ArgumentParser, cls: type, run_help: str) -> None:
    """The arguments of a training stage's command: RUN, --force, --quiet and `cls`'s options."""
    parser.add_argument("run", type=Path, help=run_help)
    parser.add_argument(
        "--force",
        action="store_true",
        help="train again even when finished with these options (the old results stay until "
        "the new run has finished)",
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no progress bar, only the summary line"
    )
    add_options(parser, cls)


def _flag(f: dataclasses.Field) -> str:
    return f.metadata.get("flag") or "--" + f.name.replace("_", "-")


def from_args(cls: type[T], args: argparse.Namespace, **overrides: Any) -> T:
    """Builds `cls` from parsed arguments (fields not on the command line keep their defaults)
    and validates it (a SineError names the first option out of range)."""
    values = {}
    for f in dataclasses.fields(cls):
        if f.name in overrides:
            values[f.name] = overrides[f.name]
        elif hasattr(args, f.name):
            values[f.name] = getattr(args, f.name)
    return validate(cls(**values))


def validate(config: T) -> T:
    """Checks every option declared with a range (`low`/`high`) or `choices`; returns `config`.

    Raises SineError("--iterations must be >= 1 (got -5)") for the first bad value."""
    from render.errors import SineError

    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        items = value if isinstance(value, (list, tuple)) else [value]
        low, high, choices = (f.metadata.get(k) for k in ("low", "high", "choices"))
        for item in items:
            if item is None or isinstance(item, bool):
                continue
            if choices and item not in choices:
                raise SineError(f"{_flag(f)} must be one of {', '.join(map(str, choices))}")
            if low is not None and item < low:
                raise SineError(f"{_flag(f)} must be >= {low} (got {item})")
            if high is not None and item > high:
                raise SineError(f"{_flag(f)} must be <= {high} (got {item})")
    return config


def to_dict(config: Any) -> dict:
    """A dataclass config as plain YAML-able values."""
    out = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            value = to_dict(value)
        elif isinstance(value, Path):
            value = str(value)
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out


def from_dict(cls: type[T], data: dict) -> T:
    """Builds `cls` from a dict (e.g. a saved config; nested dataclass fields from nested dicts),
    ignoring unknown keys; missing keys keep their defaults."""
    hints = typing.get_type_hints(cls)
    values = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value, (tp, _) = data[f.name], _base_type(hints[f.name])
        if dataclasses.is_dataclass(tp) and isinstance(value, dict):
            value = from_dict(tp, value)
        elif tp is Path and value is not None:
            value = Path(value)
        values[f.name] = value
    return cls(**values)


def to_json(config: Any) -> str:
    """A dataclass config as JSON text (how checkpoints and field files store configs)."""
    return json.dumps(to_dict(config), sort_keys=True)


def from_json(cls: type[T], text: str) -> T:
    """The config `to_json` wrote (unknown keys ignored)."""
    return from_dict(cls, json.loads(text))
