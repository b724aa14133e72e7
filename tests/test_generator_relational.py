"""The relational generator: deterministic from a seed, valid and plausible by construction over many seeds, the
dataset folder format, its options and the refusal of options that cannot make valid data (naming the key)."""

import hashlib
import json
from collections import Counter

import numpy as np
import pytest

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.scene import default_catalog, default_tables, load_dataset
from degusta_learn.scene.dataset import off_surface
from degusta_learn.synth import STYLES_FILE, generate_dataset, read_relational_styles, relational_with_styles
from degusta_learn.synth.geometry import footprint_points, inside, sizes_of
from degusta_learn.synth.plausible import dataset_violations, violations
from degusta_learn.synth.relational_habits import relational_violations, sample_relational_style
from degusta_learn.synth.relational_realize import (
    MAX_OVERLAP,
    edge_point,
    expected_relational,
    layout,
    overlap_fractions,
    resolve,
    sample_relational,
)
from degusta_learn.synth.relational_style import RelationalStyle, Rule, Seat


def _digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def default_dir(tmp_path_factory):
    return generate_dataset("relational", tmp_path_factory.mktemp("data") / "relational")


def test_the_default_is_the_naturalistic_size_and_loads_with_its_styles(default_dir, capsys):
    assert set(_digest(default_dir)) == {"catalog.json", "tables.json", "arrangements.jsonl", "ratings.jsonl",
                                         "meta.json", STYLES_FILE}
    ds = load_dataset(default_dir)
    assert len(ds.participants) == 199 and len(ds.arrangements) == 995 and len(ds.ratings) == 995
    for pid in ds.participants:  # five trials each, one per default table
        assert sorted(a.table for a in ds.trials_of(pid)) == [0, 1, 2, 3, 4]
    meta = json.loads((default_dir / "meta.json").read_text())
    assert meta["synthetic"] is True and meta["name"] == "relational"
    assert meta["generator"] == "degusta_learn.synth.relational" and meta["seed"] == 0
    assert meta["options"] == {"participants": 199, "noise": 1.0, "multi": 0.2}
    assert ds.label == "relational (SYNTHETIC data)"
    styles = read_relational_styles(default_dir / STYLES_FILE)
    assert sorted(styles) == ds.participants and all(isinstance(s, RelationalStyle) for s in styles.values())
    assert main(["data", "validate", str(default_dir)]) == 0
    out = capsys.readouterr().out
    assert "valid" in out and "199 latent styles" in out and "note:" not in out  # no centre off a surface
    # the population is varied: every habit and several multi-diner layouts occur
    assert len({s.habit for s in styles.values()}) == 6
    assert Counter(s.layout for s in styles.values())["single"] < 190


def test_the_same_seed_gives_byte_identical_files_and_another_seed_others(default_dir, tmp_path):
    again = generate_dataset("relational", tmp_path / "a")
    assert _digest(again) == _digest(default_dir)
    other = generate_dataset("relational", tmp_path / "b", seed=1, options={"participants": 20})
    assert _digest(other)["arrangements.jsonl"] != _digest(default_dir)["arrangements.jsonl"]
    # participant i is the same whatever the number of participants
    small, small_styles = relational_with_styles(0, {"participants": 12})
    styles = read_relational_styles(default_dir / STYLES_FILE)
    assert [s.to_json() for s in small_styles] == [styles[f"p{i:03d}"].to_json() for i in range(12)]
    full = load_dataset(default_dir)
    assert [a.to_json() for a in small.arrangements] == \
        [a.to_json() for a in full.arrangements if int(a.participant[1:]) < 12]


def _overlapping_pairs(ds):
    """(type, type) of every pair of objects of one table that overlap by more than MAX_OVERLAP."""
    pairs = Counter()
    for a in ds.arrangements:
        types = [ds.catalog[p.object].type for p in a.placements]
        frac = overlap_fractions(a.positions, np.array([p.rotation for p in a.placements]), sizes_of(types))
        for i, j in zip(*np.nonzero(frac > MAX_OVERLAP)):
            pairs[tuple(sorted((types[i], types[j])))] += 1
    return pairs


