"""`sine` subcommands that produce a run directory, in pipeline order (built by `sine_cli`)."""

from __future__ import annotations

from recon import fit_cli, ingest_cli, recon_cli, synth_cli

MODULES = (synth_cli, ingest_cli, recon_cli, fit_cli)
