"""Metrics (numpy + scipy only): matching, Kabsch RMSD, per-episode scores, acceptability, bootstrap.

See docs/metrics.md. Kabsch RMSD alone rewards predicting one or two objects (N = 1 gives RMSD 0), so
unregistered RMSD, count error and the set-aware `set_rmsd` (unmatched objects cost SET_PENALTY each;
used to rank methods) are always reported beside it. The rest of the task plan: object precision and F1
(beside accuracy, the recall), placement order (Kendall's tau, plan.py), rotation modulo each object's
symmetry (plan.py), the unregistered set RMSD, and physical plausibility: centroids off the table and
overlapping footprints (plausibility.py). A method whose answers take a shortcut (too few objects, padding,
one answer for everyone) is degenerate (degenerate.py) and ranked last. Intervals and paired tests resample participants when given
`clusters` (bootstrap.py).

Usage:
    from degusta_learn.metrics import score_many, bootstrap_ci, fraction_acceptable
    scores = score_many(ds.catalog, gts, predictions, tables=ds.tables)
    mean, lo, hi = bootstrap_ci([s.rmsd for s in scores], clusters=[gt.participant for gt in gts])
"""

from degusta_learn.metrics.acceptability import (
    ACCEPTABILITY_ERROR,
    PAPER_ACCEPTABILITY,
    PAPER_ACCEPTABILITY_ERROR,
    PAPER_MOGMA_FRACTION,
    THRESHOLDS,
    acceptability_curve,
    fraction_acceptable,
)
from degusta_learn.metrics.bootstrap import (
    bootstrap_ci,
    bootstrap_means,
    n_clusters,
    paired_bootstrap,
    percentile_p_value,
)
from degusta_learn.metrics.degenerate import (
    PAD_MARGIN,
    PAD_RATIO,
    REASONS,
    SHORT_RATIO,
    DegenerateVerdict,
    answer_key,
    constant_fraction,
    degenerate_answers,
)
from degusta_learn.metrics.kabsch import kabsch_rmsd, kabsch_rmsd_batch, kabsch_transform, unregistered_rmsd
from degusta_learn.metrics.matching import feature_table, match, match_costs
from degusta_learn.metrics.plan import (
    SHAPE_SYMMETRY,
    TYPE_SYMMETRY,
    UNKNOWN_SYMMETRY,
    kendall_tau,
    rotation_errors,
    symmetry_order,
)
from degusta_learn.metrics.plausibility import (
    OVERLAP_FRACTION,
    footprint_overlap,
    off_table_rates,
    overlap_rates,
)
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
    "ACCEPTABILITY_ERROR", "PAPER_ACCEPTABILITY_ERROR",
    "DEGENERATE_FRACTION", "OVERLAP_FRACTION", "PAD_MARGIN", "PAD_RATIO", "PAPER_ACCEPTABILITY",
    "PAPER_MOGMA_FRACTION", "REASONS", "SET_PENALTY", "SHAPE_SYMMETRY", "SHORT_RATIO", "THRESHOLDS", "TYPE_SYMMETRY",
    "UNKNOWN_SYMMETRY",
    "DegenerateVerdict", "EpisodeScore", "MatchedPair", "acceptability_curve", "answer_key", "bootstrap_ci",
    "bootstrap_means", "constant_fraction", "degenerate_answers", "feature_table", "few_matched_fraction", "footprint_overlap", "fraction_acceptable", "kabsch_rmsd", "kabsch_rmsd_batch",
    "kabsch_transform", "kendall_tau", "match", "match_costs", "matched_pairs", "n_clusters", "off_table_rates",
    "overlap_rates", "paired_bootstrap", "percentile_p_value", "rotation_errors", "score_many", "score_prediction",
    "set_rmsd_points", "symmetry_order", "unregistered_rmsd",
]
