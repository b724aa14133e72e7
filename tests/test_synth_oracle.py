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
