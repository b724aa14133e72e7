"""`degusta collect --dataset DIR [--new] [--config STUDY] [--set KEY=VALUE] [--host H] [--port N]`.

Holds the study folder's lock while it serves (a second `degusta collect`, or any other writer of the folder, is
refused in one line), and the researcher's key in memory only: DEGUSTA_COLLECT_KEY if set, else a new random one.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

from degusta_learn.collect.server import serve
from degusta_learn.collect.study import load_study_config, new_study_folder, open_study
from degusta_learn.errors import DegustaError
from degusta_learn.files.locks import hold
from degusta_learn.shipped import resolve_config
from degusta_learn.webio import check_bindable

KEY_VARIABLE = "DEGUSTA_COLLECT_KEY"


def collect(dataset: Path, config: Path | None, overrides: list[str], new: bool = False, host: str = "127.0.0.1",
            port: int = 8765) -> str:
    cfg = load_study_config(config or resolve_config("collect_study"), overrides)
    key = os.environ.get(KEY_VARIABLE) or secrets.token_urlsafe(18)
    if len(key) < 12:
        raise DegustaError(f"{KEY_VARIABLE}: a key of {len(key)} characters is too easy to guess (use at least 12)")
    check_bindable(host, port)  # before --new makes a folder or the server says it serves
    with hold(dataset, "study folder"):
        if new:
            new_study_folder(dataset)
        study = open_study(dataset, cfg)
        serve(study, key, host=host, port=port)
    return "study server stopped; the data is in " + str(dataset)
