"""Shared helpers of the tests/test_finetune_*.py files: tiny models built once per test process.

The tiny models are built (random weights, offline) into a temporary cache folder the first time a
test asks for them; `functools.cache` makes every test module of the session reuse that build.
"""

from __future__ import annotations

import functools
import os
import tempfile
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"

import torch  # noqa: E402

torch.set_num_threads(1)

from conftest import make_small_dataset  # noqa: E402

from degusta_learn.finetune.data import LiftedExamples  # noqa: E402
from degusta_learn.render.grid import Grid  # noqa: E402
from degusta_learn.scene import make_episodes  # noqa: E402
from degusta_learn.vlm.prompt_options import PromptOptions  # noqa: E402

GRID = Grid(8, 8)


@functools.cache
def cache_dir() -> Path:
    return Path(tempfile.mkdtemp(prefix="degusta-tiny-"))


@functools.cache
def tiny_dir(kind: str) -> Path:
    """Folder of the tiny `kind` model (idefics3 / qwen2vl), built on first use."""
    from degusta_learn.vlm.random_models.tiny import ensure_tiny

    return ensure_tiny(cache_dir() / kind, kind)


def load(kind: str, adapter=None):
    """A fresh (model, processor) of the tiny model with its image budget set."""
    from degusta_learn.vlm.inputs import set_image_budget
    from degusta_learn.vlm.load import load_vlm

    model, processor = load_vlm(str(tiny_dir(kind)), adapter=adapter, device="cpu", dtype="float32")
    set_image_budget(processor, model.config, None)
    return model, processor


@functools.cache
def dataset():
    return make_small_dataset(n_participants=10, n_trials=5)


def examples(context: int = 2, split: str = "train", options: PromptOptions | None = None, method="mogma",
             render_size: int = 128) -> LiftedExamples:
    ds = dataset()
    opts = options or PromptOptions(compose=["objects"])
    return LiftedExamples(ds, make_episodes(ds, context, split, 0), method, GRID, render_size, opts)
