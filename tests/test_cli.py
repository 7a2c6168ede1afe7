"""The `sine` command itself: every subcommand documented, and a fast top-level --help."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import pytest

import sine_cli
from edit import commands as edit_commands
from recon import commands as recon_commands
from recon.fit_config import FitConfig
from render.configs import from_args, resolve_settings, write_settings
from render.errors import SineError

COMMANDS = [m.NAME for m in recon_commands.MODULES + edit_commands.MODULES]


def _subparser(parser, name):
    return next(a for a in parser._actions if a.dest == "command").choices[name]


@pytest.mark.parametrize("name", COMMANDS)
def test_every_option_of_every_command_has_help(name):
    sub = _subparser(sine_cli.build_parser([name]), name)
    options = [a for a in sub._actions if a.dest != "help"]
    assert options, name  # the full parser, not the one-line entry
    for action in options:
        assert action.help, (name, action.dest)
    # the formatter adds no defaults of its own (add_options already writes each one once)
    written = sum(a.help.count("(default:") for a in sub._actions if a.help)
    assert sub.format_help().count("(default:") == written


def test_top_level_help_lists_every_command_without_importing_torch():
    code = (
        "import sys, sine_cli\n"
        "try:\n"
        "    sine_cli.main(['--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "print('torch' in sys.modules, 'open3d' in sys.modules)\n"
    )
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=True
    ).stdout
    for name in COMMANDS:
        assert name in out
    assert out.strip().splitlines()[-1] == "False False"


def test_command_help_shows_the_command_options(capsys):
    with pytest.raises(SystemExit):
        sine_cli.main(["fit", "--help"])
    assert "--iterations" in capsys.readouterr().out


@pytest.mark.parametrize("name", COMMANDS)
def test_each_command_help_fits_a_screen_and_help_all_lists_every_setting(name, capsys):
    with pytest.raises(SystemExit):
        sine_cli.main([name, "--help"])
    text = capsys.readouterr().out
    assert len(text.splitlines()) <= 45, name
    assert sum(line.startswith("  -") for line in text.splitlines()) <= 15, name
    assert " dB" not in text  # no benchmark figures in help
    sub = _subparser(sine_cli.build_parser([name]), name)
    configs = sub.get_default("_configs") or []
    if not configs:
        return
    with pytest.raises(SystemExit):
        sine_cli.main([name, "--help-all"])
    listed = capsys.readouterr().out
    for cls, skip in configs:
        for f in dataclasses.fields(cls):
            assert f.name in skip or f"\n  {f.name}: " in listed, (name, f.name)


def _fit_settings(*args):
    parser = sine_cli.build_parser(["fit", "run", *args])
    return resolve_settings(parser.parse_args(["fit", "run", *args]))


def test_settings_come_from_the_file_then_set_then_flags(tmp_path):
    config = tmp_path / "fit.toml"
    config.write_text('iterations = 3\nlr_grid = 0.1\nbackground = "white"\n')
    args = _fit_settings(
        "--config", str(config), "--set", "lr_grid=0.5", "--set", "sampler=uniform",
        "--iterations", "7",
    )  # fmt: skip
    assert (args.iterations, args.lr_grid, args.background, args.sampler) == (
        7,
        0.5,
        "white",
        "uniform",
    )
    assert args.levels == FitConfig().levels  # the rest: defaults
    assert isinstance(
        _fit_settings("--set", "lr_grid=1").lr_grid, float
    )  # an int where a float goes
    assert _fit_settings("--set", "iterations=none").iterations is None  # an optional setting
    for bad, message in [
        (["--set", "bogus=1"], "unknown setting 'bogus'; `--help-all` lists the settings"),
        (["--set", "iterations=abc"], "setting 'iterations' must be int | None (got 'abc')"),
        (["--set", "iterations"], "--set 'iterations': write NAME=VALUE"),
        (["--config", str(tmp_path / "none.toml")], "does not exist"),
    ]:
        with pytest.raises(SineError, match=re.escape(message)):
            _fit_settings(*bad)
    (tmp_path / "broken.toml").write_text("iterations = = 3")
    with pytest.raises(SineError, match="is not a readable TOML file"):
        _fit_settings("--config", str(tmp_path / "broken.toml"))
    # what a stage saves reads back as the same config
    write_settings(tmp_path / "saved.toml", FitConfig(iterations=9, background="black"))
    args = _fit_settings("--config", str(tmp_path / "saved.toml"))
    assert from_args(FitConfig, args) == FitConfig(iterations=9, background="black")


def _readme_commands() -> list[list[str]]:
    """Every `sine ...` command line of README.md's code blocks, as argv (comments cut, the
    placeholders K / CAPTURE made concrete)."""
    import shlex

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    commands, block = [], False
    for line in text.splitlines():
        if line.strip().startswith("```"):
            block = not block
            continue
        words = line.split("#")[0].replace("|", " | ").strip()
        if (block or line.startswith("    ")) and words.startswith("sine "):
            argv = shlex.split(words.split(" | ")[0].replace(" K ", " 3 "))[1:]
            commands.append(argv)
    return commands


def test_every_readme_command_parses_with_its_settings():
    commands = _readme_commands()
    assert len(commands) >= 15
    for argv in commands:
        if "--help-all" in argv or "--config" in argv:  # exits / reads a run's file
            argv = [a for a in argv if a != "--help-all"]
            if "--config" in argv:
                k = argv.index("--config")
                argv = argv[:k] + argv[k + 2 :]
        args = sine_cli.build_parser(argv).parse_args(argv)
        resolve_settings(args)  # every --set names a setting of the right type


def test_an_edit_preset_sets_the_steps_unless_they_are_given():
    from edit.edit_stage import with_preset
    from edit.geometry_config import GeometryEditConfig
    from edit.texture_config import TextureEditConfig

    assert with_preset(GeometryEditConfig()).iterations == 600
    assert with_preset(TextureEditConfig(preset="fast")).iterations == 300
    assert with_preset(GeometryEditConfig(preset="quality", iterations=7)).iterations == 7
    with pytest.raises(SineError, match="--preset must be one of fast, default, quality"):
        with_preset(GeometryEditConfig(preset="slow"))
