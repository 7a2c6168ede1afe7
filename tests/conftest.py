"""Settings and shared runs of every test module."""

import os

# OpenMP threads sleep instead of spinning while they wait (as the `sine` CLI does): on a small,
# shared CPU spinning threads make torch ops several times slower. Set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


# ---- shared runs ---------------------------------------------------------------------------
import pytest  # noqa: E402


@pytest.fixture(scope="session")
def tiny_fitted_run(tmp_path_factory):
    """A tiny run directory with a fitted template (toycar, 8 views of 64x64, the GT mesh as
    proxy; tests/feature_run_helpers.py), built once per test run. Read-only: copy it to change it."""
    from feature_run_helpers import tiny_feature_run

    return tiny_feature_run(tmp_path_factory, features=False)
