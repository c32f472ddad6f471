"""The test session keeps out of the user's home directory."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from conftest import REAL_HOME


def test_home_is_private_for_tests_and_their_subprocesses() -> None:
    home = Path.home()
    assert home != REAL_HOME and home.name.startswith("gr_graph-test-home-")
    out = subprocess.run([sys.executable, "-c", "from pathlib import Path; print(Path.home())"],
                         capture_output=True, text=True, check=True, env=os.environ.copy())
    assert Path(out.stdout.strip()) == home


def test_evo_settings_land_in_the_private_home() -> None:
    """evo's CLI creates ``~/.evo/settings.json`` on first use: it must not be the real home's."""
    code = "from evo.tools.settings import USER_ASSETS_PATH; print(USER_ASSETS_PATH)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assets = Path(out.stdout.strip().splitlines()[-1])  # evo may print "Initialized new ..." first
    assert assets.parent == Path.home()
    assert REAL_HOME not in assets.parents