def test_tables_are_plausible_and_on_the_surface_over_many_seeds():
    """20 seeds x 15 participants (~3 s): plausibility rules, a plate on every table, every footprint on the
    surface, and overlaps only where one object lies on or is stacked against another (utensils, plates)."""
    for seed in range(20):
        ds, styles = relational_with_styles(seed, {"participants": 15, "multi": 0.5})
        assert all(not relational_violations(s) for s in styles)
        assert dataset_violations(ds)["any"] == (0, 0)
        assert not off_surface(ds)
        for a in ds.arrangements:
            types = [ds.catalog[p.object].type for p in a.placements]
            assert "plate" in types and len(types) >= 3 and not violations(types)
            rot = np.array([p.rotation for p in a.placements])
            assert inside(ds.tables[a.table], footprint_points(a.positions, rot, sizes_of(types))).all()
        assert all("cup" not in pair and pair != ("plate", "plate") for pair in _overlapping_pairs(ds))


def test_objects_follow_their_rules_not_slots():
    """A rule places an object against its reference's realized position: move the plate and its fork follows
    at the rule's gap; drop the knife and the spoon takes its place in the row; the seat is the table's own edge."""
    table = default_tables()[0]  # oak rectangle, surface y in [0.12, 0.88]
    style = RelationalStyle("p", "classic", "single", [Seat("near", 0.0, 0.05)], [
        Rule("plate", 75, "edge"), Rule("fork", 25, "beside", 0, 0, 270.0, 0.02),
        Rule("knife", 50, "beside", 0, 0, 90.0, 0.03), Rule("spoon", 100, "beside", 2, 0, 90.0, 0.01)])
    xy, rot = layout(style, table, [0, 1, 2, 3])
    assert xy[0] == pytest.approx([0.5, 0.88 - 0.05 - 0.085])  # plate: inset from the near edge
    assert xy[1] == pytest.approx([0.5 - 0.085 - 0.02 - 0.017, xy[0][1]])  # fork: plate rim, gap, half a fork
    assert xy[3][0] == pytest.approx(xy[2][0] + 0.015 + 0.01 + 0.019)
    assert resolve(style, 3, {0, 1, 3})[:2] == ("beside", 0)  # no knife: the spoon is right of the plate ...
    xy_no_knife, _ = layout(style, table, [0, 1, 3])
    assert xy_no_knife[2][0] == pytest.approx(xy[0][0] + 0.085 + 0.03 + 0.019)  # ... at the knife's gap
    # the far seat faces the other way: the fork is on the image's right of the plate, utensils point down
    far = RelationalStyle("p", "classic", "single", [Seat("far", 0.0, 0.05)], style.rules[:2])
    xy_far, rot_far = layout(far, table, [0, 1])
    assert xy_far[0][1] == pytest.approx(0.12 + 0.05 + 0.085) and xy_far[1][0] > xy_far[0][0]
    assert rot_far[1] == pytest.approx(180.0)
    # a round table's edge is its boundary, not its bounding box
    marble = default_tables()[1]
    assert edge_point(marble, 0.0, 0.5)[1] < edge_point(marble, 0.0, 0.0)[1] - 0.05


def test_a_trial_follows_the_rule_graph_order_and_the_oracle_is_noiseless():
    catalog, tables = default_catalog(), list(default_tables())
    rng = np.random.default_rng(3)
    for k in range(30):
        style = sample_relational_style(rng, f"p{k}", catalog, tables, multi=0.5)
        assert style.rules[0].relation == "edge" and style.rules[0].seat == 0
        for i, r in enumerate(style.rules):  # references come first: the list is a topological order
            assert r.relation in ("edge", "centre") or 0 <= r.ref < i
        style.loyalty = 1.0  # every object its rule's favourite: placements map back to rules
        rule_of = {r.object: i for i, r in enumerate(style.rules)}
        trial = sample_relational(style, tables[k % 5], catalog, rng)
        order = [rule_of[p.object] for p in trial]
        assert order[0] == 0  # the anchor first
        for n, i in enumerate(order):  # every object after the object it was placed against
            relation, ref, *_ = resolve(style, i, set(order))
            assert relation in ("edge", "centre") or ref in order[:n]
        assert expected_relational(style, tables[k % 5]) == expected_relational(style, tables[k % 5])


