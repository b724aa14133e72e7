"""The posterior floor on relational data: a person's rules recovered from noiseless tables, structures that cannot
have made a table dropped, the prior predictive at context 0, the floor ahead of consensus and near the oracle on
low-noise data, and data the relational generator did not make refused in one line."""

import copy
import json

import numpy as np
import pytest

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.methods import get_method
from degusta_learn.metrics import score_many
from degusta_learn.scene import load_dataset, make_episodes, save_dataset
from degusta_learn.synth import generate_dataset, relational_with_styles
from degusta_learn.synth.posterior import PosteriorConfig
from degusta_learn.synth.posterior_base import check_relational
from degusta_learn.synth.posterior_model import Trial
from degusta_learn.synth.relational_posterior import RelationalPosterior, RelationalPrior, fit_structure, signature
from degusta_learn.synth.relational_realize import expected_relational, oracle_rules, place


@pytest.fixture(scope="module")
def quiet():
    """Six relational people without noise: their context tables show their rules exactly."""
    return relational_with_styles(3, {"participants": 6, "noise": 0.0})


@pytest.fixture(scope="module")
def rel_dir(tmp_path_factory):
    return generate_dataset("relational", tmp_path_factory.mktemp("data") / "relational", options={"participants": 12})


def _trials(ds, pid, trials):
    return [Trial.of(a, ds.tables[a.table], ds.catalog) for a in ds.arrangements
            if a.participant == pid and a.trial in trials]


def _cfg(ds_dir, **kw) -> PosteriorConfig:
    return PosteriorConfig(method="posterior", dataset=str(ds_dir), out="unused.jsonl", **{
        "prior_styles": 200, "candidates": 20, "samples": 30, "structures": 4, **kw})


def test_a_persons_numbers_are_recovered_from_four_noiseless_tables(quiet):
    ds, styles = quiet
    prior = RelationalPrior.draw(ds.catalog, [ds.tables[t] for t in sorted(ds.tables)], 20, 0, 0.2, 0.0)
    for style in styles:
        proto = copy.deepcopy(style)  # the right structure, every number off
        for rule in proto.rules:
            if rule.relation != "edge":
                rule.direction, rule.gap, rule.shift = rule.direction + 8, rule.gap + 0.008, rule.shift - 0.005
        for seat in proto.seats:
            seat.along, seat.inset = seat.along + 0.1, seat.inset + 0.01
        fit = fit_structure(proto, _trials(ds, style.participant, range(4)), prior, 0.0)
        target = ds.tables[next(a.table for a in ds.arrangements if a.participant == style.participant and a.trial == 4)]
        want = np.array([[p.x, p.y] for p in expected_relational(style, target)])
        got, _, _ = place(fit.style, target, oracle_rules(fit.style), None)
        assert got.shape == want.shape and np.abs(got - want).max() < 1e-3, style.template
        assert fit.sigma == pytest.approx(0.003)  # the least noise the fit allows


def test_a_structure_that_cannot_have_made_a_table_is_dropped(quiet):
    ds, styles = quiet
    style = styles[0]
    prior = RelationalPrior.draw(ds.catalog, [ds.tables[t] for t in sorted(ds.tables)], 20, 0, 0.2, 0.0)
    fewer = copy.deepcopy(style)
    plate = next(i for i, r in enumerate(fewer.rules) if r.type == "plate")
    fewer.rules[plate].type = "cup"  # no plate rule left to have made the context's plate
    assert signature(fewer) != signature(style)
    assert fit_structure(fewer, _trials(ds, style.participant, range(4)), prior, 0.0) is None


def test_context_zero_is_the_prior_predictive_one_answer_per_table(rel_dir):
    ds = load_dataset(rel_dir)
    model = RelationalPosterior(ds, _cfg(rel_dir), check_relational(ds))
    episodes = make_episodes(ds, 0, "all", 0)
    answers = {}
    for ep in episodes:
        placements, diag = model.predict(ep)
        table = ds.arrangement(ep.participant, ep.target).table
        assert diag["structure"] == "prior" and len(placements) >= 3
        answers.setdefault(table, placements)
        assert placements == answers[table]  # the same for everyone: the context is empty


