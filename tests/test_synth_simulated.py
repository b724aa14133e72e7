"""The simulated benchmark: 18 preferences x 2 tables, 72 experiments, colour and layout preferences."""

import numpy as np

from degusta_learn.synth import simulated, simulated_with_styles
from degusta_learn.synth.simulated import COLORS, NOISE, POSITIONS


def test_eighteen_preferences_on_two_tables():
    ds, styles, _ = simulated_with_styles(0)
    expected = {f"sim_{p}_{c}_{n}" for p in POSITIONS for c in COLORS for n in NOISE}
    assert len(expected) == 18 and set(ds.participants) == expected
    assert set(ds.tables) == {0, 1} and ds.synthetic
    for pid, arrs in ds.by_participant().items():
        assert [a.trial for a in arrs] == list(range(12))
        assert [a.table for a in arrs] == [0] * 6 + [1] * 6
        colour = pid.split("_")[2]
        for a in arrs:  # all objects in the preferred colour, the same objects every time
            assert all(colour in ds.catalog[o].colors for o in a.objects)
            assert a.objects == arrs[0].objects
            assert [ds.catalog[o].type for o in a.objects] == ["plate", "fork", "knife", "spoon", "cup"]
            assert ds.tables[a.table].contains(a.positions[:, 0], a.positions[:, 1]).all()


def test_seventy_two_experiments():
    ds, _, episodes = simulated_with_styles(0)
    assert len(episodes) == 72 and len({e.id for e in episodes}) == 72
    contexts = {(e.participant, e.context) for e in episodes}
    assert len(contexts) == 36  # 18 preferences x 2 context tables
    for e in episodes:
        tables = {ds.arrangement(e.participant, t).table for t in e.context}
        target = ds.arrangement(e.participant, e.target).table
        assert len(e.context) == 4 and len(tables) == 1 and e.target not in e.context
        assert (target in tables) == (e.task == "reconstruction")
    assert sum(e.task == "reconstruction" for e in episodes) == 36


def test_layouts_and_noise_levels_differ():
    ds = simulated(0)

    def spread(pid):  # std of each object's position over the participant's trials on table 0
        arrs = [a for a in ds.trials_of(pid) if a.table == 0]
        return np.stack([a.positions - a.positions.mean(0) for a in arrs]).std(0).mean()

    assert spread("sim_western_red_high") > 1.5 * spread("sim_western_red_low")
    west, mirror = ds.arrangement("sim_western_blue_low", 0), ds.arrangement("sim_mirrored_blue_low", 0)
    # fork left of the plate in western, right of it when mirrored
    assert west.positions[1, 0] < west.positions[0, 0] and mirror.positions[1, 0] > mirror.positions[0, 0]
