"""The relational oracle, reached by `method: oracle` through meta.json "generator": it matches the in-memory rules,
beats consensus and scores about the generator's own noise; other generators' data and malformed styles are
refused in one line; the posterior floor refuses data of a generator it has no prior for, naming it."""

import json
import shutil

import numpy as np
import pytest
from benchmark_support import load_benchmark

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.methods import get_method, run_predict
from degusta_learn.metrics import paired_bootstrap, score_many
from degusta_learn.scene import load_dataset, make_episodes, read_predictions
from degusta_learn.synth import generate_dataset, relational_with_styles
from degusta_learn.synth.relational_oracle import predict_relational_oracle
from degusta_learn.synth.relational_realize import sample_relational, taste_weights


@pytest.fixture(scope="module")
def rel_dir(tmp_path_factory):
    return generate_dataset("relational", tmp_path_factory.mktemp("data") / "relational")


def _run(name, ds, episodes):
    spec = get_method(name)
    return spec.run(spec.config_cls(method=name, dataset=str(ds.root), out="", seed=0), ds, episodes)


def test_method_oracle_dispatches_on_the_generator_and_matches_the_rules(rel_dir, tmp_path):
    out = run_predict(None, ["method=oracle", f"dataset={rel_dir}", f"out={tmp_path / 'p.jsonl'}"])
    ds = load_dataset(rel_dir)
    episodes = make_episodes(ds, 4, "test", 0)
    preds = read_predictions(out, ds.catalog, {e.id: e for e in episodes})
    _, styles = relational_with_styles(0)
    mem = predict_relational_oracle(ds, {s.participant: s for s in styles}, episodes)
    for p in preds:
        p.diagnostics.pop("split"), p.diagnostics.pop("choices")
    assert [p.to_json() for p in preds] == [p.to_json() for p in mem]
    assert {p.diagnostics["template"].split("/")[0] for p in preds} <= {
        "classic", "left_handed", "compact", "on_plate", "stacked", "above"}


def test_the_oracle_beats_consensus_and_scores_its_own_noise_level(rel_dir):
    ds = load_dataset(rel_dir)
    episodes = make_episodes(ds, 4, "test", 0)
    gts = [ds.arrangement(e.participant, e.target) for e in episodes]
    oracle = [s.set_rmsd for s in score_many(ds.catalog, gts, _run("oracle", ds, episodes))]
    consensus = [s.set_rmsd for s in score_many(ds.catalog, gts, _run("consensus", ds, episodes))]
    test = paired_bootstrap(consensus, oracle, clusters=[e.participant for e in episodes])
    assert test["diff"] > 0.005 and test["p_value"] < 0.05  # the ceiling is clearly ahead
    # its error is the persons' own noise: the same oracle against fresh trials of the same people
    _, styles = relational_with_styles(0)
    by = {s.participant: s for s in styles}
    rng = np.random.default_rng(7)
    preds = _run("oracle", ds, episodes)
    fresh = []
    for _ in range(3):
        trials = [sample_relational(by[e.participant], ds.tables[gt.table], ds.catalog, rng,
                                    taste_weights(by[e.participant], ds.catalog)) for e, gt in zip(episodes, gts)]
        fresh_gts = [type(gt)(gt.participant, gt.trial, gt.table, tuple(t)) for gt, t in zip(gts, trials)]
        fresh += [s.set_rmsd for s in score_many(ds.catalog, fresh_gts, preds)]
    assert np.mean(oracle) == pytest.approx(np.mean(fresh), rel=0.2)


