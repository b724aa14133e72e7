"""The posterior-predictive floor: hand-computed posteriors, known styles recovered, the prior predictive, refusals."""

import json

import numpy as np
import pytest

from degusta_learn.baselines.heuristic import consensus_rows
from degusta_learn.baselines.transfer import place_on
from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.metrics import score_many, score_prediction
from degusta_learn.scene import Arrangement, Dataset, Episode, default_catalog, default_tables, load_dataset, save_dataset
from degusta_learn.synth import naturalistic_with_styles
from degusta_learn.synth.posterior import Posterior, PosteriorConfig
from degusta_learn.synth.posterior_base import check_generator, expected_set_rmsd
from degusta_learn.synth.posterior_prior import GeneratorPrior
from degusta_learn.synth.realize import expected_arrangement, sample_arrangement
from degusta_learn.synth.style import Setting, Slot, Style
from degusta_learn.synth.templates import sample_style

CAT = default_catalog()
TABLES = {t.id: t for t in default_tables()}


def _cfg(**kw) -> PosteriorConfig:
    return PosteriorConfig(method="posterior", dataset="unused", out="unused.jsonl", **{
        "prior_styles": 300, "candidates": 20, "samples": 40, **kw})


def _ids(type_: str, k: int) -> list[int]:
    return [o.id for o in CAT.of_type(type_)][:k]


def test_inclusion_is_the_beta_bernoulli_posterior_over_the_prior_values():
    prior = GeneratorPrior(CAT, 1, seed=0)
    prior.p_include["cup"] = np.array([1.0, 0.5])  # a prior of two slots: always set, or half the time
    # set in 2 of 2: (1 * 1 + 0.5^2 * 0.5) / (1 + 0.5^2) = 0.9; in 1 of 2 only p = 0.5 can explain it
    assert prior.inclusion("cup", 2, 2) == pytest.approx(0.9)
    assert prior.inclusion("cup", 1, 2) == pytest.approx(0.5)
    assert prior.inclusion("cup", 0, 0) == pytest.approx(0.75)  # no context: the prior mean
    draws = [prior.sample_inclusion("cup", 2, 2, np.random.default_rng(i)) for i in range(400)]
    assert 0.75 < np.mean(np.array(draws) == 1.0) < 0.85  # weights 1 : 0.25 -> 0.8


def test_object_posterior_matches_a_hand_computed_case():
    prior = GeneratorPrior(CAT, 1, seed=0)
    ids = prior.ids["cup"]
    n = len(ids)
    logits = np.full((1, n), -50.0)
    logits[0, :3] = 0.0  # the favourite is one of the first three cups, equally likely
    weights = np.full((1, n), 1e-9)
    weights[0, :3] = [1.0, 1.0, 2.0]  # other picks: taste weights 1, 1, 2
    prior.logits["cup"], prior.weights["cup"], prior.loyalty = logits, weights, np.array([0.8])
    a, b, c = (int(i) for i in ids[:3])
    post = prior.object_posterior(["cup"], [[a, a]])
    z = 4.0 + (n - 3) * 1e-9
    lik = np.array([0.8 ** 2, (0.2 * 1 / (z - 1)) ** 2, (0.2 * 1 / (z - 2)) ** 2])  # favourite a, b or c
    fav = lik / lik.sum()
    assert post.favourite[0][0, :3] == pytest.approx(fav, rel=1e-6)
    # next object: the favourite with p 0.8, else another by weight (excluding the favourite)
    w = [1.0, 1.0, 2.0]
    nxt = [sum(fav[f] * (0.8 if o == f else 0.2 * w[o] / (z - w[f])) for f in range(3)) for o in range(3)]
    assert post.predictive[0][:3] == pytest.approx(nxt, rel=1e-6)
    assert prior.prior_objects(["cup", "cup"]) == [c, a]  # no context: the heaviest first, then a tie -> a


