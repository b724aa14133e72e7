"""The oracle: reads latent styles from the folder, predicts the noiseless style, clear errors without styles."""

import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_predict
from degusta_learn.metrics import score_many
from degusta_learn.scene import load_dataset, read_episodes, read_predictions
from degusta_learn.synth import expected_arrangement, generate_dataset, simulated_with_styles
from degusta_learn.synth.oracle import predict_oracle


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    return generate_dataset("simulated", tmp_path_factory.mktemp("data") / "simulated")


def test_oracle_from_folder_matches_in_memory_styles(sim_dir, tmp_path):
    out = run_predict(None, ["method=oracle", f"dataset={sim_dir}", f"out={tmp_path / 'p.jsonl'}",
                             f"episodes={sim_dir / 'episodes.jsonl'}"])
    ds = load_dataset(sim_dir)
    episodes = read_episodes(sim_dir / "episodes.jsonl", ds)
    preds = read_predictions(out, ds.catalog, {e.id: e for e in episodes})
    _, styles, _ = simulated_with_styles(0)
    mem = predict_oracle(ds, {s.participant: s for s in styles}, episodes)
    for p in preds:  # what run_predict adds to every record (methods.predict.record_run): the run, not the oracle
        assert p.diagnostics.pop("split") == "train+val+test" and p.diagnostics.pop("choices")["method"] == "oracle"
    assert [p.to_json() for p in preds] == [p.to_json() for p in mem]
    # noiseless: the same style on the same table gives the same arrangement, on any table
    style = styles[0]
    assert expected_arrangement(style, ds.tables[0]) == expected_arrangement(style, ds.tables[0])
    assert expected_arrangement(style, ds.tables[0]) != expected_arrangement(style, ds.tables[1])


def test_oracle_is_near_perfect_on_the_simulated_benchmark(sim_dir):
    ds, styles, episodes = simulated_with_styles(0)
    preds = predict_oracle(ds, {s.participant: s for s in styles}, episodes)
    scores = score_many(ds.catalog, [ds.arrangement(e.participant, e.target) for e in episodes], preds)
    assert all(s.object_accuracy == 1.0 and s.count_error == 0 for s in scores)
    rmsd = [s.rmsd for s in scores]
    assert min(rmsd) > 0.0 and sum(rmsd) / len(rmsd) < 0.04  # small but not zero: the noise is left


def test_oracle_needs_latent_styles(small_dataset_dir, sim_dir, tmp_path):
    with pytest.raises(DegustaError, match="oracle needs a synthetic dataset with latent styles"):
        run_predict(None, ["method=oracle", f"dataset={small_dataset_dir}", f"out={tmp_path / 'p.jsonl'}"])
    assert not (tmp_path / "p.jsonl").exists()
    with pytest.raises(DegustaError, match="latent_styles.json: no latent style for participant 'p0"):
        run_predict(None, ["method=oracle", f"dataset={small_dataset_dir}", f"out={tmp_path / 'p.jsonl'}",
                           f"styles={sim_dir / 'latent_styles.json'}"])


BAD_STYLES = [  # (edit of the first style, what the one-line error names)
    (lambda s: s["settings"][0].update(u="abc"), "field 'settings[0].u': expected a finite number"),
    (lambda s: s.update(settings=[]), "field 'settings': expected a non-empty list"),
    (lambda s: s["slots"][0].update(setting=7), "field 'slots[0].setting': 7 is not a setting index"),
    (lambda s: s.update(scale=1e308), "field 'scale': 1e+308 is outside"),
    (lambda s: s["slots"][0].update(p_include=True), "field 'slots[0].p_include': expected a finite number"),
    (lambda s: s.update(noise=5), "field 'noise': expected an object"),
    (lambda s: s.update(colour=["red"]), "unknown field 'colour'"),
    (lambda s: s.pop("slots"), "missing field 'slots'"),
    (lambda s: s["slots"][0].update(object=99999), "slots[0]: object 99999 is not a"),
]


@pytest.mark.parametrize("edit, message", BAD_STYLES)
def test_a_malformed_latent_style_is_one_line_naming_the_field(sim_dir, tmp_path, capsys, edit, message):
    """These were tracebacks deep in the layout (TypeError, ZeroDivisionError, IndexError) or an oracle that
    wrote predictions evaluate refuses (object 99999, coordinates of 1e307); `data validate` passed them."""
    import json
    import shutil

    from degusta_learn.cli import main as cli_main

    data = tmp_path / "data"
    shutil.copytree(sim_dir, data)
    styles = json.loads((data / "latent_styles.json").read_text())
    edit(styles[0])
    (data / "latent_styles.json").write_text(json.dumps(styles))
    for argv in (["predict", "--config", "oracle", "--set", f"dataset={data}", "--set",
                  f"out={tmp_path / 'p.jsonl'}", "--set", f"episodes={data / 'episodes.jsonl'}"],
                 ["data", "validate", str(data)]):
        assert cli_main(argv) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        assert "latent_styles.json" in err and message in err, err
    assert not (tmp_path / "p.jsonl").exists()


def test_data_validate_counts_the_latent_styles(sim_dir, capsys):
    from degusta_learn.cli import main as cli_main

    assert cli_main(["data", "validate", str(sim_dir)]) == 0
    assert "latent styles" in capsys.readouterr().out
