"""Render a synthetic sequence's frames in a separate process, ahead of the reads.

The SLAM loop reads frames through a reader thread (:func:`gr_graph.frame_loop.prefetch_frames`)
so that making the next frame overlaps registering this one. For the synthetic worlds that overlap
is poor: open3d's ray casting, small_gicp's preprocessing and registration and gtsam's
optimisation all hold Python's GIL while they run, so the reader thread and the SLAM thread mostly
take turns (sampled with py-spy on round 0 of the full route: one of the two threads held the GIL
64 % of the time, each waiting for the other). A child process has its own interpreter.

:class:`RenderProcessSequence` wraps a :class:`~gr_graph.datasets.synthetic.SyntheticSequence`:
frame ``i`` is asked of a child process (started on the first read, ``spawn``) that renders it
with the same code and seeds, so the frames are the same, bit for bit. After two consecutive
requests the child renders the next ``ahead`` frames while the parent works; other access
patterns (random pairs) get no speculative frames. The town is built in the child only: the
parent never holds it. :meth:`RenderProcessSequence.release_cache` stops the child (its town freed
with it); a later read starts a new one.

Nothing is lost when the child cannot serve: a sequence that cannot be pickled, a child that
cannot start or that dies (e.g. killed for memory) makes the wrapper render in this process from
then on, with a warning naming the cause; :meth:`RenderProcessSequence.stats` counts the frames
each way. An error while rendering a frame (the same error the sequence would raise in this
process) is raised in the parent as the same type with the same message.
"""

from __future__ import annotations

import logging
import multiprocessing
import pickle
import signal
import threading
import traceback
import weakref
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from gr_graph.datasets.base import DatasetError, LidarFrame, check_index

log = logging.getLogger(__name__)

DEFAULT_AHEAD = 4
"""Frames the child renders ahead of the last of two consecutive requests."""

_POLL_S = 1.0  # how often a waiting parent checks that the child is alive
_STOP_TIMEOUT_S = 10.0
# errors raised in the parent as themselves (a frame the sequence refuses); others as RuntimeError
_PASSED_ERRORS: dict[str, type[BaseException]] = {"DatasetError": DatasetError, "IndexError": IndexError,
                                                   "ValueError": ValueError, "MemoryError": MemoryError}


def _serve(conn: Any, ahead: int, log_level: int) -> None:
    """The child's loop: receive the pickled sequence and answer ``("ready",)`` (or ``("failed",
    message)``), then answer each ``("get", i)`` with ``("frame", i, frame)`` or ``("error", i,
    type name, message, traceback)``; render ahead between requests; end on ``("stop",)`` or when
    the parent's end of the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    logging.basicConfig(level=log_level, format="%(asctime)s %(levelname)s %(name)s [render process]: %(message)s")
    try:
        sequence = pickle.loads(conn.recv_bytes())
        n = len(sequence)
    except Exception as exc:
        conn.send(("failed", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready",))
    ready: dict[int, LidarFrame] = {}
    plan: list[int] = []
    last: int | None = None
    while True:
        if plan and not conn.poll():
            j = plan.pop(0)
            try:
                ready[j] = sequence[j]
            except Exception:  # rendered again when asked for, and the error raised then
                plan.clear()
            continue
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message[0] != "get":
            return
        i = int(message[1])
        try:
            frame = ready.pop(i) if i in ready else sequence[i]
        except Exception as exc:
            conn.send(("error", i, type(exc).__name__, str(exc), traceback.format_exc()))
            plan.clear()
            continue
        conn.send(("frame", i, frame))
        sequential = last is not None and i == last + 1
        last = i
        for j in [j for j in ready if j <= i or j > i + ahead]:
            del ready[j]
        plan = [j for j in range(i + 1, min(i + 1 + ahead, n)) if j not in ready] if sequential else []


def _peak_rss_mb(pid: int) -> float | None:
    """Peak resident memory of process ``pid`` [MiB] from ``/proc`` (None where unavailable)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return None


def _stop(process: Any, conn: Any) -> None:
    """Ask the child to end, wait for it, and terminate it if it does not."""
    try:
        conn.send(("stop",))
    except (OSError, ValueError):
        pass
    process.join(_STOP_TIMEOUT_S)
    if process.is_alive():
        process.terminate()
        process.join(_STOP_TIMEOUT_S)
    conn.close()