def test_the_oracle_refuses_data_of_a_generator_it_does_not_know(rel_dir, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(rel_dir, data)
    meta = json.loads((data / "meta.json").read_text())
    meta["generator"] = "my_lab_generator"
    (data / "meta.json").write_text(json.dumps(meta))
    assert main(["predict", "--config", "oracle", "--set", f"dataset={data}", "--set", f"out={tmp_path / 'p.jsonl'}"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "'my_lab_generator', which has no oracle" in err, err
    assert "degusta_learn.synth.relational" in err and not (tmp_path / "p.jsonl").exists()


def test_the_bare_generator_name_is_understood_too(rel_dir, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(rel_dir, data)
    meta = json.loads((data / "meta.json").read_text())
    meta["generator"] = "relational"
    (data / "meta.json").write_text(json.dumps(meta))
    ds = load_dataset(data)
    assert len(_run("oracle", ds, make_episodes(ds, 4, "test", 0))) == 200


BAD_RULES = [  # (edit of the first style, what the one-line error names)
    (lambda s: s["rules"][1].update(ref=9), "field 'rules[1].ref': 9 is not an earlier rule"),
    (lambda s: s["rules"][0].update(relation="beside"), "field 'rules[0].ref': -1 is not an earlier rule"),
    (lambda s: s["rules"][1].update(relation="hover"), "field 'rules[1].relation': 'hover' is not one of"),
    (lambda s: s["rules"][0].update(p_include=0.5), "field 'rules[0].relation': 'edge' places an always-set plate"),
    (lambda s: s["seats"][0].update(side="under"), "field 'seats[0].side': 'under' is not one of"),
    (lambda s: s["rules"][1].update(gap=1e9), "field 'rules[1].gap': 1000000000.0 is outside"),
    (lambda s: s["rules"][1].update(seat=3), "field 'rules[1].seat': 3 is not a seat index"),
    (lambda s: s["noise"].update(turn=-1), "field 'noise.turn': -1 is outside"),
    (lambda s: s.update(slots=[]), "unknown field 'slots'"),
    (lambda s: s["rules"][1].update(object=0), "rules[1]: object 0 is not a"),
]


@pytest.mark.parametrize("edit, message", BAD_RULES)
def test_a_malformed_relational_style_is_one_line_naming_the_field(rel_dir, tmp_path, capsys, edit, message):
    data = tmp_path / "data"
    shutil.copytree(rel_dir, data)
    styles = json.loads((data / "latent_styles.json").read_text())
    edit(styles[0])
    (data / "latent_styles.json").write_text(json.dumps(styles))
    for argv in (["predict", "--config", "oracle", "--set", f"dataset={data}", "--set", f"out={tmp_path / 'p.jsonl'}"],
                 ["data", "validate", str(data)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        assert "latent_styles.json" in err and message in err, err
    assert not (tmp_path / "p.jsonl").exists()


def test_the_posterior_floor_refuses_a_generator_it_has_no_prior_for(tmp_path, capsys):
    sim = generate_dataset("simulated", tmp_path / "simulated")
    assert main(["predict", "--config", "posterior", "--set", f"dataset={sim}",
                 "--set", f"out={tmp_path / 'p.jsonl'}"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert "posterior needs data made by `degusta data generate naturalistic` or `degusta data generate relational`" in err
    assert "'degusta_learn.synth.simulated'" in err and not (tmp_path / "p.jsonl").exists()


def test_the_benchmarks_rank_statistics():
    bench = load_benchmark("bench_generators")
    rho, tau = bench.rank_correlations(np.array([1.0, 2.0, 3.0, 4.0]), np.array([1.0, 3.0, 2.0, 4.0]))
    assert rho == pytest.approx(0.8) and tau == pytest.approx(2 / 3)
    # two generators, 3 methods x 4 participants: the bootstrap keeps a perfect agreement perfect
    sums = np.array([[1.0, 1.0, 1.0, 1.0], [2.0, 2.1, 1.9, 2.0], [3.0, 3.0, 3.2, 2.9]])
    counts = np.ones(4)
    boot = bench.bootstrap_correlations([(sums, counts), (sums * 2, counts)], 50, seed=0)
    assert boot.shape == (50, 2) and np.allclose(boot, 1.0)
    with pytest.raises(DegustaError):
        generate_dataset("relational", "unused", options={"participants": 1})