def _perturbed(style, rng):
    """The person's structure with other numbers and objects: a prior draw of the same structure."""
    other = copy.deepcopy(style)
    other.participant = "prior-copy"
    for rule in other.rules:
        if rule.relation != "edge":
            rule.direction += rng.normal(0, 10)
            rule.gap, rule.shift = rule.gap + rng.normal(0, 0.008), rule.shift + rng.normal(0, 0.006)
    for seat in other.seats:
        seat.along, seat.inset = seat.along + rng.normal(0, 0.1), max(0.0, seat.inset + rng.normal(0, 0.02))
    return other


def test_with_the_persons_structure_in_the_prior_the_floor_is_near_the_oracle_and_ahead_of_consensus(rel_dir):
    """The fit, weights and minimum-Bayes-risk choice, given a prior that holds each person's structure (the real
    prior holds about four in five: docs/generators.md)."""
    ds = load_dataset(rel_dir)
    _, styles = relational_with_styles(0, {"participants": 12})
    episodes = make_episodes(ds, 4, "all", 0)[::5]
    model = RelationalPosterior(ds, _cfg(rel_dir, samples=40, structures=2), check_relational(ds))
    rng = np.random.default_rng(0)
    model.prior = RelationalPrior(ds.catalog, model.prior.styles + [_perturbed(s, rng) for s in styles])
    scores = {}
    for name in ("posterior", "consensus", "oracle"):
        if name == "posterior":
            placements = [model.predict(ep)[0] for ep in episodes]
        else:
            spec = get_method(name)
            preds = spec.run(spec.config_cls(method=name, dataset=str(rel_dir), out="", seed=0), ds, episodes)
            placements = [p.placements for p in preds]
        gts = [ds.arrangement(e.participant, e.target) for e in episodes]
        scores[name] = float(np.mean([s.set_rmsd for s in score_many(ds.catalog, gts, placements)]))
    assert scores["posterior"] < scores["consensus"] - 0.008, scores
    assert scores["posterior"] < scores["oracle"] + 0.02, scores


def test_predict_end_to_end_and_refusals_name_the_reason(rel_dir, tmp_path, capsys):
    out = tmp_path / "p.jsonl"
    small = ["--set", "prior_styles=80", "--set", "candidates=5", "--set", "samples=10", "--set", "structures=2",
             "--set", "search=1"]
    assert main(["predict", "--config", "posterior", "--set", f"dataset={rel_dir}", "--set", f"out={out}",
                 "--set", "context=2", *small]) == 0
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    assert rows and all(not r["failed"] and len(r["placements"]) >= 3 for r in rows)
    assert {r["diagnostics"]["context"] for r in rows} == {2} and all(r["diagnostics"]["structures"] >= 1 for r in rows)
    capsys.readouterr()
    edited = tmp_path / "edited"
    save_dataset(load_dataset(rel_dir), edited)
    lines = (edited / "arrangements.jsonl").read_text().splitlines()
    row = json.loads(lines[3])
    row["placements"][0]["x"] = round(row["placements"][0]["x"] + 0.01, 6)
    (edited / "arrangements.jsonl").write_text("\n".join(lines[:3] + [json.dumps(row)] + lines[4:]) + "\n")
    with pytest.raises(DegustaError, match=f"participant {row['participant']!r} trial {row['trial']} is not what the "
                                           "generator makes"):
        check_relational(load_dataset(edited))
    meta = json.loads((edited / "meta.json").read_text())
    meta["options"]["noise"] = 9.0
    (edited / "meta.json").write_text(json.dumps(meta))
    assert main(["predict", "--config", "posterior", "--set", f"dataset={edited}", "--set", f"out={tmp_path / 'x.jsonl'}",
                 *small]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "noise" in err and "meta.json" in err and "Traceback" not in err, err
    assert not (tmp_path / "x.jsonl").exists()
