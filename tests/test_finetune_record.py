"""The fine-tune -> hf contract (vlm/record.py): one typed, versioned record, and the train/test leakage guard.

Most tests need no model: the record is read and checked before the model loads, so the runner tests replace
the model loader with one that fails the test (`no_load`). One slow test runs the same guard with the tiny model.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import make_small_dataset

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.finetune.train import write_meta
from degusta_learn.methods import run_predict
from degusta_learn.render.grid import Grid
from degusta_learn.scene import load_dataset, save_dataset, split_participants
from degusta_learn.scene.dataset import dataset_identity
from degusta_learn.vlm.prompt_options import PromptOptions
from degusta_learn.vlm.record import (
    BASE_FILE,
    FINETUNE_FILE,
    FINETUNE_VERSION,
    BaseRecord,
    FinetuneRecord,
    locate_record,
    read_record,
    write_record,
)

PROCESSOR = SimpleNamespace(image_processor=SimpleNamespace(size={"longest_edge": 64}))
# What `write_meta` wrote before the record was versioned (format 1).
OLD_META = {"base_model": "runs/tiny/idefics3", "method": "mogma", "mode": "lora",
            "grid": {"rows": 8, "cols": 8}, "prompt": {"include": ["objects", "context", "target"],
                                                       "compose": ["objects"]},
            "image_size": 64, "render_size": 224, "processor_size": {"longest_edge": 64}}


def _cfg(data: Path, seed: int = 0, **data_keys) -> FinetuneConfig:
    return load_config(FinetuneConfig, data={"dataset": str(data), "seed": seed,
                                             "data": {"render_size": 128, **data_keys}})


@pytest.fixture(scope="module")
def naturalistic_ids(tmp_path_factory) -> Path:
    """199 participants p000..p198, as in the naturalistic default: its split sizes (139 / 20 / 40)."""
    return save_dataset(make_small_dataset(n_participants=199), tmp_path_factory.mktemp("ds") / "data")


@pytest.fixture(scope="module")
def adapter(naturalistic_ids, tmp_path_factory) -> Path:
    """A model folder whose record says: trained with seed 0 on `naturalistic_ids`, images at 128 px."""
    folder = tmp_path_factory.mktemp("model")
    write_meta(folder, _cfg(naturalistic_ids), PROCESSOR)
    return folder


@pytest.fixture
def no_load(monkeypatch):
    """Any model load fails the test: the guard must refuse before a (possibly 2B-parameter) model loads."""
    from degusta_learn.vlm import load

    def refuse(*a, **k):
        raise AssertionError("the model was loaded before the leakage guard ran")

    monkeypatch.setattr(load, "load_vlm", refuse)
    monkeypatch.setattr(load, "load_processor", refuse)


def _predict(data: Path, model: Path, out: Path, *keys: str) -> Path:
    return run_predict(None, ["method=mogma", f"dataset={data}", f"out={out / 'predictions.jsonl'}", "context=2",
                              "backend.name=hf", f"model.name={model}", "backend.device=cpu",
                              "model.dtype=float32", "decoding.max_new_tokens=140", "decoding.n=1",
                              "decoding.temperature=0.0", "decoding.constrained=false", "concurrency=1", "cache='off'",
                              "render_size=128", *keys])


def test_write_meta_and_read_record_round_trip(small_dataset_dir, tmp_path):
    write_meta(tmp_path, _cfg(small_dataset_dir, seed=3, contexts=[2, 4]), PROCESSOR)
    record = read_record(locate_record(None, tmp_path))
    split = split_participants(load_dataset(small_dataset_dir).participants, 3)
    assert isinstance(record, FinetuneRecord) and record.version == FINETUNE_VERSION == 2
    t = record.trained_on
    assert (t.seed, t.contexts, t.dataset) == (3, [2, 4], str(small_dataset_dir))
    assert t.train_participants == split["train"] and t.val_participants == split["val"]
    assert t.fingerprint == dataset_identity(load_dataset(small_dataset_dir))
    assert (record.render_size, record.grid.rows, record.prompt.include) == (128, 8, ["objects", "context", "target"])
    # the one writer writes back exactly what the one reader read
    written = json.loads((tmp_path / FINETUNE_FILE).read_text())
    assert dataclasses.asdict(record) == written
    write_record(tmp_path / "again", record)
    assert (tmp_path / "again" / FINETUNE_FILE).read_text() == (tmp_path / FINETUNE_FILE).read_text()
    # no validation ran: no participant chose the checkpoint
    write_meta(tmp_path, _cfg(small_dataset_dir, val_episodes=0), PROCESSOR)
    assert read_record(tmp_path / FINETUNE_FILE).trained_on.val_participants == []


def test_a_record_of_an_older_version_is_refused_with_what_to_do(tmp_path):
    run = tmp_path / "run"  # a run folder as `degusta train` leaves it: config.yaml, adapter/
    (run / "adapter").mkdir(parents=True)
    (run / "config.yaml").write_text("kind: finetune\n")
    (run / "adapter" / FINETUNE_FILE).write_text(json.dumps(OLD_META))
    with pytest.raises(DegustaError, match=r"adapter/degusta_finetune.json: written by an older degusta \(format 1.*"
                                           r"leakage guard needs\); re-run its training command \(degusta train "
                                           f"--config {run / 'config.yaml'}:"):
        read_record(run / "adapter" / FINETUNE_FILE)
    (run / "adapter" / FINETUNE_FILE).write_text(json.dumps({**OLD_META, "kind": "degusta_finetune", "version": 1}))
    with pytest.raises(DegustaError, match=r"older degusta \(format 1; this one reads format 2\)"):
        read_record(run / "adapter" / FINETUNE_FILE)
    from degusta_learn.prompting.backends.hf import HFBackend

    with pytest.raises(DegustaError, match="older degusta"):  # refused before any model is loaded
        HFBackend(str(tmp_path / "no-model"), adapter=str(run / "adapter"))


@pytest.mark.parametrize("text, message", [
    ('{"kind": "degusta_finetune", "version": 2,', "invalid JSON"),
    ('[1, 2]', "not a degusta record \\(expected a JSON object, got list\\)"),
    ('{"kind": "something_else", "version": 1}', "not a record degusta wrote .*'something_else'"),
    ('{"kind": "degusta_finetune", "version": 99}', "written by a newer degusta \\(format 99.*upgrade"),
    ('{"kind": "degusta_finetune", "version": "2"}', "field 'version': expected an integer"),
    ('{"kind": "degusta_finetune", "version": 2, "method": "mogma"}', "missing required key .*re-run"),
])
def test_corrupt_or_foreign_records_are_one_line_errors_naming_the_file(tmp_path, text, message):
    (tmp_path / FINETUNE_FILE).write_text(text)
    with pytest.raises(DegustaError, match=message) as e:
        read_record(tmp_path / FINETUNE_FILE)
    assert str(tmp_path / FINETUNE_FILE) in str(e.value) and "\n" not in str(e.value)


def test_base_record_round_trip_and_the_unversioned_base_file_still_reads(tmp_path):
    base = BaseRecord(architecture={"image_size": 256}, parameters=10, image_size=256, render_size=256,
                      tokens_per_image=64, grid=Grid(8, 8), prompt=PromptOptions(compose=["objects"]), catalog="embedded default",
                      training={"steps": 0}, validation_curve=[{"step": 1, "val/perception": 0.5}])
    path = write_record(tmp_path, base)
    assert read_record(path) == base and json.loads(path.read_text())["version"] == 1
    unversioned = {k: v for k, v in json.loads(path.read_text()).items() if k != "version"}
    (tmp_path / BASE_FILE).write_text(json.dumps(unversioned))  # what the pretrain export wrote before
    assert read_record(locate_record(tmp_path)) == base
    base.check_prediction("any", {"p000"}, 256)  # a base saw no participant: only the render size counts
    with pytest.raises(DegustaError, match="render_size: .* 256 px .* set render_size=256"):
        base.check_prediction("any", {"p000"}, 448)
    (tmp_path / BASE_FILE).write_text(json.dumps({**unversioned, "render_size": -256}))
    with pytest.raises(DegustaError, match="render_size: expected a value from 16 to 4,096, got -256"):
        read_record(tmp_path / BASE_FILE)  # was echoed back later as "set image_size=-256"


def test_check_prediction_lets_unseen_participants_through(adapter, naturalistic_ids):
    record = read_record(adapter / FINETUNE_FILE)
    split = split_participants(load_dataset(naturalistic_ids).participants, 0)
    record.check_prediction(record.trained_on.fingerprint, set(split["test"]), 128)
    record.check_prediction("another dataset", {"q001", "q002"}, 128)  # other ids: other people


def test_predicting_with_another_split_seed_is_refused(adapter, naturalistic_ids, tmp_path, no_load):
    # 27 of the 40 test participants of seed 1 are training participants of seed 0 (issue 15, item 3)
    with pytest.raises(DegustaError, match=r"^seed: 27 of the 40 participants predicted here are in this model's "
                                           r"training split \(.*: trained with seed 0 on this dataset\); "
                                           r"predict with seed=0 and split=test"):
        _predict(naturalistic_ids, adapter, tmp_path, "seed=1")
    assert not (tmp_path / "predictions.jsonl").exists()


def test_a_dry_run_is_refused_like_the_real_run(adapter, naturalistic_ids, tmp_path, no_load, capsys):
    # `degusta predict --dry-run` must not estimate (and bless) a run that the real run refuses
    with pytest.raises(DegustaError, match=r"^seed: 27 of the 40 participants predicted here"):
        run_predict(None, ["method=mogma", f"dataset={naturalistic_ids}", f"out={tmp_path / 'p.jsonl'}",
                           "context=2", "backend.name=hf", f"model.name={adapter}", "seed=1",
                           "render_size=128"], dry_run=True)
    assert "tokens" not in capsys.readouterr().out and not (tmp_path / "p.jsonl").exists()


def test_predicting_on_the_validation_participants_is_refused(adapter, naturalistic_ids, tmp_path, no_load):
    with pytest.raises(DegustaError, match=r"^seed: 20 of the 20 participants .* validation participants .* "
                                           r"chose these weights \(to choose a decoding on them, predict the run's "
                                           r"last weights, adapter/ or model/, of a run without early stopping\)"):
        _predict(naturalistic_ids, adapter, tmp_path, "split=val")


def test_the_last_weights_may_be_predicted_on_the_validation_participants(naturalistic_ids, tmp_path):
    # choosing a decoding (n, temperature, aggregation) on the participants validation is for: the last weights of
    # a run without early stopping were not chosen on them; the best ones were, and so is every run early stopping
    # ended; a record written before the key existed is taken as chosen
    ds = load_dataset(naturalistic_ids)
    split = split_participants(ds.participants, 0)
    fingerprint = dataset_identity(ds)
    last, best, stopped = tmp_path / "adapter", tmp_path / "best_adapter", tmp_path / "stopped"
    write_meta(last, _cfg(naturalistic_ids), PROCESSOR, chosen_on_val=False)
    write_meta(best, _cfg(naturalistic_ids), PROCESSOR, chosen_on_val=True)
    early = load_config(FinetuneConfig, data={"dataset": str(naturalistic_ids), "data": {"render_size": 128},
                                              "trainer": {"early_stopping_patience": 2}})
    write_meta(stopped, early, PROCESSOR, chosen_on_val=False)
    read_record(last / FINETUNE_FILE).check_prediction(fingerprint, set(split["val"]), 128)
    for folder in (best, stopped):
        with pytest.raises(DegustaError, match=r"^seed: 20 of the 20 participants .* validation participants"):
            read_record(folder / FINETUNE_FILE).check_prediction(fingerprint, set(split["val"]), 128)
    for folder in (last, best, stopped):  # the training participants stay refused whatever chose the weights
        with pytest.raises(DegustaError, match=r"^seed: 139 of the 139 participants .* training split"):
            read_record(folder / FINETUNE_FILE).check_prediction(fingerprint, set(split["train"]), 128)
    older = json.loads((last / FINETUNE_FILE).read_text())
    del older["trained_on"]["chosen_on_val"]
    (last / FINETUNE_FILE).write_text(json.dumps(older))
    with pytest.raises(DegustaError, match=r"validation participants"):
        read_record(last / FINETUNE_FILE).check_prediction(fingerprint, set(split["val"]), 128)


def test_another_dataset_with_the_same_participant_ids_is_refused(adapter, tmp_path, no_load):
    other = save_dataset(make_small_dataset(n_participants=199, seed=1), tmp_path / "other")
    with pytest.raises(DegustaError, match=r"^dataset: 27 of the 40 participant ids predicted here are training "
                                           r"participants of this model .*, trained with seed 0 on another dataset"):
        _predict(other, adapter, tmp_path, "seed=1")


def test_images_are_rendered_at_the_recorded_render_size(adapter, naturalistic_ids, tmp_path, no_load):
    with pytest.raises(DegustaError, match=r"^render_size: this model was trained on images rendered at 128 px "
                                           r"\(data.render_size in .*degusta_finetune.json\), the predict config "
                                           r"renders them at 224 px; set render_size=128"):
        _predict(naturalistic_ids, adapter, tmp_path, "render_size=224")


@pytest.mark.slow
def test_the_guard_with_a_real_tiny_model(tmp_path, one_torch_thread):
    from finetune_support import dataset, tiny_dir

    from degusta_learn.scene import make_episodes, read_predictions, write_episodes

    data = save_dataset(dataset(), tmp_path / "data")
    model = tmp_path / "model"  # a full fine-tune's model/ folder: weights and the record side by side
    shutil.copytree(tiny_dir("idefics3"), model)
    write_meta(model, _cfg(data), PROCESSOR)
    with pytest.raises(DegustaError, match="^seed: 1 of the 2 participants"):  # seed 1: test p004 p008, p008 trained
        _predict(data, model, tmp_path / "refused", "seed=1")
    episodes = tmp_path / "episodes.jsonl"
    write_episodes(episodes, make_episodes(dataset(), 2, "test", 0)[:1])
    out = _predict(data, model, tmp_path / "ok", f"episodes={episodes}", "decoding.constrained=true")
    assert len(read_predictions(out, dataset().catalog)) == 1

