"""How often a learning round met unusable network covariances (non-finite / not positive definite).

:func:`covariance_failures` gathers, for one learning round, every place where the network's
covariances could not be used, so that a regression of the network's numerics shows up in
``metrics.json`` (round summary, key ``covariance_failures``) instead of only in warnings:

- densification (:class:`gr_graph.densify.DensifiedSequence`): frames whose covariances were
  non-finite or not positive definite (the raw frame was used);
- training (``round_<r>/training/summary.json``, :mod:`training.trainer`): pairs skipped for
  a non-finite network output or loss, or a loss that found covariances not positive definite
  (``loss_error``), out of the pairs drawn (edges x epochs);
- edges (:class:`gr_graph.edge_noise.LearnedEdgeNoise`): edges that got no learned information
  because a scan had no usable covariances (``no_covariances``).

``fraction_frames`` and ``fraction_pairs`` are what the target of issue 10 bounds (< 0.1 %).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gr_graph.atomic import read_json_or_none

__all__ = ["TRAINING_COVARIANCE_SKIPS", "covariance_failures"]

#: trainer skip reasons that mean unusable covariances (``training.trainer.SkipSample``)
TRAINING_COVARIANCE_SKIPS = ("nonfinite_output", "nonfinite_loss", "loss_error")


def covariance_failures(densify_stats: dict[str, Any], training_summary: Path | None = None,
                        edge_noise: dict[str, Any] | None = None) -> dict[str, Any]:
    """Counts of unusable network covariances in one learning round.

    Parameters
    ----------
    densify_stats : dict
        :meth:`gr_graph.densify.DensifiedSequence.stats` of the round.
    training_summary : Path, optional
        The trainer's ``summary.json`` of the round (skipped when missing or unreadable).
    edge_noise : dict, optional
        :meth:`gr_graph.edge_noise.LearnedEdgeNoise.summary` of the round.
    """
    fb = densify_stats.get("fallbacks", {})
    frames = int(densify_stats.get("frames", 0))
    nonfinite, non_pd = int(fb.get("nonfinite_covariance", 0)), int(fb.get("non_pd_covariance", 0))
    out: dict[str, Any] = {
        "frames": frames, "frames_nonfinite": nonfinite, "frames_non_pd": non_pd,
        "fraction_frames": (nonfinite + non_pd) / frames if frames else 0.0,
        "training_pairs": None, "training_pairs_skipped": None, "fraction_pairs": None,
    }
    ts = None if training_summary is None else read_json_or_none(training_summary)
    if ts is not None:
        pairs = int(ts.get("dataset", {}).get("n_edges", 0)) * int(ts.get("epochs_done", 0))
        skips = ts.get("skip_counts", {})
        skipped = int(sum(int(skips.get(k, 0)) for k in TRAINING_COVARIANCE_SKIPS))
        out.update(training_pairs=pairs, training_pairs_skipped=skipped,
                   training_skips={k: int(skips.get(k, 0)) for k in TRAINING_COVARIANCE_SKIPS},
                   fraction_pairs=skipped / pairs if pairs else 0.0)
    if edge_noise is not None and edge_noise.get("mode") == "learned":
        out["edges_without_covariances"] = {
            "odometry": int(edge_noise.get("fallbacks", {}).get("no_covariances", 0)),
            "loop": int(edge_noise.get("loop", {}).get("fallbacks", {}).get("no_covariances", 0)),
        }
    return out
