"""Drift as hard as reality? KISS-ICP 1.3.0 and gr_graph round 0 on the full ``kitti``-preset world.

Issue 9, item 3: on the full synthetic sequence rendered with the ``kitti`` preset, along the
project's generated route and along the real KITTI 00 route (its official ground truth from
``../shared/data/kitti00_gt``, when present), measure KISS-ICP 1.3.0 and gr_graph round 0
(odometry only and SLAM) at 64/32/16 channels: RPE-300, KITTI %, ATE. Writes
``benchmarks/results/drift.md`` (rebuilt from every stored ``drift_*.json``).

Steps (each stores its JSON, so they can run separately and be resumed)::

    # 1. render the route once to disk (KITTI layout; ~9 GB for 4,541 frames at 64 rings)
    python benchmarks/bench_drift.py export   --route generated --root /tmp/drift/generated
    python benchmarks/bench_drift.py export   --route kitti00   --root /tmp/drift/kitti00
    # 2. one reading pass feeding KISS-ICP and gr_graph's front end at 64/32/16 channels
    python benchmarks/bench_drift.py odometry --route generated --root /tmp/drift/generated
    # 3. the SLAM command itself (loop closures + pose graph), one run per channel count
    python benchmarks/bench_drift.py slam     --route generated --root /tmp/drift/generated --channels 64
    python benchmarks/bench_drift.py report
    # or without an export: the route rendered on the fly (slower per pass, no 9 GB on disk)
    python benchmarks/bench_drift.py odometry --route kitti00 --render --systems kiss_icp@32,kiss_icp@16 --tag ch32_16
    python benchmarks/bench_drift.py slam     --route kitti00 --render --channels 32

Channel counts 32 and 16 keep every 2nd / 4th ring of the 64-ring scans (ring recovery of
the KITTI loader, as for real KITTI). KISS-ICP runs with its default configuration, deskew
off (the ``kitti`` preset, like KITTI's odometry scans, is motion-compensated up to a residual),
one thread; gr_graph's front end is the pipeline's (preprocess + VGICP), also with the KITTI
vertical-angle correction (0.205 deg, KISS-ICP's value) at 64 channels to measure its effect.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_slam import CHANNELS, GrFrontEnd, KissFrontEnd, machine, run_front_ends  # noqa: E402

from gr_graph.atomic import atomic_write_json, atomic_write_text  # noqa: E402

ROUTES = {
    "generated": "the project's generated route (route seed 0), 4,541 frames",
    "kitti00": "the real KITTI 00 route (official ground truth of ../shared/data/kitti00_gt), 4,541 frames",
}
KITTI00_GT = REPO.parent / "shared" / "data" / "kitti00_gt" / "00.txt"
VERTICAL_DEG = 0.205


def export(route: str, root: Path, preset: str, frames: str | None) -> None:
    """Render the route with ``preset`` to ``root`` in KITTI layout (the project's exporter)."""
    cmd = [sys.executable, "-m", "gr_graph.datasets.synthetic", "--out", str(root), "--preset", preset,
           "--overwrite"]
    if route == "kitti00":
        if not KITTI00_GT.exists():
            raise SystemExit(f"{KITTI00_GT} not found: the real KITTI 00 route needs ../shared/data/kitti00_gt")
        cmd += ["--trajectory", str(KITTI00_GT)]
    if frames:
        cmd += ["--frames", frames]
    print(" ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=REPO)


def open_root(root: Path | None, route: str = "generated"):
    """The exported folder ``root``, or (``root`` None) the kitti-preset route rendered on the fly."""
    from gr_graph.datasets.registry import open_sequence

    if root is None:
        trajectory = str(KITTI00_GT) if route == "kitti00" else None  # rendered, never a KITTI root found
        return open_sequence("00", trajectory=trajectory, synthetic_preset="kitti", dataset="synthetic")
    return open_sequence("00", str(root))


class KissVerticalFrontEnd(KissFrontEnd):
    """KISS-ICP fed scans with the KITTI vertical-angle correction, as its KITTI dataloader does."""

    def __call__(self, points):
        from gr_graph.datasets.kitti import correct_vertical_angle

        return super().__call__(correct_vertical_angle(points, VERTICAL_DEG))


def odometry(route: str, root: Path | None, systems: tuple[str, ...]) -> dict:
    """KISS-ICP and/or gr_graph odometry at 64/32/16 channels, one reading pass.

    ``systems``: ``kiss_icp``, ``gr_graph`` (its front end; the SLAM runs report the same
    odometry), ``vertical`` / ``kiss_vertical`` (gr_graph's / KISS-ICP's front end with the
    vertical-angle correction, 64 channels).
    """
    seq, desc = open_root(root, route)
    makers = {"gr_graph": GrFrontEnd, "kiss_icp": KissFrontEnd}
    fes = {}
    for entry in systems:  # "kiss_icp" (every channel count) or "kiss_icp@64" (one)
        name, _, only = entry.partition("@")
        for ch in (CHANNELS if not only else (int(only),)):
            if name in makers:
                fes[(name, ch)] = makers[name]()
    names = tuple(e.partition("@")[0] for e in systems)
    if "vertical" in names:
        fes[(f"gr_graph + vertical {VERTICAL_DEG} deg", 64)] = GrFrontEnd(vertical_correction_deg=VERTICAL_DEG)
    if "kiss_vertical" in names:  # as KISS-ICP's own KITTI loader reads KITTI scans
        fes[(f"kiss_icp + vertical {VERTICAL_DEG} deg", 64)] = KissVerticalFrontEnd()
    t0 = time.perf_counter()
    res = run_front_ends(seq, fes, desc=f"drift {route}")
    return {"route": route, "source": desc, "n_frames": len(seq), "systems": ",".join(systems), "render": root is None,
            "wall_s": time.perf_counter() - t0, **res}


def slam(route: str, root: Path | None, channels: int, out: Path) -> dict:
    """``python -m gr_graph.slam`` on the exported folder (``root`` None: rendered on the fly); round 0."""
    if root is None:  # no export: the command renders the kitti preset along the route itself
        where = ["--dataset", "synthetic"] + (["--trajectory", str(KITTI00_GT)] if route == "kitti00" else [])
    else:
        where = ["--data-root", str(root)]
    cmd = [sys.executable, "-m", "gr_graph.slam", "--seq", "00", *where,  # a fresh run: its wall time is measured
           "--channels", str(channels), "--out", str(out), "--no-progress", "--no-resume"]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO)
    m = json.loads((out / "metrics.json").read_text())
    r0 = m["rounds"]["0"]
    return {"route": route, "channels": channels, "wall_s": time.perf_counter() - t0,
            "command": " ".join(["python", "-m", "gr_graph.slam"] + cmd[3:]), "source": m["source"],
            "odometry": r0.get("odometry", {}), "slam": r0.get("slam", {}),
            "n_loops": r0.get("loop_closure", {}).get("n_loops"),
            "n_correct_loops": r0.get("loop_closure", {}).get("n_correct")}


SYSTEMS = ("kiss_icp", "gr_graph", "vertical", "kiss_vertical")


def check_systems(text: str) -> tuple[str, ...]:
    """``--systems`` as a tuple; an unknown name or channel count is an error (it would be skipped after a
    full reading pass, leaving a results file without its rows)."""
    systems = tuple(s.strip() for s in text.split(",") if s.strip())
    for entry in systems:
        name, at, only = entry.partition("@")
        allowed = (64,) if name in ("vertical", "kiss_vertical") else CHANNELS  # the corrections: 64 channels only
        if name not in SYSTEMS or (at and (not only.isdigit() or int(only) not in allowed)):
            raise SystemExit(f"--systems: unknown entry {entry!r}; use {', '.join(SYSTEMS)}, optionally NAME@C with "
                             f"C one of {', '.join(map(str, CHANNELS))} (vertical, kiss_vertical: 64 only)")
    if not systems:
        raise SystemExit("--systems: no system given")
    return systems


def refuse_overwrite(path: Path, force: bool) -> Path:
    """``path``, or an error when it exists and ``force`` is not set: a published pass (another ``--tag``'s
    systems, another route) is not replaced by a mistyped command."""
    if path.exists() and not force:
        raise SystemExit(f"{path} exists (a published pass): add --force to replace it, or --tag NAME for another file")
    return path


def _f(x, fmt: str = "{:.2f}") -> str:
    return "n/a" if x is None else fmt.format(x)


def write_markdown() -> Path:
    lines = ["# Drift on the `kitti`-preset world: KISS-ICP 1.3.0 and gr_graph round 0", "",
             f"Machine: {machine()}. Issue 9, item 3. Target: KISS-ICP's KITTI % at 64 channels between "
             "0.3 and 1.5 % (its published real KITTI 00 figure is about 0.5 %). Steps and settings: "
             "`benchmarks/bench_drift.py` (docstring).", ""]
    header = ("| system | channels | RPE300 mean (consec.) [m] | RMSE (consec.) | mean (all pairs) | "
              "RMSE (all pairs) | ATE RMSE [m] | KITTI % |")
    for route, what in ROUTES.items():
        rows = []
        paths = sorted(RESULTS.glob(f"drift_{route}_odometry*.json"))
        passes = [json.loads(p.read_text()) for p in paths]
        tags = [p.stem[len(f"drift_{route}_odometry_"):] if p.stem != f"drift_{route}_odometry" else "" for p in paths]
        for odo, tag in zip(passes, tags):
            for r in sorted(odo["rows"], key=lambda r: (-r["channels"], r["system"])):
                rows.append((r["system"] + (f" (odometry, pass {tag})" if tag else " (odometry)"), r["channels"], r))
        for ch in CHANNELS:
            p = RESULTS / f"drift_{route}_slam_{ch}.json"
            if p.exists():
                d = json.loads(p.read_text())
                o, s = d["odometry"], d["slam"]
                rows.append((f"gr_graph SLAM odometry part ({d['wall_s'] / 60:.0f} min run)", ch, o))
                rows.append((f"gr_graph SLAM ({d['n_loops']} loops, {d['n_correct_loops']} correct)", ch, s))
        if not rows:
            continue
        lines += [f"## {what}", ""]
        for tag, odo in zip(tags, passes):
            where = "--render" if odo.get("render") else "--root DIR"
            lines += [f"Odometry pass: `python benchmarks/bench_drift.py odometry --route {route} {where} "
                      f"--systems {odo.get('systems', 'kiss_icp,gr_graph,vertical')}{f' --tag {tag}' if tag else ''}` "
                      f"— {odo['source']}; {odo['n_frames']} frames, {odo['wall_s'] / 60:.0f} min.", ""]
        lines += [header, "|---|---|---|---|---|---|---|---|"]
        for name, ch, m in sorted(rows, key=lambda t: -t[1]):
            lines.append(f"| {name} | {ch} | {_f(m.get('rpe300_consecutive_mean'))} | "
                         f"{_f(m.get('rpe300_consecutive_rmse'))} | {_f(m.get('rpe300_all_pairs_mean'))} | "
                         f"{_f(m.get('rpe300_all_pairs_rmse'))} | {_f(m.get('ate_rmse'))} | "
                         f"{_f(m.get('kitti_t_err_percent'))} |")
        lines.append("")
    out = RESULTS / "drift.md"
    atomic_write_text(out, "\n".join(lines) + "\n")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("step", choices=("export", "odometry", "slam", "report"))
    ap.add_argument("--route", choices=tuple(ROUTES), default="generated")
    ap.add_argument("--root", type=Path, default=None, help="the exported KITTI-layout folder")
    ap.add_argument("--preset", default="kitti", help="export: synthetic preset (default: kitti)")
    ap.add_argument("--frames", default=None, help="export: frame range A:B (default: all)")
    ap.add_argument("--channels", type=int, choices=CHANNELS, default=64)
    ap.add_argument("--systems", default="kiss_icp,gr_graph,vertical",
                    help="odometry: comma-separated front ends (kiss_icp, gr_graph, vertical, kiss_vertical; "
                         "NAME@64 runs one channel count only)")
    ap.add_argument("--render", action="store_true",
                    help="odometry, slam: render the route on the fly instead of reading --root (no export)")
    ap.add_argument("--tag", default=None, help="odometry: suffix of the results file (a second pass)")
    ap.add_argument("--out", type=Path, default=None, help="slam: run directory (default: ROOT.slam_C)")
    ap.add_argument("--force", action="store_true",
                    help="odometry, slam: replace a published results file (without it, an existing one is an error)")
    a = ap.parse_args()
    root = a.root or Path(f"/tmp/drift/{a.route}")
    if a.step == "export":
        export(a.route, root, a.preset, a.frames)
    elif a.step == "odometry":
        systems = check_systems(a.systems)
        tag = "" if a.tag is None else f"_{a.tag}"
        target = refuse_overwrite(RESULTS / f"drift_{a.route}_odometry{tag}.json", a.force)
        atomic_write_json(target, odometry(a.route, None if a.render else root, systems))
    elif a.step == "slam":
        out = a.out or Path(f"{root}.slam_{a.channels}")
        target = refuse_overwrite(RESULTS / f"drift_{a.route}_slam_{a.channels}.json", a.force)
        atomic_write_json(target, slam(a.route, None if a.render else root, a.channels, out))
    print(write_markdown())


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "Agg")
    main()
