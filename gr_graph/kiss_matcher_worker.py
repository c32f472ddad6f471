"""KISS-Matcher in a process of its own, bound to one CPU (``python -m gr_graph.kiss_matcher_worker``).

KISS-Matcher runs its loops on TBB threads and its answer depends on how they are scheduled: on 2
cores the same pair gave another transform and inlier count on every call. Bound to one CPU before
KISS-Matcher starts TBB, the process sizes its thread pool to that CPU and answers the same in every
call and process. :func:`gr_graph.global_solvers.register_kiss_matcher` starts one such process on
first use and talks to it over a pipe; it is started with ``-m``, so it never imports the caller's
main script (a script without an ``if __name__ == "__main__":`` guard is not run twice).

Protocol: every message is an 8-byte little-endian length and a pickle. A request is ``(source,
target, voxel)``; the reply is ``("ok", (valid, T, n_inliers), cpu_s)`` or ``("error", message,
cpu_s)``, ``cpu_s`` the CPU time the solve took in this process. The process ends when its input
closes. Anything the native library prints goes to standard error, never into the replies.
"""

from __future__ import annotations

import os
import pickle
import struct
import sys
import time
from typing import Any, BinaryIO

HEADER = struct.Struct("<Q")


def write_message(stream: BinaryIO, message: Any) -> None:
    """One length-prefixed pickle onto ``stream`` (flushed)."""
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(HEADER.pack(len(data)) + data)
    stream.flush()


def read_message(stream: BinaryIO) -> Any:
    """The next length-prefixed pickle from ``stream``; EOFError when the stream ends (also midway)."""
    header = stream.read(HEADER.size)
    if len(header) < HEADER.size:
        raise EOFError("the stream ended")
    (size,) = HEADER.unpack(header)
    data = stream.read(size)
    if len(data) < size:
        raise EOFError("the stream ended inside a message")
    return pickle.loads(data)


def main() -> int:
    """Serve solves until standard input closes."""
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # before KISS-Matcher starts TBB
    replies = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # the native library's prints go to standard error, not into the replies
    sys.stdout = sys.stderr
    from gr_graph.global_solvers import kiss_matcher_estimate

    requests = sys.stdin.buffer
    while True:
        try:
            source, target, voxel = read_message(requests)
        except EOFError:
            return 0
        c0 = time.process_time()
        try:
            reply: tuple[Any, ...] = ("ok", kiss_matcher_estimate(source, target, voxel))
        except Exception as exc:  # the caller counts the pair as failed, the process serves on
            reply = ("error", f"{type(exc).__name__}: {exc}")
        write_message(replies, (*reply, time.process_time() - c0))


if __name__ == "__main__":
    sys.exit(main())
