"""`sine` subcommands that produce a run directory: ingest, synth, recon, fit, features."""

from __future__ import annotations

from recon import features_cli, fit_cli, ingest_cli, recon_cli, synth_cli


def register(sub) -> None:
    """Adds this package's subcommands to the `sine` parser (in pipeline order)."""
    for module in (synth_cli, ingest_cli, recon_cli, fit_cli, features_cli):
        module.add_parser(sub)
