"""`sine` subcommands that produce a run directory: ingest, synth, recon, fit, features."""

from __future__ import annotations


def register(sub) -> None:
    """Adds this package's subcommands to the `sine` parser."""
    # Each subcommand module exposes `add_parser(sub)`; they are filled in as stages land.
    for module_name in (
        "recon.ingest_cli",
        "recon.synth_cli",
        "recon.recon_cli",
        "recon.fit_cli",
        "recon.features_cli",
    ):
        try:
            module = __import__(module_name, fromlist=["add_parser"])
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            continue
        module.add_parser(sub)
