"""`degusta collect`: the paper's browser study for collecting participants' arrangements and ratings.

A researcher points it at a study folder (a dataset folder: the catalog and tables participants set); participants
set tables in the browser and rate them; every submission is appended to the folder in the dataset format, so that
`degusta data validate`, `train`, `evaluate` and `plan` read it as they read any dataset (docs/collect.md).

Modules: study.py (the config and the folder), store.py (sessions, steps, writes, resuming), selfeval.py (the
jittered copy and its distances), images.py (the pictures), server.py (the web application), research.py (progress
and export), static/ (the page).
"""

from degusta_learn.collect.study import StudyConfig, load_study_config, new_study_folder, open_study

__all__ = ["StudyConfig", "load_study_config", "new_study_folder", "open_study"]