def _dataset(style: Style, tables: list[int]) -> Dataset:
    """A participant whose trials are the style's noiseless arrangements on `tables` (the last is the target)."""
    arrs = [Arrangement("p000", i, t, tuple(expected_arrangement(style, TABLES[t]))) for i, t in enumerate(tables)]
    return Dataset(CAT, TABLES, arrs, meta={"synthetic": True})


def _answer(style: Style, tables: list[int], **kw):
    ds = _dataset(style, tables)
    ep = Episode("p000/e", "p000", tuple(range(len(tables) - 1)), len(tables) - 1, "generalization")
    placements, diag = Posterior(ds, _cfg(**kw), plausible=False).predict(ep)
    truth = ds.arrangement("p000", len(tables) - 1)
    return placements, diag, score_prediction(CAT, truth, placements)


def test_a_one_setting_style_is_recovered_from_two_noiseless_tables():
    plate, fork, knife, cup = _ids("plate", 1)[0], _ids("fork", 1)[0], _ids("knife", 1)[0], _ids("cup", 1)[0]
    style = Style("p000", "western", [Setting(0.5, 0.75)], [
        Slot("plate", 0.0, 0.0, 0.0, plate), Slot("fork", -0.13, 0.0, 0.0, fork),
        Slot("knife", 0.13, 0.0, 0.0, knife), Slot("cup", 0.17, -0.16, 0.0, cup)])
    placements, diag, score = _answer(style, [0, 4, 1])  # oak and bench in the context; the round table next
    assert [p.object for p in placements] == [plate, fork, knife, cup]  # the slots, their favourites, in order
    assert diag["hypothesis"] == "single" and diag["context"] == 2
    assert score.set_rmsd < 0.001 and score.object_accuracy == 1.0
    # consensus carries positions relative to the surface bounds, which stretches physical offsets: 0.022 here
    ds = _dataset(style, [0, 4, 1])
    (objs, uv, rot), _ = consensus_rows(ds, [ds.arrangement("p000", 0), ds.arrangement("p000", 1)], TABLES[1])
    assert score_prediction(CAT, ds.arrangement("p000", 2), place_on(TABLES[1], CAT, objs, uv, rot)).set_rmsd > 0.015


def test_two_settings_facing_each_other_are_told_from_one_by_their_spacing():
    plates, forks, knives = _ids("plate", 2), _ids("fork", 2), _ids("knife", 2)
    slots = []
    for s in range(2):
        slots += [Slot("plate", 0.0, 0.0, 0.0, plates[s], s), Slot("fork", -0.13, 0.0, 0.0, forks[s], s),
                  Slot("knife", 0.13, 0.0, 0.0, knives[s], s)]
    style = Style("p000", "multi", [Setting(0.5, 0.8, 0.0), Setting(0.5, 0.2, 180.0)], slots, scale=0.9)
    # round (0.92 high) and bench (0.6): the seats are 0.55 and 0.36 apart; offsets keep their size
    placements, diag, score = _answer(style, [1, 4, 0])
    assert diag["hypothesis"] == "multi" and diag["hypothesis_weights"]["multi"] > 0.99
    assert sorted(p.object for p in placements) == sorted(plates + forks + knives)
    assert score.set_rmsd < 0.001  # one setting (offsets kept, the seats' spacing too) would score 0.004


def test_context_zero_is_the_prior_predictive_one_answer_per_table():
    style = sample_style(np.random.default_rng(5), "p000", CAT)
    ds = _dataset(style, [0, 1, 2])
    model = Posterior(ds, _cfg(), plausible=False)
    a0, d0 = model.predict(Episode("a", "p000", (), 0, "generalization"))
    b0, _ = model.predict(Episode("b", "p000", (), 0, "generalization"))
    a1, _ = model.predict(Episode("c", "p000", (), 1, "generalization"))
    assert a0 == b0 and d0["hypothesis"] == "prior" and d0["context"] == 0 and len(a0) >= 3
    assert a1 != a0  # another table, another answer
    # its expected set RMSD beats that of every prior style's own (noise-free, own-object) answer on those draws
    draws = [sample_arrangement(s, TABLES[0], CAT, np.random.default_rng(9)) for s in model._truth_styles]
    risk = expected_set_rmsd(CAT, a0, draws)
    assert risk < np.mean([expected_set_rmsd(CAT, expected_arrangement(s, TABLES[0]), draws)
                           for s in model.prior.styles[:20]])


