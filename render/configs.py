"""Typed dataclass configs that become command-line settings.

Every config field is declared with `option(default, "help text")`; the help text is the field's
documentation. `add_options` turns a dataclass into a command's settings: the few a user sets
(`shown`) appear in `--help` as `--name VALUE` flags; every field, shown or not, is set with
`--set name=value` (repeatable), a `--config FILE.toml` of `name = value` lines (what each stage
saves as config.toml beside its results: `write_settings`), or its `--name VALUE` flag, and
`--help-all` lists them all with type, default and meaning. Later wins: defaults, then the config
file, then --set, then flags (`resolve_settings`, called once after parsing).
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
import textwrap
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import tomli_w

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

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


def add_options(
    parser: argparse.ArgumentParser,
    cls: type,
    skip: tuple[str, ...] = (),
    shown: tuple[str, ...] | None = None,
) -> None:
    """Makes the fields of `cls` (except those in `skip`) settings of the command: `shown` ones
    (None: all) in --help, the others in --help-all only (see the module docstring)."""
    hints = typing.get_type_hints(cls)
    _add_setting_arguments(parser)
    parser.set_defaults(_configs=[*(parser.get_default("_configs") or []), (cls, tuple(skip))])
    group = parser.add_argument_group("settings (--help-all lists every other one)")
    own = cls.__dict__.get("__annotations__", {})  # the class's own options first, then inherited
    for f in sorted(dataclasses.fields(cls), key=lambda f: f.name not in own):
        if f.name in skip:
            continue
        tp, _ = _base_type(hints[f.name])
        visible = shown is None or f.name in shown
        help_text = f"{_brief(f.metadata.get('help', ''))} (default: {_default(f)})"
        kwargs: dict[str, Any] = {
            "dest": f.name,
            "help": help_text if visible else argparse.SUPPRESS,
            "default": argparse.SUPPRESS,  # the namespace holds what was given (resolve_settings)
        }
        if f.metadata.get("choices"):
            kwargs["choices"] = f.metadata["choices"]
        if tp is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif typing.get_origin(tp) in (list, tuple):
            kwargs.update(nargs="+", type=typing.get_args(tp)[0])
        else:
            kwargs["type"] = Path if tp is Path else tp
        group.add_argument(_flag(f), **kwargs)


def _default(f: dataclasses.Field) -> Any:
    return f.default if f.default is not dataclasses.MISSING else f.default_factory()


def _brief(text: str, limit: int = 90) -> str:
    """The first clause of a help text (the whole text is in --help-all)."""
    for stop in (". ", "; ", " (", ": "):
        cut = text.find(stop)
        if 12 <= cut < len(text) - 1:
            text = text[:cut]
    return text if len(text) <= limit else text[: limit - 3].rsplit(" ", 1)[0] + " ..."


def _add_setting_arguments(parser: argparse.ArgumentParser) -> None:
    """--config, --set and --help-all (once per parser)."""
    if parser.get_default("_configs") is not None:
        return
    parser.add_argument(
        "--config",
        type=Path,
        action="append",
        metavar="FILE.toml",
        help="settings from a TOML file, e.g. a run's config.toml",
    )
    parser.add_argument(
        "--set",
        action="append",
        metavar="NAME=VALUE",
        dest="settings",
        help="one setting, repeatable (--help-all lists them)",
    )
    parser.add_argument("--help-all", action=_HelpAll, nargs=0, help="list every setting and exit")


class _HelpAll(argparse.Action):
    def __call__(self, parser, namespace, values, option_string=None):
        print(settings_help(parser.prog, parser.get_default("_configs") or []))
        parser.exit()


def settings_help(prog: str, configs: list[tuple[type, tuple[str, ...]]]) -> str:
    """Every setting of the config classes `configs`: name, type, default, meaning."""
    lines = [
        f"settings of `{prog}`: --set NAME=VALUE, `NAME = VALUE` lines in a --config FILE.toml,"
        " or --NAME VALUE (later wins: file, --set, flags)"
    ]
    seen: set[str] = set()
    for cls, skip in configs:
        hints = typing.get_type_hints(cls)
        lines.append(f"\n{cls.__name__}: {(cls.__doc__ or '').strip().splitlines()[0]}")
        for f in dataclasses.fields(cls):
            if f.name in skip or f.name in seen:
                continue
            seen.add(f.name)
            kind = _type_name(hints[f.name])
            choices = f.metadata.get("choices")
            kind += f" ({'|'.join(map(str, choices))})" if choices else ""
            lines.append(f"  {f.name}: {kind} = {_default(f)!r}")
            lines += textwrap.wrap(
                f.metadata.get("help", ""), 96, initial_indent=" " * 6, subsequent_indent=" " * 6
            )
    return "\n".join(lines)


def _type_name(tp: Any) -> str:
    base, optional = _base_type(tp)
    name = getattr(base, "__name__", str(base))
    if typing.get_origin(base) in (list, tuple):
        name = f"list[{typing.get_args(base)[0].__name__}]"
    return f"{name} | None" if optional else name


def resolve_settings(args: argparse.Namespace, base: dict | None = None) -> argparse.Namespace:
    """Fills every setting of the parsed command into `args`: defaults, then `base` (a batch
    file's settings), then --config files, then --set, then flags. Raises SineError for an
    unknown name or a value of the wrong type."""
    from render.errors import SineError

    fields: dict[str, tuple[dataclasses.Field, Any]] = {}
    for cls, skip in getattr(args, "_configs", None) or []:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if f.name not in skip:
                fields.setdefault(f.name, (f, hints[f.name]))
    if not fields:
        if base:
            raise SineError(f"this command has no settings (got {', '.join(base)})")
        return args
    given: dict[str, Any] = dict(base or {})
    for path in getattr(args, "config", None) or []:
        given.update(read_settings(path))
    for item in getattr(args, "settings", None) or []:
        name, sep, text = item.partition("=")
        if not sep:
            raise SineError(f"--set {item!r}: write NAME=VALUE (e.g. --set iterations=500)")
        given[name.strip()] = _parse_value(text.strip())
    flagged = {name for name in fields if hasattr(args, name)}  # flags win
    for name, value in given.items():
        if name not in fields:
            raise SineError(f"unknown setting {name!r}; `--help-all` lists the settings")
        value = _coerce(name, value, fields[name][1])
        if name not in flagged:
            setattr(args, name, value)
    for name, (f, _) in fields.items():
        if not hasattr(args, name):
            setattr(args, name, _default(f))
    return args


def read_settings(path: Path) -> dict:
    """The `name = value` table of a TOML config file (a SineError when it is not one)."""
    from render.errors import SineError

    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise SineError(f"--config {path} does not exist") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise SineError(f"--config {path} is not a readable TOML file ({exc})") from None


def _parse_value(text: str) -> Any:
    """A --set value as TOML (numbers, true/false, [lists], "strings"); else the bare text."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _coerce(name: str, value: Any, hint: Any) -> Any:
    """`value` as the field's type (int -> float, str -> Path, "none" -> None when optional)."""
    from render.errors import SineError

    tp, optional = _base_type(hint)
    if optional and (value is None or value == "none"):
        return None
    items_type = typing.get_args(tp)[0] if typing.get_origin(tp) in (list, tuple) else None
    if items_type is not None:
        items = value if isinstance(value, list) else [value]
        return [_coerce(name, item, items_type) for item in items]
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp is Path and isinstance(value, str):
        return Path(value)
    if (
        isinstance(tp, type)
        and isinstance(value, tp)
        and not (tp is int and isinstance(value, bool))
    ):
        return value
    raise SineError(f"setting {name!r} must be {_type_name(hint)} (got {value!r})")


def write_settings(path: Path, config: Any) -> None:
    """Writes a config (dataclass or dict of settings) as TOML that `--config` reads back
    (settings left at None are left out: they read back as their default, None)."""
    from render.io import write_text_atomic

    values = to_dict(config) if dataclasses.is_dataclass(config) else dict(config)
    values = {k: v for k, v in values.items() if v is not None}
    write_text_atomic(path, tomli_w.dumps(values))


def add_training_arguments(
    parser: argparse.ArgumentParser, cls: type, run_help: str, shown: tuple[str, ...] | None = None
) -> None:
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
    add_options(parser, cls, shown=shown)


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
