"""`sine` subcommands that produce a run directory: ingest, synth, recon, fit, features."""

from __future__ import annotations

from recon import features_cli, fit_cli, ingest_cli, recon_cli, synth_cli

MODULES = (synth_cli, ingest_cli, recon_cli, fit_cli, features_cli)  # pipeline order


def register(sub, selected: str | None = None) -> None:
    """Adds this package's subcommands to the `sine` parser: the full parser (options from the
    library configs, which import torch / Open3D) only for the `selected` command, a one-line
    entry for the others (so `sine --help` stays fast)."""
    for module in MODULES:
        if module.NAME == selected:
            module.add_parser(sub)
        else:
            sub.add_parser(module.NAME, help=module.HELP)
