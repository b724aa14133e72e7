"""Shared fixtures: a small hand-built dataset (no generator needed) and its folder on disk.

The suite never downloads: Hugging Face offline mode is set here, before any test imports huggingface_hub
(which reads it once), and every subprocess a test starts inherits it. The toolkit itself never sets it.
"""

from __future__ import annotations

import os
import signal
import warnings

os.environ["HF_HUB_OFFLINE"] = "1"
os.environ["TRANSFORMERS_OFFLINE"] = "1"

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from degusta_learn.scene import Arrangement, Dataset, Placement, default_catalog, default_tables, save_dataset  # noqa: E402


def make_small_dataset(n_participants: int = 10, n_trials: int = 5, seed: int = 0) -> Dataset:
    """Participants who each set a fixed-ish layout of 3-5 objects on every table, with noise."""
    rng = np.random.default_rng(seed)
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    arrangements = []
    for p in range(n_participants):
        n_obj = int(rng.integers(3, 6))
        objects = rng.choice(catalog.ids, size=n_obj, replace=False).tolist()
        layout = rng.uniform(0.3, 0.7, size=(n_obj, 2))
        rot = rng.choice([0.0, 90.0, 180.0, 270.0], size=n_obj)
        for t in range(n_trials):
            table = t % len(tables)
            xy = np.clip(layout + rng.normal(0, 0.01, size=layout.shape), 0.25, 0.75)
            arrangements.append(Arrangement(f"p{p:03d}", t, table, tuple(
                Placement(int(o), float(x), float(y), float(r)) for o, (x, y), r in zip(objects, xy, rot))))
    return Dataset(catalog, tables, arrangements, meta={"name": "small-test", "synthetic": True})


@pytest.fixture
def small_dataset() -> Dataset:
    return make_small_dataset()


@pytest.fixture
def small_dataset_dir(tmp_path, small_dataset):
    return save_dataset(small_dataset, tmp_path / "small")


@pytest.fixture
def one_torch_thread():
    """Two torch threads on a shared 2-core machine oversubscribe badly; tiny models run best on one."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(autouse=True)
def _sigint_restored(request):
    """Every test starts with Python's own Ctrl-C handler, and one that leaves another behind is named: a library
    (Lightning, a server) that sets SIGINT to "ignore" and does not put it back would otherwise make every later
    test's Ctrl-C, and every subprocess it starts, ignore the signal (the signal tests then fail far from the cause).
    A suite started with SIGINT ignored (a background job of a non-interactive shell) gets Python's handler too."""
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        warnings.warn(f"{request.node.nodeid} left SIGINT set to another handler; restored", stacklevel=1)
