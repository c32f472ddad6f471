"""Figure of position_nees_study's draws: each round's observed mean position NEES against the spread it
would have were every edge's information exact.

Usage::

    python benchmarks/position_nees_figure.py benchmarks/results/position_nees_study.json \\
        benchmarks/results/figures/position_nees_draws.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np


def draws_figure(runs: list[dict[str, Any]], out: Path) -> Path:
    """One row per round (``runs`` of the study's JSON, with ``position_draws``): the draws' 5-95 % range
    and median, the observed figure, the band; log scale. Written atomically to ``out`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    from gr_graph.atomic import atomic_write_bytes
    from gr_graph.noise_consistency import POSITION_BAND

    rows = [r for r in runs if r.get("position_draws")]
    if not rows:
        raise ValueError("no round with draws (run the study with --draws N)")
    fig, ax = plt.subplots(figsize=(7.5, 0.32 * len(rows) + 1.4))
    ax.axvspan(*POSITION_BAND, color="0.9", label=f"band {POSITION_BAND[0]:g}-{POSITION_BAND[1]:g}")
    ax.axvline(3.0, color="0.6", lw=0.8)
    for y, r in enumerate(rows):
        p = r["position_draws"]["position"]
        lo, mid, hi = np.percentile(p["draws"], [5, 50, 95])
        ax.plot([lo, hi], [y, y], color="tab:blue", lw=3, solid_capstyle="butt",
                label="exact model: 5-95 % of runs" if y == 0 else None)
        ax.plot(mid, y, "|", color="navy", ms=10, label="exact model: median" if y == 0 else None)
        if p.get("observed") is not None:
            ax.plot(p["observed"], y, "o", color="tab:red", ms=5, label="observed" if y == 0 else None)
    ax.set_yticks(range(len(rows)), [r["label"] for r in rows])
    ax.invert_yaxis()
    ax.set_xscale("log")
    ticks = [t for t in (0.1, 0.25, 0.5, 1, 1.5, 3, 6, 10, 20, 50) if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    ax.xaxis.set_major_locator(matplotlib.ticker.FixedLocator(ticks))
    ax.xaxis.set_major_formatter(matplotlib.ticker.FixedFormatter([f"{t:g}" for t in ticks]))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("mean position NEES of the run (ideal 3)")
    ax.legend(loc="upper left", fontsize=7, framealpha=0.9)
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(out, buf.getvalue())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("study_json", type=Path, help="position_nees_study's JSON (made with --draws)")
    ap.add_argument("out", type=Path, help="PNG to write")
    args = ap.parse_args(argv)
    try:
        runs = json.loads(args.study_json.read_text())["runs"]
        draws_figure(runs, args.out)
    except (OSError, KeyError, ValueError) as exc:
        ap.error(f"{args.study_json}: {exc}")
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
