"""The `sine` command: a thin layer over the library.

Each package registers its own subcommands (`recon.commands`, `edit.commands`); this module only
builds the parser, picks the device/thread settings and turns user errors into one readable line.
"""

from __future__ import annotations

import argparse
import os
import sys

# OpenMP threads that sleep instead of spinning while waiting: on a small, shared CPU (2 cores,
# other processes running) spinning threads make torch ops 3-5x slower (measured in
# bench/RESULTS.md, "Hash grid"). Must be set before torch is imported; the user's value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


class ShortUsageFormatter(argparse.RawDescriptionHelpFormatter):
    """`usage: sine CMD [options] POSITIONALS`: the options are listed below it anyway."""

    def _format_usage(self, usage, actions, groups, prefix):
        names = [a.metavar or a.dest for a in actions if not a.option_strings]
        return f"usage: {self._prog} [options] {' '.join(names)}\n\n"


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The `sine` parser. Each command module has NAME, HELP, DESCRIPTION, add_arguments(parser)
    and run(args); only the command named in `argv` gets its options (they come from library
    configs that import torch and Open3D, which `sine --help` does not need)."""
    from edit import commands as edit_commands
    from recon import commands as recon_commands

    args = sys.argv[1:] if argv is None else argv
    selected = next((a for a in args if not a.startswith("-")), None)
    parser = argparse.ArgumentParser(
        prog="sine",
        description=(
            "SINE: reconstruct an object from a turntable capture, then edit it in 3D from one "
            "edited image. Run `sine COMMAND --help` for each command's options."
        ),
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in recon_commands.MODULES + edit_commands.MODULES:
        if module.NAME != selected:
            sub.add_parser(module.NAME, help=module.HELP)
            continue
        command = sub.add_parser(
            module.NAME,
            help=module.HELP,
            description=module.DESCRIPTION,
            formatter_class=ShortUsageFormatter,
        )
        module.add_arguments(command)
        command.set_defaults(func=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    from render.configs import resolve_settings
    from render.errors import SineError
    from render.io import WRITE_ERRORS, write_error

    parser = build_parser(argv)
    args = parser.parse_args(argv)
    try:
        result = args.func(resolve_settings(args))
    except SineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a read-only or protected folder: not a bug
        if exc.errno not in WRITE_ERRORS:
            raise
        print(f"error: {write_error(exc.filename or 'a file', exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(
            "interrupted: finished artefacts and checkpoints are kept; re-run to resume",
            file=sys.stderr,
        )
        return 130
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