def test_the_noise_option_scales_every_persons_noise():
    quiet, q_styles = relational_with_styles(0, {"participants": 30, "noise": 0.0})
    loud, l_styles = relational_with_styles(0, {"participants": 30, "noise": 2.0})
    assert all(s.noise.position == 0 and s.noise.turn == 0 for s in q_styles)
    assert [s.habit for s in q_styles] == [s.habit for s in l_styles]  # the same people, noisier
    tables = {t.id: t for t in default_tables()}

    def spread(ds, styles):  # mean distance of each trial's plate from the person's noiseless plate
        by = {s.participant: s for s in styles}
        d = []
        for a in ds.arrangements:
            plate = expected_relational(by[a.participant], tables[a.table])[0]
            d.append(np.hypot(a.placements[0].x - plate.x, a.placements[0].y - plate.y))
        return float(np.mean(d))

    # without noise a trial moves only when the rules it sets shift the fit onto the surface
    assert spread(quiet, q_styles) < 0.25 * spread(loud, l_styles)


@pytest.mark.parametrize("argv, message", [
    (["--set", "participants=2"], "relational generator: participants: expected a value from 3 to 20,000, got 2"),
    (["--set", "participants=true"], "relational generator: participants: expected int, got True"),
    (["--set", "participants=ten"], "relational generator: participants: expected int"),
    (["--set", "noise=-1"], "relational generator: noise: expected a value from 0.0 to 5.0"),
    (["--set", "noise=6"], "relational generator: noise: expected a value from 0.0 to 5.0, got 6"),
    (["--set", "multi=1.5"], "relational generator: multi: expected a value from 0.0 to 1.0"),
    (["--set", "colour=red"], "relational generator: unknown key 'colour' (known keys: multi, noise, participants)"),
    (["--set", "participants"], "--set 'participants': expected key=value"),
    (["--legacy"], "legacy: only the naturalistic generator has legacy tables (not 'relational')"),
])
def test_an_option_that_cannot_make_valid_data_is_refused_naming_the_key(tmp_path, capsys, argv, message):
    out = tmp_path / "d"
    assert main(["data", "generate", "relational", "--out", str(out), *argv]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err and message in err, err
    assert not out.exists()


def test_the_other_generators_take_no_options(tmp_path, capsys):
    for name in ("naturalistic", "simulated"):
        assert main(["data", "generate", name, "--out", str(tmp_path / name), "--set", "participants=5"]) == 2
        err = capsys.readouterr().err
        assert f"participants: the {name} generator takes no options" in err and err.count("\n") == 1
        assert not (tmp_path / name).exists()
    with pytest.raises(DegustaError, match="relational generator: noise"):
        relational_with_styles(0, {"noise": "loud"})


def test_options_on_the_command_line_and_overwrite(tmp_path, capsys):
    out = tmp_path / "d"
    assert main(["data", "generate", "relational", "--out", str(out), "--set", "participants=6",
                 "--set", "noise=0.5", "--seed", "4"]) == 0
    assert "wrote the relational dataset (SYNTHETIC)" in capsys.readouterr().out
    meta = json.loads((out / "meta.json").read_text())
    assert meta["seed"] == 4 and meta["options"] == {"participants": 6, "noise": 0.5, "multi": 0.2}
    assert len(load_dataset(out).participants) == 6
    assert main(["data", "generate", "relational", "--out", str(out)]) == 2  # not without --overwrite
    capsys.readouterr()
    assert main(["data", "generate", "relational", "--out", str(out), "--overwrite",
                 "--set", "participants=4"]) == 0
    assert len(load_dataset(out).participants) == 4


@pytest.mark.parametrize("seed", [-1, 2**32, 1.0, True, None])
def test_a_bad_seed_is_refused_before_writing_and_the_largest_validates(tmp_path, capsys, seed):
    with pytest.raises(DegustaError, match="seed"):
        generate_dataset("relational", tmp_path / "g", seed=seed, options={"participants": 3})
    assert not (tmp_path / "g").exists()
    out = generate_dataset("relational", tmp_path / "big", seed=2**32 - 1, options={"participants": 3})
    assert main(["data", "validate", str(out)]) == 0, capsys.readouterr().err
