"""``--viz``: an open3d window on a run's map, when the machine has a display.

Without a display (no ``DISPLAY`` / ``WAYLAND_DISPLAY`` on Linux, or an X display that does not
open) :func:`show_map` prints one
message saying so and where the map is, and returns False; it never raises for a missing
display or a window that cannot open.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["display_available", "show_map"]


def display_available() -> tuple[bool, str]:
    """``(True, "")`` if a window can be opened, else ``(False, why)``.

    An X display named by ``DISPLAY`` alone is opened once to check it (a dead SSH forwarding or a
    container that inherited ``DISPLAY``: open3d would fall back to offscreen rendering and block
    with no window); where libX11 cannot be loaded the variable is trusted."""
    if sys.platform in ("darwin", "win32"):
        return True, ""
    if os.environ.get("WAYLAND_DISPLAY"):
        return True, ""
    display = os.environ.get("DISPLAY")
    if not display:
        return False, "no display (neither DISPLAY nor WAYLAND_DISPLAY is set)"
    if _x_display_opens(display) is False:
        return False, f"the X display DISPLAY={display} cannot be opened (X forwarding ended? no X server?)"
    return True, ""


#: Seconds to wait for an X server to answer (a listener that never answers: a stalled forwarding).
X_PROBE_TIMEOUT_S = 3.0


def _x_display_opens(display: str) -> bool | None:
    """Whether libX11 can open ``display`` within :data:`X_PROBE_TIMEOUT_S` (no answer: False); None when
    libX11 is not there to ask. The call has no timeout of its own: it runs in a daemon thread (ctypes
    releases the GIL), left behind blocked when the server never answers."""
    import ctypes
    import ctypes.util
    import threading

    name = ctypes.util.find_library("X11")
    if name is None:
        return None
    try:
        x11 = ctypes.CDLL(name)
    except OSError:
        return None
    x11.XOpenDisplay.restype = ctypes.c_void_p
    x11.XOpenDisplay.argtypes = [ctypes.c_char_p]
    x11.XCloseDisplay.argtypes = [ctypes.c_void_p]
    opened: list[bool] = []

    def probe() -> None:
        handle = x11.XOpenDisplay(display.encode())
        if handle:
            x11.XCloseDisplay(handle)
        opened.append(bool(handle))

    thread = threading.Thread(target=probe, name="x-display-probe", daemon=True)
    thread.start()
    thread.join(X_PROBE_TIMEOUT_S)
    return bool(opened and opened[0])


def show_map(path: str | os.PathLike[str], title: str = "gr_graph map") -> bool:
    """Open an open3d window on the PLY map at ``path`` (points coloured by height).

    Returns True if a window was shown; False (after printing why to stderr) when there is no
    map, no display, or the window could not be opened.
    """
    p = Path(path)
    if not p.is_file():
        print(f"--viz: no map at {p} (output.map.enabled is false?)", file=sys.stderr)
        return False
    ok, why = display_available()
    if not ok:
        print(f"--viz: {why}; not opening a window. The map is {p}: open it with open3d, CloudCompare or "
              "MeshLab on a machine with a display.", file=sys.stderr)
        return False
    try:
        import matplotlib
        import open3d as o3d

        cloud = o3d.io.read_point_cloud(str(p))
        z = np.asarray(cloud.points)[:, 2] if len(cloud.points) else np.zeros(0)
        if len(z):
            lo, hi = np.percentile(z, [2, 98])
            cloud.colors = o3d.utility.Vector3dVector(
                matplotlib.colormaps["viridis"](np.clip((z - lo) / max(hi - lo, 1e-6), 0, 1))[:, :3])
        o3d.visualization.draw_geometries([cloud], window_name=title)
    except Exception as exc:  # a display that refuses OpenGL must not fail a finished run
        print(f"--viz: could not open a window ({type(exc).__name__}: {exc}); the map is {p}", file=sys.stderr)
        return False
    return True
