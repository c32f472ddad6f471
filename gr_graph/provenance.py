"""Provenance of a result: which code, which packages, which seeds, threads and device made it.

Every run's ``metrics.json`` and every training ``summary.json`` carry the dict of
:func:`provenance` under the key ``"provenance"``, so that a figure can be traced back to a
commit and an environment, and a run can be repeated.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]

# Distributions whose versions decide the numbers (names as pip knows them).
TRACKED_DISTRIBUTIONS = (
    "gr-graph", "numpy", "scipy", "torch", "gtsam", "small_gicp", "open3d-cpu", "open3d",
    "evo", "kiss-matcher", "kiss-icp", "pydantic", "matplotlib",
)


def git_state(repo: Path = REPO_ROOT) -> dict[str, Any]:
    """``{"commit": sha or None, "dirty": bool or None}`` of the checkout holding the code.

    Both are None when the code is not in a git checkout (an installed wheel) or git is absent.
    ``dirty`` ignores untracked files (run outputs under the checkout are common).
    """
    def run(*args: str) -> str | None:
        try:
            out = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return out.stdout if out.returncode == 0 else None

    commit = run("rev-parse", "HEAD")
    if commit is None:
        return {"commit": None, "dirty": None}
    status = run("status", "--porcelain", "--untracked-files=no")
    return {"commit": commit.strip(), "dirty": None if status is None else bool(status.strip())}


def package_versions(names: tuple[str, ...] = TRACKED_DISTRIBUTIONS) -> dict[str, str]:
    """Installed version of each distribution in ``names`` that is installed."""
    versions: dict[str, str] = {}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return versions


def thread_count() -> int | None:
    """Threads torch computes with (``torch.get_num_threads``); None when torch is not imported."""
    torch = sys.modules.get("torch")
    return int(torch.get_num_threads()) if torch is not None else None


def cpu_description() -> dict[str, str | None]:
    """The CPU model (``/proc/cpuinfo``'s ``model name``, else :func:`platform.processor`) and
    the instruction set torch's CPU kernels use (``torch.backends.cpu.get_cpu_capability()``,
    e.g. ``AVX2`` or ``AVX512``; None when torch is not loaded, as in a round-0 run) beside the
    vector extensions the CPU has (``simd``, from ``/proc/cpuinfo``'s flags). Float results of training can
    differ between kernel sets, so a result names both."""
    model, simd = None, None
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                low = line.lower()
                if model is None and low.startswith("model name"):
                    model = line.split(":", 1)[1].strip() or None
                elif simd is None and low.startswith("flags"):
                    flags = set(low.split(":", 1)[1].split())
                    simd = " ".join(x for x in ("avx512f", "avx2", "fma", "neon", "asimd") if x in flags) or None
                if model is not None and simd is not None:
                    break
    except OSError:
        pass
    torch = sys.modules.get("torch")
    capability = None
    if torch is not None:
        try:
            capability = str(torch.backends.cpu.get_cpu_capability())
        except (AttributeError, RuntimeError):
            capability = None
    return {"model": model or platform.processor() or platform.machine() or None, "simd": simd,
            "torch_capability": capability}


def provenance(seeds: dict[str, int] | None = None, device: str = "cpu",
               num_threads: int | None = None) -> dict[str, Any]:
    """Everything needed to trace and repeat a result.

    Parameters
    ----------
    seeds : dict of str to int, optional
        The seeds of the run by role (e.g. ``{"training": 0, "world": 0}``).
    device : str
        ``"cpu"`` or ``"cuda[:k]"``.
    num_threads : int, optional
        Threads used; defaults to torch's thread count when torch is loaded.

    Returns
    -------
    dict
        ``git`` (commit, dirty), ``packages`` (name -> version), ``python``, ``platform``,
        ``seeds``, ``num_threads``, ``torch_threads`` (None when torch is not loaded),
        ``cpu_count``, ``cpu`` (:func:`cpu_description`), ``device`` and the thread-related
        environment variables that were set.
    """
    env_keys = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "CUBLAS_WORKSPACE_CONFIG")
    return {
        "git": git_state(),
        "packages": package_versions(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "seeds": dict(seeds or {}),
        "num_threads": num_threads if num_threads is not None else thread_count(),
        "torch_threads": thread_count(),
        "cpu_count": os.cpu_count(),
        "cpu": cpu_description(),
        "device": device,
        "environment": {k: os.environ[k] for k in env_keys if k in os.environ},
    }


def machine_line() -> str:
    """One line naming the machine: CPU model and torch's kernel instruction set, core count,
    platform, Python (imports torch, so that the instruction set is known)."""
    import torch  # noqa: F401

    return format_machine(cpu_description(), os.cpu_count(), platform.platform(), platform.python_version())


def format_machine(cpu: dict[str, Any], cpu_count: int | None, platform_name: str | None, python: str | None) -> str:
    """The line of :func:`machine_line` from its parts, e.g. from a stored :func:`provenance`
    (``cpu``, ``cpu_count``, ``platform``, ``python``): an unknown CPU model reads "unknown CPU",
    an unknown kernel instruction set (torch not loaded) is left out."""
    kernels = cpu.get("torch_capability")
    model = cpu.get("model") or "unknown CPU"
    return (f"{model}{f' (torch kernels {kernels})' if kernels else ''}, {cpu_count} cores, "
            f"{platform_name}, Python {python}")
