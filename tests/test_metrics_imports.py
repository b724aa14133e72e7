"""The metrics stay light: importing them pulls in no torch, PIL or transformers (STYLE.md, light core)."""

import subprocess
import sys

import degusta_learn.metrics as metrics


def test_metrics_import_no_heavy_packages():
    code = ("import sys, degusta_learn.metrics; "
            "bad = [m for m in ('torch', 'PIL', 'transformers') if m in sys.modules]; "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_public_names_exist():
    for name in ("match", "kabsch_rmsd", "unregistered_rmsd", "EpisodeScore", "score_prediction", "score_many",
                 "PAPER_ACCEPTABILITY", "THRESHOLDS", "acceptability_curve", "fraction_acceptable",
                 "bootstrap_ci", "paired_bootstrap"):
        assert name in metrics.__all__ and hasattr(metrics, name)
