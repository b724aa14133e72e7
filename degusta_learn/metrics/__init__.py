"""Metrics (numpy + scipy only): matching, Kabsch RMSD, per-episode scores, acceptability, bootstrap.

See docs/metrics.md. Kabsch RMSD alone rewards predicting one or two objects (N = 1 gives RMSD 0), so
unregistered RMSD, count error and the set-aware `set_rmsd` (unmatched objects cost SET_PENALTY each;
used to rank methods) are always reported beside it.

Usage:
    from degusta_learn.metrics import score_many, bootstrap_ci, fraction_acceptable
    scores = score_many(ds.catalog, gts, predictions)
    mean, lo, hi = bootstrap_ci([s.rmsd for s in scores])
"""

from degusta_learn.metrics.acceptability import (
    PAPER_ACCEPTABILITY,
    PAPER_MOGMA_FRACTION,
    THRESHOLDS,
    acceptability_curve,
    fraction_acceptable,
)
from degusta_learn.metrics.bootstrap import bootstrap_ci, paired_bootstrap
from degusta_learn.metrics.kabsch import kabsch_rmsd, kabsch_rmsd_batch, kabsch_transform, unregistered_rmsd
from degusta_learn.metrics.matching import feature_table, match, match_costs
from degusta_learn.metrics.scores import (
    EpisodeScore,
    MatchedPair,
    matched_pairs,
    score_many,
    score_prediction,
)
from degusta_learn.metrics.set_score import (
    DEGENERATE_FRACTION,
    SET_PENALTY,
    few_matched_fraction,
    set_rmsd_points,
)

__all__ = [
    "DEGENERATE_FRACTION", "PAPER_ACCEPTABILITY", "PAPER_MOGMA_FRACTION", "SET_PENALTY", "THRESHOLDS",
    "EpisodeScore", "MatchedPair", "acceptability_curve", "bootstrap_ci", "feature_table", "few_matched_fraction",
    "fraction_acceptable", "kabsch_rmsd", "kabsch_rmsd_batch", "kabsch_transform", "match", "match_costs",
    "matched_pairs", "paired_bootstrap", "score_many", "score_prediction", "set_rmsd_points", "unregistered_rmsd",
]
