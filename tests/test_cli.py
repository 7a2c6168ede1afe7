"""The `sine` command itself: every subcommand documented, and a fast top-level --help."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

import sine_cli
from edit import commands as edit_commands
from recon import commands as recon_commands

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