def test_expected_set_rmsd_equals_the_metrics_set_rmsd():
    rng = np.random.default_rng(3)
    styles = [sample_style(rng, "x", CAT) for _ in range(60)]
    draws = [sample_arrangement(s, TABLES[2], CAT, rng) for s in styles[:50]]
    gts = [Arrangement("d", i, 2, tuple(d)) for i, d in enumerate(draws)]
    for s in styles[50:]:
        pred = expected_arrangement(s, TABLES[2])
        assert expected_set_rmsd(CAT, pred, draws) == pytest.approx(
            np.mean([x.set_rmsd for x in score_many(CAT, gts, [pred] * len(gts))]), abs=1e-12)
    assert expected_set_rmsd(CAT, [], draws) == pytest.approx(0.2)


@pytest.mark.parametrize("key, value, match", [("samples", 0, "samples: expected an integer >= 1"),
                                               ("search", -1, "search: expected an integer >= 0"),
                                               ("candidates", 400, "candidates: 400 is more than prior_styles")])
def test_bad_config_values_name_the_key(key, value, match):
    with pytest.raises(DegustaError, match=match):
        _cfg(**{key: value})


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The naturalistic generator's first 8 participants (seed 0), as a dataset folder."""
    return save_dataset(naturalistic_with_styles(0, 8)[0], tmp_path_factory.mktemp("nat") / "d")


def test_refuses_data_the_generator_did_not_make(tiny, small_dataset_dir, tmp_path):
    assert check_generator(load_dataset(tiny)) == (0, True)
    legacy = save_dataset(naturalistic_with_styles(0, 8, plausible=False)[0], tmp_path / "legacy")
    assert check_generator(load_dataset(legacy)) == (0, False)  # the legacy tables' generator, from meta.json
    with pytest.raises(DegustaError, match="posterior needs data made by `degusta data generate naturalistic`"):
        check_generator(load_dataset(small_dataset_dir))
    edited = tmp_path / "edited"
    save_dataset(load_dataset(tiny), edited)
    lines = (edited / "arrangements.jsonl").read_text().splitlines()
    row = json.loads(lines[7])
    row["placements"][0]["x"] = round(row["placements"][0]["x"] + 0.01, 6)
    (edited / "arrangements.jsonl").write_text("\n".join(lines[:7] + [json.dumps(row)] + lines[8:]) + "\n")
    with pytest.raises(DegustaError, match="participant 'p001' trial 2 is not what the generator makes"):
        check_generator(load_dataset(edited))
    meta = json.loads((edited / "meta.json").read_text())
    del meta["seed"]
    (edited / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DegustaError, match="has no integer 'seed'"):
        check_generator(load_dataset(edited))


def test_predict_end_to_end_and_the_one_line_refusal(tiny, small_dataset_dir, tmp_path, capsys):
    out = tmp_path / "p.jsonl"
    small = ["--set", "prior_styles=60", "--set", "candidates=5", "--set", "samples=10", "--set", "search=1"]
    assert main(["predict", "--config", "configs/posterior.yaml", "--set", f"dataset={tiny}", "--set", f"out={out}",
                 "--set", "context=2", *small]) == 0
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    assert len(rows) == 10 and all(not r["failed"] and len(r["placements"]) >= 3 for r in rows)  # 2 test people
    assert {r["diagnostics"]["context"] for r in rows} == {2} and all(r["method"] == "posterior" for r in rows)
    capsys.readouterr()
    assert main(["predict", "--config", "configs/posterior.yaml", "--set", f"dataset={small_dataset_dir}",
                 "--set", f"out={tmp_path / 'x.jsonl'}", *small]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "posterior needs data made by" in err and "meta.json" in err
    assert not (tmp_path / "x.jsonl").exists()