class RenderProcessSequence:
    """A synthetic sequence whose frames are rendered by a child process (module docstring).

    Parameters
    ----------
    sequence : SyntheticSequence
        The sequence; every attribute other than frames is read from it.
    ahead : int
        Frames rendered ahead of consecutive reads.

    Attributes
    ----------
    frames_from_process, frames_in_this_process : int
        Frames served each way.
    fallback : str or None
        Why frames are rendered in this process (None while the child serves them).
    child_peak_rss_mb : float
        The largest peak resident memory of a child so far [MiB] (0 before one ran), read when
        it is stopped.
    """

    def __init__(self, sequence: Any, ahead: int = DEFAULT_AHEAD) -> None:
        self._sequence = sequence
        self.ahead = int(ahead)
        self._lock = threading.Lock()
        self._process: Any = None
        self._conn: Any = None
        self._finalizer: Any = None
        self.frames_from_process = 0
        self.frames_in_this_process = 0
        self.fallback: str | None = None
        self.child_peak_rss_mb = 0.0

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name == "_sequence":  # pickling, copying: not delegated
            raise AttributeError(name)
        return getattr(self._sequence, name)

    def __len__(self) -> int:
        return len(self._sequence)

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return f"RenderProcessSequence({self._sequence!r}, ahead={self.ahead})"

    def __getitem__(self, index: int) -> LidarFrame:
        i = check_index(index, len(self), self._sequence.name)
        with self._lock:
            if self.fallback is None and self._process is None:
                self._start()
            if self.fallback is None:
                frame = self._from_process(i)
                if frame is not None:
                    self.frames_from_process += 1
                    return frame
            self.frames_in_this_process += 1
        return self._sequence[i]

    def _fall_back(self, reason: str) -> None:
        self.fallback = reason
        log.warning("%s: %s; rendering in this process from now on", self._sequence.name, reason)
        if self._process is not None:
            self._shut_down()

    def _start(self) -> None:
        try:
            payload = pickle.dumps(self._sequence, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:  # e.g. actors given as an object holding ray-casting scenes
            self._fall_back(f"the sequence cannot be sent to a render process ({type(exc).__name__}: {exc})")
            return
        try:
            ctx = multiprocessing.get_context("spawn")  # no fork of a process that runs threads
            parent_end, child_end = ctx.Pipe()
            # the sequence goes through the pipe, not as an argument: start() writes its arguments to
            # a pipe the child may never read (if it dies on start-up), which blocks for large ones
            process = ctx.Process(target=_serve, name=f"{self._sequence.name}-render", daemon=True,
                                  args=(child_end, self.ahead, logging.getLogger().getEffectiveLevel()))
            process.start()
            child_end.close()
        except Exception as exc:
            self._fall_back(f"the render process could not start ({type(exc).__name__}: {exc})")
            return
        self._process, self._conn = process, parent_end
        self._finalizer = weakref.finalize(self, _stop, process, parent_end)
        try:
            parent_end.send_bytes(payload)
            reply = self._receive()
        except (EOFError, OSError) as exc:
            self._fall_back(f"the render process ended on start-up (exit code {process.exitcode}; {exc!r})")
            return
        if reply[0] != "ready":
            self._fall_back(f"the render process could not take the sequence ({reply[-1]})")
            return
        log.info("%s: frames rendered in a separate process (pid %d), %d ahead", self._sequence.name,
                 process.pid, self.ahead)

    def _from_process(self, i: int) -> LidarFrame | None:
        """Frame ``i`` from the child; None (after falling back) when the child is gone."""
        try:
            self._conn.send(("get", i))
            reply = self._receive()
        except (EOFError, OSError):
            code = self._process.exitcode
            self._fall_back(f"the render process ended (exit code {code}) while rendering frame {i}")
            return None
        if reply[0] == "frame" and reply[1] == i:
            return reply[2]
        if reply[0] == "error":
            _, _, kind, message, child_traceback = reply
            error = _PASSED_ERRORS.get(kind)
            if error is not None:
                raise error(message)
            raise RuntimeError(f"{self._sequence.name}: frame {i}: the render process raised {kind}: {message}\n"
                               f"{child_traceback}")
        self._fall_back(f"the render process answered frame {i} with {reply[:2]!r}")
        return None

    def _receive(self) -> tuple:
        """The child's next message; EOFError when it ends before sending one."""
        while not self._conn.poll(_POLL_S):
            if not self._process.is_alive():
                raise EOFError("the render process is gone")
        return self._conn.recv()

    def _shut_down(self) -> None:
        process = self._process
        peak = _peak_rss_mb(process.pid) if process.is_alive() else None
        self._finalizer()  # _stop: ask, wait, terminate
        self._process = self._conn = self._finalizer = None
        if peak is not None:
            self.child_peak_rss_mb = max(self.child_peak_rss_mb, peak)

    def release_cache(self) -> bool:
        """Stop the child (its town and scene freed with it) and drop this process's cached town,
        if any. A later read starts a new child. Returns whether anything was freed."""
        with self._lock:
            stopped = self._process is not None
            if stopped:
                self._shut_down()
        return bool(self._sequence.release_cache()) or stopped

    def stats(self) -> dict[str, Any]:
        """Frames served by the child and in this process, the fallback's reason, the child's peak memory."""
        return {"frames_from_process": self.frames_from_process,
                "frames_in_this_process": self.frames_in_this_process, "fallback": self.fallback,
                "child_peak_rss_mb": round(self.child_peak_rss_mb, 1)}
