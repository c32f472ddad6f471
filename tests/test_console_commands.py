"""Console commands: declared in pyproject, resolving to the modules' ``main``, runnable as
``python -m`` and (when the package is installed with them) as scripts; ``--dump-config``."""

from __future__ import annotations

import importlib
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

from gr_graph.config import SlamConfig, load_config

REPO = Path(__file__).resolve().parents[1]
COMMANDS = {
    "gr-slam": "gr_graph.slam:main",
    "gr-train": "training.train:main",
    "gr-densify": "gr_graph.densify_cli:main",
    "gr-registration": "gr_graph.global_registration:main",
}


def _env() -> dict[str, str]:
    """The subprocess imports this tree's code (the venv's editable install may point elsewhere)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    return env


def test_entry_points_are_declared_and_resolve_to_callables() -> None:
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts == COMMANDS
    for target in scripts.values():
        module, attr = target.split(":")
        func = getattr(importlib.import_module(module), attr)
        assert callable(func)
        with pytest.raises(SystemExit) as exc:  # the function is the module's CLI
            func(["--help"])
        assert exc.value.code == 0


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_python_m_forms_run(command: str) -> None:
    module = COMMANDS[command].split(":")[0]
    r = subprocess.run([sys.executable, "-m", module, "--help"], cwd=REPO, env=_env(), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "examples:" in r.stdout


def _dump(cmd: list[str], tmp_path: Path) -> dict:
    r = subprocess.run(cmd, cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return yaml.safe_load(r.stdout)


def test_dump_config_prints_the_resolved_configuration(tmp_path: Path) -> None:
    cfg_file = tmp_path / "in.yaml"
    cfg_file.write_text(yaml.safe_dump({"loops": {"min_frame_gap": 77}, "data": {"channels": 32}}))
    # defaults: the whole SlamConfig, every section
    defaults = _dump([sys.executable, "-m", "gr_graph.slam", "--dump-config"], tmp_path)
    expected = SlamConfig().model_dump(mode="json")
    expected["sensor"] = {}  # the sensor keys that were given only: unsaid ones are guessed from the data
    assert defaults == expected
    # --config, then options on top (the command line wins over the file)
    dumped = _dump([sys.executable, "-m", "gr_graph.slam", "--config", str(cfg_file), "--channels", "16",
                    "--rounds", "2", "--dump-config"], tmp_path)
    assert dumped["loops"]["min_frame_gap"] == 77 and dumped["data"]["channels"] == 16
    assert dumped["training"]["rounds"] == 2
    resolved = load_config(cfg_file, {"data": {"channels": 16}, "training": {"rounds": 2}})
    assert dumped == {**resolved.model_dump(mode="json"), "sensor": resolved.sensor.model_dump(mode="json", exclude_unset=True)}
    # the dump is a valid config file that gives the same configuration back
    again = tmp_path / "again.yaml"
    again.write_text(yaml.safe_dump(dumped))
    assert load_config(again) == resolved
    assert not (tmp_path / "runs").exists()  # nothing was run


def test_dump_config_refuses_a_bad_config(tmp_path: Path, capsys) -> None:
    from gr_graph.slam import main

    bad = tmp_path / "bad.yaml"
    bad.write_text("loops: {no_such_key: 1}\n")
    assert main(["--config", str(bad), "--dump-config"]) == 2
    assert "no_such_key" in capsys.readouterr().err


def test_console_scripts_when_installed(tmp_path: Path) -> None:
    """Run through the installed console scripts (``pip install -e .`` of this tree)."""
    bindir = Path(sys.executable).parent
    missing = [c for c in COMMANDS if shutil.which(c, path=str(bindir)) is None]
    if missing:
        pytest.skip(f"console scripts {missing} not installed in {bindir} (pip install -e . installs them)")
    dumped = _dump([str(bindir / "gr-slam"), "--dump-config", "--channels", "32"], tmp_path)
    assert dumped["data"]["channels"] == 32
    for command in COMMANDS:
        r = subprocess.run([str(bindir / command), "--help"], env=_env(), capture_output=True, text=True, timeout=120)
        assert r.returncode == 0 and "examples:" in r.stdout, (command, r.stderr)
