"""Test-session settings shared by every test module."""

import os

# OpenMP threads sleep instead of spinning while they wait (as the `sine` CLI does): on a small,
# shared CPU spinning threads make torch ops several times slower. Set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
