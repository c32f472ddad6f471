"""Cost of one loop check against the length of the run (a benchmark, not a test).

Every ``loops.check_every`` frames the frame loop asks for loop candidates of the newest scan:
the Scan Context ring keys of all older scans (:meth:`gr_graph.loop_closure.ScanContextDatabase.query`)
and the current trajectory estimate (:meth:`gr_graph.frame_loop.LoopCorrectedEstimate.poses`, for the
proximity search). Both used to turn a Python list of every scan's key and pose into an array at
each check, so a check cost grew with the run and the whole run quadratically (about 120 ms a check
at 50,000 frames, measured in a review). They now keep the rows in an array that grows
(:class:`gr_graph.loop_closure.RowBuffer`).

This measures, at several run lengths, the time of the two parts of one check as done now and as
done before (the list conversion, rebuilt here as the reference), interleaved, and their ratio.
The descriptor comparisons of the few candidates (the same in both) are left out.

    python benchmarks/bench_loop_query.py [--frames 5000 20000 50000] [--repeats 20] [--write]

``--write`` stores ``benchmarks/results/loop_query.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gr_graph.frame_loop import LoopCorrectedEstimate  # noqa: E402
from gr_graph.loop_closure import RowBuffer  # noqa: E402
from gr_graph.provenance import machine_line  # noqa: E402
from results_io import print_and_write  # noqa: E402

RING_KEY_LENGTH = 20  # loops.sc_rings


def timed(fn, repeats: int) -> float:
    """Median wall time [ms] of ``fn()`` over ``repeats`` calls."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(out))


def measure(n_frames: int, repeats: int, rng: np.random.Generator) -> dict[str, float]:
    keys_list = [rng.random(RING_KEY_LENGTH) for _ in range(n_frames)]
    keys = RowBuffer((RING_KEY_LENGTH,))
    keys.extend(keys_list)
    poses_list = [np.eye(4) for _ in range(n_frames)]
    for k, T in enumerate(poses_list):
        T[:3, 3] = [k * 0.8, 0.01 * k, 0.0]
    estimate = LoopCorrectedEstimate(poses_list)
    estimate.optimised = np.asarray(poses_list[: n_frames - 40])  # optimised 40 frames ago
    last, i = n_frames - 101, n_frames - 1

    def keys_before() -> np.ndarray:
        return np.linalg.norm(np.asarray(keys_list[: last + 1]) - keys_list[i][None, :], axis=1)

    def keys_now() -> np.ndarray:
        return np.linalg.norm(keys.rows(last + 1) - keys.rows()[i][None, :], axis=1)

    def poses_before() -> np.ndarray:
        odom = np.asarray(poses_list[:n_frames])
        n = len(estimate.optimised)
        corr = estimate.optimised[n - 1] @ np.linalg.inv(odom[n - 1])
        return np.concatenate([estimate.optimised, corr[None] @ odom[n:]])

    def poses_now() -> np.ndarray:
        return estimate.poses(n_frames)

    assert np.array_equal(keys_before(), keys_now()) and np.array_equal(poses_before(), poses_now())
    fig = {"frames": n_frames}
    for name, before, now in (("keys", keys_before, keys_now), ("poses", poses_before, poses_now)):
        b, a = [], []
        for _ in range(3):  # interleaved: a slower moment of the machine hits both
            b.append(timed(before, repeats))
            a.append(timed(now, repeats))
        fig[f"{name}_before_ms"], fig[f"{name}_now_ms"] = float(np.median(b)), float(np.median(a))
    fig["check_ratio"] = (fig["keys_now_ms"] + fig["poses_now_ms"]) / (fig["keys_before_ms"] + fig["poses_before_ms"])
    return fig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", nargs="+", type=int, default=[5000, 20000, 50000])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    rows = [measure(n, args.repeats, rng) for n in args.frames]
    lines = ["# Cost of one loop check against the run's length", "",
             f"`python benchmarks/bench_loop_query.py --frames {' '.join(map(str, args.frames))} --repeats "
             f"{args.repeats}`; {machine_line()}. Median ms of {args.repeats} calls, median of 3 interleaved "
             "measurements; the same arrays before and after (checked).", "",
             "| frames | ring keys before / now [ms] | trajectory estimate before / now [ms] | check now / before |",
             "|---|---|---|---|"]
    for f in rows:
        lines.append(f"| {f['frames']} | {f['keys_before_ms']:.2f} / {f['keys_now_ms']:.2f} | "
                     f"{f['poses_before_ms']:.2f} / {f['poses_now_ms']:.2f} | {f['check_ratio']:.2f} |")
    print_and_write("loop_query", "\n".join(lines), {"frames": args.frames, "repeats": args.repeats, "rows": rows},
                    args.write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
