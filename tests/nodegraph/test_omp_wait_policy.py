"""The `nodegraph` command makes OpenMP threads wait passively unless the user chose a policy
(spinning waiters made mode pursuit 9x slower on an oversubscribed 2-core machine)."""

from __future__ import annotations

import os
import subprocess
import sys

SCRIPT = ("import contextlib, io, os\n"
          "from nodegraph.cli import main\n"
          "with contextlib.redirect_stdout(io.StringIO()):\n"
          "    main(['nodes'])\n"
          "print(os.environ.get('OMP_WAIT_POLICY'))\n")


def _policy(value: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if value is not None:
        env["OMP_WAIT_POLICY"] = value
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1]


def test_passive_by_default_and_the_users_choice_kept():
    assert _policy(None) == "PASSIVE"
    assert _policy("ACTIVE") == "ACTIVE"
