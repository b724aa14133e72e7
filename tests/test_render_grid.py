"""Grid geometry: cell ids, encode/decode, footprints, directions, circular mean, quantization floor."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import circmean

from degusta_learn.errors import DegustaError
from degusta_learn.render.grid import (
    DIRECTIONS,
    Grid,
    circular_mean,
    direction_to_rotation,
    quantization_rmsd,
    rotation_to_direction,
)
from degusta_learn.scene import default_catalog

CAT = default_catalog()


def _first(type_):
    return CAT.of_type(type_)[0]


def test_cell_ids_letters_are_columns_numbers_are_rows():
    g = Grid(8, 8)
    assert g.cell_id(0, 0) == "A1" and g.cell_id(2, 6) == "C7" and g.cell_id(7, 7) == "H8"
    assert g.cells[:3] == ["A1", "B1", "C1"] and g.cells[8] == "A2" and len(g.cells) == 64
    assert g.parse_cell(" c7 ") == (2, 6)
    assert g.cell_center("A1") == (1 / 16, 1 / 16)
    assert Grid(4, 6).cell_center("F4") == pytest.approx((11 / 12, 7 / 8))


@pytest.mark.parametrize("bad", ["I1", "A9", "A0", "7C", "", "AA1", 3])
def test_parse_cell_rejects(bad):
    with pytest.raises(DegustaError):
        Grid(8, 8).parse_cell(bad)


@pytest.mark.parametrize("rows, cols", [(0, 8), (8, 0), (8, 27), (-1, 3)])
def test_bad_grid_sizes(rows, cols):
    with pytest.raises(DegustaError, match="grid"):
        Grid(rows, cols)


def test_small_object_in_one_cell_round_trips_to_its_centre():
    g = Grid(8, 8)
    x, y = g.cell_center("C3")
    cells = g.encode(_first("cup"), x, y, 0.0)  # a cup (0.08) inside a 0.125 cell
    assert cells == ["C3"]
    assert g.decode(cells) == pytest.approx((x, y))


def test_plate_on_a_grid_corner_covers_four_cells():
    g = Grid(8, 8)
    cells = g.encode(_first("plate"), 0.5, 0.5, 0.0)
    assert cells == ["D4", "E4", "D5", "E5"]
    assert g.decode(cells) == pytest.approx((0.5, 0.5))


def test_knife_cells_follow_its_rotation():
    # knife 0.03 x 0.18 centred in cell D4: north-south it spans y 0.348..0.527 (rows 3-5), east-west x
    g = Grid(8, 8)
    knife = _first("knife")
    assert g.encode(knife, 0.4375, 0.4375, 0.0) == ["D3", "D4", "D5"]
    assert g.encode(knife, 0.4375, 0.4375, 90.0) == ["C4", "D4", "E4"]
    assert g.encode(knife, 0.4375, 0.4375, 180.0) == ["D3", "D4", "D5"]


def test_footprint_cells_grow_with_object_size():
    g = Grid(12, 12)
    x, y = 0.46, 0.52
    cup, plate = set(g.encode(_first("cup"), x, y, 0)), set(g.encode(_first("plate"), x, y, 0))
    assert cup < plate  # the cup's cells are a strict subset of the (larger) plate's
    big = dataclasses.replace(_first("fork"), type="plate")  # same object, plate-sized footprint
    assert len(g.encode(big, x, y, 0)) > len(g.encode(_first("fork"), x, y, 0))


def test_picture_objects_use_the_footprint_rectangle():
    g = Grid(10, 10)
    round_plate = next(o for o in CAT.of_type("plate") if o.shape == "round")
    pic = dataclasses.replace(round_plate, image="plate.png")
    # the 0.17 square's corner reaches (0.605, 0.605), inside cell G7; the round plate's rim only ~0.58
    drawn, rect = set(g.encode(round_plate, 0.52, 0.52, 0)), set(g.encode(pic, 0.52, 0.52, 0))
    assert drawn < rect and "G7" in rect - drawn and "G6" in drawn


def test_decode_weighted_weighs_each_response_equally():
    """The mean of the responses' centroids (the paper): a response listing more cells weighs no more."""
    g = Grid(8, 8)
    x, _ = g.decode_weighted([["A1"], ["A1", "B1"]])
    assert x == pytest.approx((1 / 16 + (1 / 16 + 3 / 16) / 2) / 2)  # not (1/16 + 1/16 + 3/16) / 3
    # A 9-cell plate answer and a 1-cell one pull equally: the midpoint of their centroids.
    big = [f"{c}{r}" for r in (1, 2, 3) for c in "ABC"]
    assert g.decode_weighted([big, ["H8"]]) == pytest.approx(((3 / 16 + 15 / 16) / 2, (3 / 16 + 15 / 16) / 2))
    assert g.decode_weighted([["D4", "E5"], ["D4", "E5"]]) == g.decode(["D4", "E5"])
    with pytest.raises(DegustaError):
        g.decode([])
    with pytest.raises(DegustaError):
        g.decode_weighted([])
    with pytest.raises(DegustaError):
        g.decode_weighted([["A1"], []])


@pytest.mark.parametrize("deg, d", [(0, "N"), (350, "N"), (22.4, "N"), (22.6, "NE"), (22.5, "NE"), (45, "NE"),
                                    (180, "S"), (337.4, "NW"), (337.6, "N"), (359.99, "N"), (-10, "N"),
                                    (270, "W"), (720 + 90, "E")])
def test_rotation_to_direction(deg, d):
    assert rotation_to_direction(deg) == d


def test_direction_round_trip_and_errors():
    for i, d in enumerate(DIRECTIONS):
        assert direction_to_rotation(d) == 45.0 * i
        assert rotation_to_direction(direction_to_rotation(d)) == d
    assert direction_to_rotation(" ne ") == 45.0
    with pytest.raises(DegustaError, match="north"):
        direction_to_rotation("north")


def test_circular_mean_wraps_and_matches_scipy():
    assert circular_mean([350, 10]) == pytest.approx(0.0, abs=1e-9)
    assert circular_mean([350, 20]) == pytest.approx(5.0)
    assert circular_mean([0, 90], weights=[1, 0]) == pytest.approx(0.0)
    assert 0 <= circular_mean([359.9999999999]) < 360
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = (rng.normal(0, 40, size=5) + rng.uniform(0, 360)) % 360
        assert circular_mean(a) == pytest.approx(circmean(a, high=360, low=0) % 360, abs=1e-6)


def test_quantization_floor_shrinks_with_finer_grids(small_dataset):
    coarse, fine = quantization_rmsd(small_dataset, Grid(4, 4)), quantization_rmsd(small_dataset, Grid(12, 12))
    assert 0 < fine < coarse < 0.25
    g = Grid(8, 8)
    assert quantization_rmsd(small_dataset, g) <= quantization_rmsd(small_dataset, g, registered=False) + 1e-12


def test_registered_floor_uses_the_same_kabsch_as_the_metrics():
    from degusta_learn.metrics import kabsch_rmsd
    from degusta_learn.render.grid import _kabsch_rmsd

    rng = np.random.default_rng(1)
    for n in (2, 3, 6):
        p, q = rng.uniform(size=(n, 2)), rng.uniform(size=(n, 2))
        assert _kabsch_rmsd(p, q) == pytest.approx(kabsch_rmsd(p, q), abs=1e-12)
