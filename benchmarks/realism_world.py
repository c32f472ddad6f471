"""How much each world effect moves the realism statistics (not a test).

Renders, for each variant of the world (every effect off = ``clean``; every world effect on;
each effect on alone; each effect off alone), 50 frame pairs spread evenly along the
generated route (frames ``i`` and ``i + 1``, so that the held-out VGICP check has its
consecutive frames) into KITTI-layout folders, then runs the realism report
(``python -m gr_graph.datasets.realism``, from ``--realism-checkout``) on the real frames and
every variant, and writes ``benchmarks/results/realism_world.md``. Sensor effects are not
involved (today's sensor model: 2 cm Gaussian range noise, 2 % drop-outs).

Run::

    python benchmarks/realism_world.py --realism-checkout /work/main --real ../shared/data/kitti
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from gr_graph.datasets.synthetic import SyntheticSequence
from gr_graph.datasets.synthetic.actors import ActorsConfig
from gr_graph.datasets.synthetic.town import TownConfig
from gr_graph.datasets.synthetic.writer import write_kitti_layout

from bench_realism import FramePairs  # noqa: E402 (benchmarks/ is on sys.path when run as a script)

RESULTS = Path(__file__).resolve().parent / "results" / "realism_world.md"
TOWN_EFFECTS = ("porous_vegetation", "facade_details", "fences_hedges", "street_signs", "curved_cars",
                "sidewalk_parking", "detached_houses", "garden_vegetation", "terrain_roughness")
EFFECTS = TOWN_EFFECTS + ("actors",)
STATS = ("thickness_cm", "a90", "a99", "points_per_frame", "median_range_m", "frac_beyond_40m",
         "vgicp_inlier_rmse_cm")


def variant_configs() -> dict[str, tuple[TownConfig, ActorsConfig | None]]:
    """Name -> (town config, actors config) of every measured variant."""
    on = TownConfig.residential()
    off = TownConfig()
    out: dict[str, tuple[TownConfig, ActorsConfig | None]] = {"clean": (off, None), "all world": (on, ActorsConfig())}
    for e in TOWN_EFFECTS:
        out[f"+{e}"] = (dataclasses.replace(off, **{e: getattr(on, e)}), None)
        out[f"-{e}"] = (dataclasses.replace(on, **{e: getattr(off, e)}), ActorsConfig())
    out["+actors"] = (off, ActorsConfig())
    out["-actors"] = (on, None)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--real", type=Path, default=Path("../shared/data/kitti"))
    ap.add_argument("--realism-checkout", type=Path, required=True,
                    help="a checkout holding gr_graph/datasets/realism.py (e.g. /work/main)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/realism_world"))
    ap.add_argument("--pairs", type=int, default=50)
    ap.add_argument("--variants", default=None, help="comma-separated subset of the variant names")
    args = ap.parse_args(argv)
    variants = variant_configs()
    if args.variants:
        variants = {k: variants[k] for k in args.variants.split(",")}
    n = len(SyntheticSequence(seed=0))
    starts = np.unique(np.round(np.linspace(0, n - 2, args.pairs)).astype(int))
    folders, timings = {}, {}
    for name, (tc, ac) in variants.items():
        folder = args.work / name.replace("+", "on_").replace("-", "off_").replace(" ", "_")
        seq = SyntheticSequence(seed=0, town_config=tc, actors=ac, preset="clean")
        t0 = time.perf_counter()
        write_kitti_layout(FramePairs(seq, starts), folder, overwrite=True, progress=False)
        timings[name] = time.perf_counter() - t0
        folders[name] = folder
        print(f"{name}: {2 * len(starts)} frames in {timings[name]:.0f} s", flush=True)
    out_json = args.work / "realism.json"
    env = dict(os.environ, PYTHONPATH=str(args.realism_checkout.resolve()))
    cmd = [sys.executable, "-m", "gr_graph.datasets.realism", str(args.real.resolve()),
           *[str(f.resolve()) for f in folders.values()], "--max-frames", str(args.pairs),
           "--out", str(out_json.resolve()), "--no-progress"]
    subprocess.run(cmd, check=True, cwd=args.realism_checkout, env=env)
    results = json.loads(out_json.read_text())["results"]
    real, rows = results[0]["mean"], {name: r["mean"] for name, r in zip(folders, results[1:])}
    write_table(real, rows, starts, " ".join(sys.argv[1:]))
    return 0


def _fmt(v: float) -> str:
    return f"{v:,.0f}" if abs(v) >= 100 else f"{v:.3g}"


def write_table(real: dict, rows: dict, starts: np.ndarray, args: str) -> None:
    lines = [
        "# World effects: how much each moves the realism statistics",
        "",
        f"Reproduce: `python benchmarks/realism_world.py {args}`",
        "",
        f"- date (UTC): {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M}",
        f"- {len(starts)} frame pairs spread along the generated route (frames {starts[0]}..{starts[-1]} "
        "and their successors), seed 0, 64 rings, today's sensor model (no sensor effects); real: "
        "the frames of `../shared/data/kitti`. Statistics as defined in `gr_graph.datasets.realism`.",
        "- `+effect`: that world effect alone on the clean world; `-effect`: every world effect "
        "(`TownConfig.residential()` + `ActorsConfig()`) but that one. Differences in % are to `clean` "
        "(for `+`) or to `all world` (for `-`).",
        "",
        "| variant | " + " | ".join(STATS) + " |",
        "|---" * (len(STATS) + 1) + "|",
        "| real KITTI 00 | " + " | ".join(_fmt(real[k]) for k in STATS) + " |",
    ]
    for name, r in rows.items():
        ref = rows.get("clean") if name.startswith("+") else rows.get("all world") if name.startswith("-") else None
        cells = []
        for k in STATS:
            c = _fmt(r[k])
            if ref is not None and ref[k]:
                c += f" ({100 * (r[k] / ref[k] - 1):+.0f} %)"
            elif name in ("clean", "all world") and real[k]:
                c += f" ({100 * (r[k] / real[k] - 1):+.0f} % vs real)"
            cells.append(c)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    from gr_graph.atomic import atomic_write_bytes

    atomic_write_bytes(RESULTS, ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    raise SystemExit(main())
