"""Global registration evaluation: random scan pairs near each other, solved without a guess.

The paper's protocol: sample ``N = 100`` scan pairs whose ground-truth translation distance
is at most 10 m, register each pair from scratch (no initial guess), and count a pair as a
success when the rotation error is below 10 deg and the translation error below 2 m.

Solvers: :mod:`gr_graph.global_solvers` (KISS-Matcher, FPFH + RANSAC).

Conventions: scans are ``(N, 3)`` points in their own sensor frame; ``poses`` are
``T_w_sensor`` for the same frames (for KITTI: ``LidarSequence.gt_poses`` = ``T_w_velo``,
not the camera-frame file). A pair ``(source, target)`` has the reference transform
``T_target_source = inv(T_w_target) @ T_w_source`` (maps source points into the target
frame), and the sampled pairs use the later frame as the source.

Command line::

    python -m gr_graph.global_registration --seq 00 --channels 32 --n-pairs 100 --seed 0 \\
        --out results/global_registration
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from factors.se3 import check_poses, rotation_angle
from gr_graph.atomic import atomic_write_text
from gr_graph.cli_common import (
    add_channels,
    add_data_root,
    add_log_level,
    add_no_progress,
    add_out,
    add_point_format,
    add_seed,
    at_least,
    make_parser,
    positive_float,
    setup_logging,
)
from gr_graph.global_solvers import (
    DEFAULT_VOXEL,
    SOLVER_NAMES,
    RegistrationOutcome,
    available_solvers,
    kiss_matcher_available,
    register,
)

logger = logging.getLogger(__name__)

MAX_ROT_DEG = 10.0
MAX_TRANS_M = 2.0


# ----------------------------------------------------------------------------- pairs


def sample_pairs(
    poses: np.ndarray,
    n: int = 100,
    max_distance: float = 10.0,
    seed: int = 0,
    min_index_gap: int = 1,
    min_frame: int = 0,
) -> np.ndarray:
    """Sample scan pairs whose ground-truth positions are within ``max_distance``.

    Parameters
    ----------
    poses : (K, 4, 4) array
        Ground-truth poses (only the translations are used).
    n : int
        Number of pairs, drawn uniformly without replacement among all qualifying pairs.
    max_distance : float
        Largest ground-truth translation distance (metres), inclusive.
    seed : int
        Seed of :func:`numpy.random.default_rng`.
    min_index_gap : int
        Smallest ``|i - j|`` (1 allows consecutive frames).
    min_frame : int
        Frames below this index are never used (e.g. 14 for KITTI 00, whose ground truth
        of frames 0-13 is an extrapolation).

    Returns
    -------
    np.ndarray
        ``(n, 2)`` int64 rows ``(source, target)`` with ``source > target``, sorted.

    Raises
    ------
    ValueError
        Fewer than ``n`` qualifying pairs exist, or ``n`` or ``min_frame`` is negative.
    """
    P = check_poses(poses, "sample_pairs poses")[:, :3, 3]
    if int(n) != n or n < 0 or int(min_frame) != min_frame or min_frame < 0:
        raise ValueError(f"n and min_frame must be integers >= 0, got n={n}, min_frame={min_frame}")
    idx = np.arange(min_frame, len(P))
    cand = cKDTree(P[idx]).query_pairs(r=float(max_distance), output_type="ndarray")
    if len(cand):
        a, b = idx[cand[:, 0]], idx[cand[:, 1]]
        cand = np.stack([np.maximum(a, b), np.minimum(a, b)], axis=1)
        cand = cand[(cand[:, 0] - cand[:, 1]) >= min_index_gap]
        # cKDTree's pair order is an implementation detail: sort before drawing.
        cand = cand[np.lexsort((cand[:, 0], cand[:, 1]))]
    if len(cand) < n:
        raise ValueError(
            f"only {len(cand)} scan pairs are within {max_distance} m "
            f"(min index gap {min_index_gap}, frames >= {min_frame}); {n} requested"
        )
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(len(cand), size=n, replace=False))
    return cand[pick].astype(np.int64)


def relative_transform(poses: np.ndarray, source: int, target: int) -> np.ndarray:
    """Reference ``T_target_source = inv(T_w_target) @ T_w_source``."""
    return np.linalg.inv(poses[target]) @ poses[source]


def save_pairs(path: str | os.PathLike[str], pairs: np.ndarray, meta: dict[str, Any]) -> Path:
    """Write the pair list and its sampling parameters (seed, distance, ...) as JSON, atomically."""
    doc = {**meta, "pairs": np.asarray(pairs, dtype=np.int64).tolist()}
    return atomic_write_text(path, json.dumps(doc, indent=1) + "\n")


def load_pairs(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict[str, Any]]:
    """Read a file written by :func:`save_pairs`: ``(pairs (n, 2), meta)``.

    Raises ``ValueError`` naming the file when it is not JSON, has no ``pairs`` or holds a row
    that is not two different non-negative frame numbers.
    """
    try:
        doc = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a pair file ({exc})") from None
    if not isinstance(doc, dict) or "pairs" not in doc:
        raise ValueError(f"{path}: no 'pairs' entry")
    try:
        raw = np.asarray(doc.pop("pairs"), dtype=np.float64).reshape(-1, 2)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: 'pairs' must be rows of two frame numbers ({exc})") from None
    fractional = np.flatnonzero(((raw != np.round(raw)) | ~np.isfinite(raw)).any(axis=1))
    if len(fractional):  # a frame number 3.7 is no frame (int64 would floor it to 3)
        raise ValueError(f"{path}: pair row {int(fractional[0])} {raw[fractional[0]].tolist()} is not two whole frame "
                         f"numbers ({len(fractional)} such rows)")
    pairs = raw.astype(np.int64)
    bad = np.flatnonzero((pairs[:, 0] == pairs[:, 1]) | (pairs < 0).any(axis=1))
    if len(bad):
        raise ValueError(f"{path}: pair row {int(bad[0])} {pairs[bad[0]].tolist()} is not two different frames "
                         f"({len(bad)} such rows)")
    return pairs, doc


# ----------------------------------------------------------------------------- errors


def rotation_error_deg(T_est: np.ndarray, T_ref: np.ndarray) -> float:
    """Angle (deg) of ``R_est^T R_ref``."""
    return float(np.degrees(rotation_angle(T_est[:3, :3].T @ T_ref[:3, :3])))


def translation_error_m(T_est: np.ndarray, T_ref: np.ndarray) -> float:
    """``|t_est - t_ref|`` (metres)."""
    return float(np.linalg.norm(T_est[:3, 3] - T_ref[:3, 3]))


def is_success(
    T_est: np.ndarray, T_ref: np.ndarray, max_rot_deg: float = MAX_ROT_DEG, max_trans_m: float = MAX_TRANS_M
) -> bool:
    """Success criterion: rotation error < ``max_rot_deg`` and translation error < ``max_trans_m``."""
    return rotation_error_deg(T_est, T_ref) < max_rot_deg and translation_error_m(T_est, T_ref) < max_trans_m


# ----------------------------------------------------------------------------- evaluation


ScanSource = Callable[[int], np.ndarray] | Sequence[Any]


def _scan(scans: ScanSource, k: int) -> np.ndarray:
    if callable(scans):
        return np.asarray(scans(k), dtype=np.float64)
    item = scans[k]
    return np.asarray(getattr(item, "points", item), dtype=np.float64)


def evaluate_pairs(
    scans: ScanSource,
    poses: np.ndarray,
    pairs: np.ndarray,
    solvers: Sequence[str] | None = None,
    voxel: float = DEFAULT_VOXEL,
    seed: int = 0,
    max_rot_deg: float = MAX_ROT_DEG,
    max_trans_m: float = MAX_TRANS_M,
    progress: bool = True,
) -> dict[str, Any]:
    """Register every pair with every solver and score it against the ground truth.

    Parameters
    ----------
    scans : callable ``k -> (N, 3)`` or sequence of frames / arrays
        Scan ``k`` in its own sensor frame (a :class:`LidarSequence` works directly).
    poses : (K, 4, 4) array
        Ground-truth ``T_w_sensor`` of the same frames.
    pairs : (n, 2) int array
        Rows ``(source, target)``.
    solvers : sequence of str, optional
        Default: :func:`available_solvers`. ``kiss_matcher`` is skipped (logged) if missing.
    voxel, seed : solver settings.
    max_rot_deg, max_trans_m : success thresholds.
    progress : bool
        Show a tqdm bar.

    Returns
    -------
    dict
        JSON-serialisable: ``settings``, ``summary`` (per solver: success_rate, n_success,
        n_pairs, n_invalid (no solution: a failure), n_errors (the solver raised on the pair, e.g. a
        scan with too few points: a failure, its row names the error), success_rate_nontrivial over the
        n_nontrivial pairs the identity does not solve, median errors and time), ``identity``
        (the identity's success: the share of pairs solved by doing nothing, e.g. scans of a
        stopped vehicle) and ``pairs`` (one row per pair and solver).
    """
    from tqdm import tqdm

    P = check_poses(poses, "evaluate_pairs poses")
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(pairs) and (pairs.min() < 0 or pairs.max() >= len(P)):
        raise ValueError(f"pair indices must be in [0, {len(P)}), got {pairs.min()}..{pairs.max()}")
    wanted = list(solvers) if solvers is not None else list(available_solvers())
    for s in wanted:
        if s not in SOLVER_NAMES:
            raise ValueError(f"unknown solver {s!r}; choose from {SOLVER_NAMES}")
    if "kiss_matcher" in wanted and not kiss_matcher_available():
        logger.warning("kiss_matcher is not installed (pip install kiss-matcher): skipping that solver")
        wanted.remove("kiss_matcher")
    rows: list[dict[str, Any]] = []
    trivial: list[bool] = []  # the identity succeeds: the pair is solved by doing nothing
    for src_i, tgt_i in tqdm(pairs.tolist(), desc="global registration", disable=not progress):
        src, tgt = _scan(scans, src_i), _scan(scans, tgt_i)
        T_ref = relative_transform(P, src_i, tgt_i)
        trivial.append(is_success(np.eye(4), T_ref, max_rot_deg, max_trans_m))
        for s in wanted:
            try:
                out = register(s, src, tgt, voxel=voxel, seed=seed)
                error = None
            except (ValueError, RuntimeError) as exc:  # e.g. a scan left with too few points: this pair fails
                error = f"{type(exc).__name__}: {exc}"
                logger.warning("global registration, pair (%d, %d), %s: %s; counted as a failure", src_i, tgt_i, s, error)
                out = RegistrationOutcome(s, np.eye(4), 0, 0.0, valid=False)
            re, te = rotation_error_deg(out.T, T_ref), translation_error_m(out.T, T_ref)
            rows.append(
                {
                    "solver": s,
                    "source": src_i,
                    "target": tgt_i,
                    "gt_distance_m": float(np.linalg.norm(T_ref[:3, 3])),
                    "rot_err_deg": re,
                    "trans_err_m": te,
                    # no solution is a failure, even where the identity it returns is close enough
                    "success": bool(out.valid and re < max_rot_deg and te < max_trans_m),
                    "valid": bool(out.valid),
                    "identity_success": trivial[-1],
                    "n_inliers": out.n_inliers,
                    "seconds": out.seconds,
                    "T_est": out.T.tolist(),
                    **({} if error is None else {"error": error}),
                }
            )
    summary: dict[str, Any] = {}
    for s in wanted:
        r = [x for x in rows if x["solver"] == s]
        ok = [x["success"] for x in r]
        hard = [x["success"] for x in r if not x["identity_success"]]
        summary[s] = {
            "n_pairs": len(r),
            "n_success": int(sum(ok)),
            "success_rate": float(np.mean(ok)) if r else None,
            "n_invalid": int(sum(not x["valid"] for x in r)),
            "n_errors": int(sum("error" in x for x in r)),
            "n_nontrivial": len(hard),
            "success_rate_nontrivial": float(np.mean(hard)) if hard else None,
            "median_rot_err_deg": float(np.median([x["rot_err_deg"] for x in r])) if r else None,
            "median_trans_err_m": float(np.median([x["trans_err_m"] for x in r])) if r else None,
            "median_seconds": float(np.median([x["seconds"] for x in r])) if r else None,
        }
    settings = {
        "voxel": voxel,
        "seed": seed,
        "max_rot_deg": max_rot_deg,
        "max_trans_m": max_trans_m,
        "solvers": wanted,
    }
    identity = {"n_success": int(sum(trivial)), "success_rate": float(np.mean(trivial)) if trivial else None}
    return {"settings": settings, "summary": summary, "identity": identity, "pairs": rows}


def write_results(path: str | os.PathLike[str], results: dict[str, Any]) -> Path:
    """Write :func:`evaluate_pairs` output as JSON, atomically."""
    return atomic_write_text(path, json.dumps(results, indent=1) + "\n")


# ----------------------------------------------------------------------------- CLI


EXAMPLES = (
    "python -m gr_graph.global_registration --seq 00 --n-pairs 100 --seed 0 --out runs/greg_64",
    "python -m gr_graph.global_registration --seq 00 --channels 16 --solvers fpfh_ransac --out runs/greg_16",
    "python -m gr_graph.global_registration --seq 00 --data-root /data/kitti --pairs runs/greg_64/pairs.json "
    "--out runs/greg_kitti",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m gr_graph.global_registration``."""
    ap = make_parser("python -m gr_graph.global_registration",
                     __doc__.split("\n\n")[0] + " Writes DIR/pairs.json and DIR/results.json.", EXAMPLES)
    add_out(ap, "output directory", required=True)
    ap.add_argument("--seq", default="00", help="KITTI sequence")
    add_data_root(ap)
    add_point_format(ap)
    add_channels(ap)
    ap.add_argument("--n-pairs", type=at_least(1), default=100, metavar="N", help="scan pairs sampled")
    ap.add_argument("--max-distance", type=positive_float, default=10.0, metavar="M",
                    help="largest ground-truth distance between the scans of a pair [m]")
    add_seed(ap, "seed of the pair sampling and of RANSAC")
    ap.add_argument("--voxel", type=positive_float, default=DEFAULT_VOXEL, metavar="M",
                    help="voxel size of the FPFH scans [m]")
    ap.add_argument("--min-frame", type=at_least(0), default=None, metavar="K",
                    help="first frame sampled "
                         "(default: 14 for seq 00, whose GT of frames 0-13 is extrapolated; else 0)")
    ap.add_argument("--pairs", default=None, metavar="FILE", help="reuse a pairs.json instead of sampling")
    ap.add_argument("--solvers", nargs="+", default=None, choices=SOLVER_NAMES,
                    help="solvers to run (default: all available)")
    add_no_progress(ap)
    add_log_level(ap)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: sample pairs on a sequence, register them, write pairs.json and results.json."""
    from gr_graph.datasets.base import DatasetError
    from gr_graph.datasets.registry import open_sequence

    args = build_parser().parse_args(argv)
    setup_logging(args.log_level)
    try:
        seq, desc = open_sequence(args.seq, args.data_root, args.channels, point_format=args.point_format)
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    logger.info("%s", desc)
    if seq.gt_poses is None:
        print(f"error: {desc}: no ground-truth poses, cannot evaluate global registration", file=sys.stderr)
        return 2
    poses = np.asarray(seq.gt_poses)
    out = Path(args.out)
    if args.pairs:
        try:
            pairs, meta = load_pairs(args.pairs)
            if len(pairs) and pairs.max() >= len(poses):
                raise ValueError(f"{args.pairs}: frame {int(pairs.max())} is past the sequence's {len(poses)} frames "
                                 f"({desc}; the file's: {meta.get('sequence', 'not recorded')})")
        except (OSError, ValueError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    else:
        min_frame = args.min_frame if args.min_frame is not None else (14 if args.seq in ("00", "0") else 0)
        try:
            pairs = sample_pairs(poses, args.n_pairs, args.max_distance, args.seed, min_frame=min_frame)
        except ValueError as exc:
            print(f"error: {desc}: {exc}: lower --n-pairs or --min-frame, or raise --max-distance", file=sys.stderr)
            return 2
        meta = {
            "sequence": desc,
            "n_pairs": args.n_pairs,
            "max_distance_m": args.max_distance,
            "seed": args.seed,
            "min_frame": min_frame,
            "convention": "rows are (source, target); T_target_source = inv(T_w_target) @ T_w_source",
        }
    (out / "results.json").unlink(missing_ok=True)  # an earlier run's, made on other pairs
    save_pairs(out / "pairs.json", pairs, meta)
    try:
        res = evaluate_pairs(seq, poses, pairs, args.solvers, voxel=args.voxel, seed=args.seed,
                             progress=not args.no_progress)
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    res["settings"].update(sequence=desc, channels=args.channels, pairs_file=str(out / "pairs.json"))
    write_results(out / "results.json", res)
    logger.info("identity (no registration): success %d/%d", res["identity"]["n_success"], len(pairs))
    for s, v in res["summary"].items():
        logger.info("%s: success %d/%d (%.1f%%), %d without a solution; %.1f%% of the %d pairs the identity "
                    "does not solve", s, v["n_success"], v["n_pairs"], 100 * (v["success_rate"] or 0), v["n_invalid"],
                    100 * (v["success_rate_nontrivial"] or 0), v["n_nontrivial"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
