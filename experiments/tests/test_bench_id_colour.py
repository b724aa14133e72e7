"""benchmarks/bench_id_colour.py: the colour-histogram reference for telling a type's objects apart."""

import numpy as np
import pytest
from benchmark_support import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_id_colour")


def test_histogram_counts_only_the_changed_pixels(bench):
    empty = np.full((4, 4, 3), 200, dtype=np.uint8)
    image = empty.copy()
    image[0, :2] = (255, 0, 0)  # two red pixels
    image[1, 0] = (0, 0, 255)  # one blue pixel
    h = bench.colour_histogram(image, empty, bins=2)
    assert h.sum() == pytest.approx(1.0)
    red, blue = (1 * 2 + 0) * 2 + 0, (0 * 2 + 0) * 2 + 1
    assert h[red] == pytest.approx(2 / 3) and h[blue] == pytest.approx(1 / 3)
    assert bench.colour_histogram(empty, empty) is None  # nothing drawn: no histogram, never a division by 0


def test_scores_are_accuracies_per_type_of_the_real_catalog(bench, capsys):
    from degusta_learn.finetune.pretrain.train import catalog_and_tables
    from degusta_learn.render.grid import Grid
    from degusta_learn.render.lifting import Renderer

    catalog, tables, root = catalog_and_tables(None)
    scores, pooled = bench.id_accuracy(Renderer(catalog, tables, root, size=64), catalog, tables, Grid(8, 8),
                                       n_views=2, seed=0)
    assert set(scores) == set(pooled) == set(catalog.types)
    assert all(0 <= v <= 1 for v in [*scores.values(), *pooled.values()])
    assert np.mean(list(scores.values())) > 2 / 25  # colour tells some objects apart even at 64 px (chance 0.04)
    assert bench.main(["--sizes", "64", "--views", "2"]) == 0
    assert "64px" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        bench.main(["--views", "1"])  # one view cannot be both reference and query
