"""Validation of fine-tuning: batched generation, n sampled answers aggregated as predict does, images logged."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from finetune_support import GRID, dataset, examples, load, tiny_dir

from degusta_learn.config import load_config
from degusta_learn.finetune import module as fm
from degusta_learn.finetune.config import DataConfig, FinetuneConfig
from degusta_learn.metrics import score_prediction
from degusta_learn.task.grammar import AnswerGrammar
from degusta_learn.task.prompt import Completion
from degusta_learn.vlm.generate import generate_answers, generate_batch

CONFIGS = Path(__file__).parent.parent / "configs"


@pytest.fixture(scope="module")
def tiny():
    model, processor = load("idefics3")
    model.eval()
    return model, processor


def _module(tiny, **keys) -> fm.FinetuneModule:
    """The tiny config's module with `keys` set: eval.batch_size / eval.log_images, the rest decoding.*."""
    sets = [f"{'eval' if k in ('batch_size', 'log_images') else 'decoding'}.{k}={v}" for k, v in keys.items()]
    cfg = load_config(FinetuneConfig, CONFIGS / "finetune_tiny_cpu.yaml", ["decoding.max_new_tokens=120"] + sets)
    return fm.FinetuneModule(*tiny, cfg, dataset(), GRID, "grid")


def test_batched_validation_equals_one_by_one(tiny):
    """One left-padded `generate` call per batch gives every episode the greedy answer it gets alone."""
    module = _module(tiny)
    exs = [examples(context=k, split="val")[i] for k, i in ((0, 0), (2, 1), (4, 0), (2, 3))]  # unequal lengths
    for constrained in (True, False):
        alone = [module.score(ex, constrained) for ex in exs]
        batched = module.score_batch(exs, constrained)
        assert [r["text"] for r in batched] == [r["text"] for r in alone]
        assert [r["set_rmsd"] for r in batched] == [r["set_rmsd"] for r in alone]
    assert len({r["text"] for r in alone}) > 1  # not one answer whatever the prompt


def test_auto_max_new_tokens_is_the_hf_backends_budget(tiny):
    """`decoding.max_new_tokens: auto` in validation is what predict's hf backend takes for the same model, dataset
    and grammar (`answer_token_budget`), so validation generates what predict writes."""
    from degusta_learn.vlm.generate import answer_token_budget

    module = _module(tiny, max_new_tokens="auto")
    grammar = AnswerGrammar("grid", dataset().catalog, GRID)
    assert module.max_new_tokens() == answer_token_budget(tiny[1].tokenizer, dataset(), "grid", GRID,
                                                          grammar=grammar)["max_new_tokens"]
    assert _module(tiny).max_new_tokens() == 120


def test_generate_batch_keeps_each_answers_noise_stream(tiny):
    """Sampled, constrained: prompt i's answers in a batch are generate_answers(seed=seeds[i])'s."""
    model, processor = tiny
    prompts = [examples(context=k, split="val")[0].prompt for k in (0, 4)]
    grammar = AnswerGrammar("grid", dataset().catalog, GRID)
    alone = [[c.text for c in generate_answers(model, processor, p, n=2, temperature=1.0, max_new_tokens=120,
                                               constrained=True, grammar=grammar, seed=s)]
             for p, s in zip(prompts, (3, 4))]
    batched = generate_batch(model, processor, prompts, n=2, temperature=1.0, max_new_tokens=120, constrained=True,
                             grammar=grammar, seeds=[3, 4])
    assert [[c.text for c in cs] for cs in batched] == alone
    assert alone[0][0] != alone[0][1]


def test_validation_batches_by_eval_batch_size(tiny, monkeypatch):
    """eval.batch_size episodes a generate call (the rest at the epoch's end); null: data.batch_size."""
    calls = []
    real = fm.FinetuneModule.score_batch
    monkeypatch.setattr(fm.FinetuneModule, "score_batch",
                        lambda self, exs, c, idx=None: calls.append(len(exs)) or real(self, exs, c, idx))
    monkeypatch.setattr(fm.FinetuneModule, "log_dict", lambda self, *a, **k: None)
    monkeypatch.setattr(fm, "gather_unique_rows", lambda module, table: table)
    monkeypatch.setattr(fm, "lm_loss", lambda model, inputs: (0.0, 0))
    monkeypatch.setattr(fm.FinetuneModule, "log", lambda self, *a, **k: None)
    module = _module(tiny, batch_size=3, report_unconstrained="false")
    module._val_positions = {}
    module._trainer = SimpleNamespace(is_global_zero=True, sanity_checking=False)  # no Lightning run around it
    exs = list(examples(context=2, split="val"))[:5]
    module.validation_step((None, exs[:2]), 0)
    module.validation_step((None, exs[2:]), 1)
    assert calls == [3]
    module.cfg.eval.log_images = 0
    module.on_validation_epoch_end()
    assert calls == [3, 2]
    assert _module(tiny).cfg.eval.batch_size is None  # data.batch_size then


@pytest.mark.parametrize("aggregation", ["steps", "greedy_votes_pooled"])
def test_sampled_validation_scores_predicts_aggregate(tiny, monkeypatch, tmp_path, aggregation):
    """decoding.n > 1: the validation row scores exactly the plan predict's runner aggregates from the same answers
    (`decoding.aggregation`, the key predict reads; greedy_votes_pooled: one more, greedy generate call)."""
    from degusta_learn.prompting.runner import ZeroShotConfig, ZeroShotRun
    from degusta_learn.scene import save_dataset
    from degusta_learn.vlm.settings import DecodingSettings

    ds = dataset()
    ex = examples(context=2, split="val")[1]
    gt = ds.arrangement(ex.participant, ex.target)
    from degusta_learn.task.answer_format import answer_items, format_answer

    truth = answer_items(list(gt.placements), ds.catalog, "grid", GRID)
    texts = [format_answer(truth, "grid"), format_answer(truth[:-1], "grid"), "not an answer",
             format_answer(truth[1:], "grid")]
    greedy = format_answer(truth[:1], "grid")
    calls = []

    def scripted(model, processor, prompts, n, temperature, max_new_tokens, constrained, grammar, seeds, on_repeat):
        calls.append(dict(n=n, temperature=temperature, seeds=seeds, on_repeat=on_repeat))
        return [[Completion(t, 10, 10, {}) for t in (texts if temperature > 0 else [greedy])] for _ in prompts]

    monkeypatch.setattr("degusta_learn.vlm.generate.generate_batch", scripted)
    module = _module(tiny, n=4, aggregation=aggregation)
    row = module.score_batch([ex], True, [7])[0]
    sampled = {"n": 4, "temperature": 1.0, "seeds": [module.cfg.seed + 7], "on_repeat": "skip"}
    assert calls == [sampled] + ([{**sampled, "n": 1, "temperature": 0.0}] if aggregation.startswith("greedy") else [])

    cfg = ZeroShotConfig(dataset=str(save_dataset(ds, tmp_path / "data")), out=str(tmp_path / "p.jsonl"),
                         method="mogma", cache="off", decoding=DecodingSettings(n=4, aggregation=aggregation))
    ep = next(e for e in examples(context=2, split="val").episodes if e.id == ex.episode)
    answers = texts + ([greedy] if aggregation.startswith("greedy") else [])
    pred = ZeroShotRun(cfg, ds).predict(ep, [Completion(t, 10, 10, {}) for t in answers], {}, cached=0)
    expected = score_prediction(ds.catalog, gt, pred.placements, pred.failed)
    assert row["placements"] == pred.placements and row["parsed"] == 0.75
    assert (row["set_rmsd"], row["acc"], row["n_matched"]) == (expected.set_rmsd, expected.object_accuracy,
                                                                expected.n_matched)
    assert pred.diagnostics["aggregation"] == aggregation
    # the mode length (steps) or the samples' median length (greedy_votes_pooled): a real aggregate, not one answer
    assert len(pred.placements) == len(truth) - 1


def test_decoding_temperature_defaults():
    cfg = FinetuneConfig()
    assert cfg.decoding.n == 1 and cfg.decoding.sampling_temperature == 0.0
    assert cfg.decoding.constrained is True  # null: validation decodes with the local model, constrained
    cfg.decoding.n = 5
    assert cfg.decoding.sampling_temperature == 1.0
    cfg.decoding.temperature = 0.7
    assert cfg.decoding.sampling_temperature == 0.7


def test_greedy_votes_validation_needs_samples():
    from degusta_learn.errors import DegustaError
    from degusta_learn.vlm.settings import DecodingSettings

    with pytest.raises(DegustaError, match="^decoding.aggregation: greedy_votes_pooled lengthens a greedy answer"):
        DecodingSettings(aggregation="greedy_votes_pooled")  # n 1: greedy, nothing to vote
    assert DecodingSettings(aggregation="greedy_votes_pooled", n=5).sampling_temperature == 1.0
    with pytest.raises(DegustaError, match="^decoding.aggregation: greedy_votes_pooled lengthens a greedy answer"):
        DecodingSettings(aggregation="greedy_votes_pooled", n=5, temperature=0.0)


def test_validation_episodes_of_several_context_lengths():
    """`data.val_contexts` (one spelling with the learned model's): the validation episodes of every length listed."""
    from degusta_learn.errors import DegustaError
    from degusta_learn.finetune.data import build_examples

    assert FinetuneConfig().data.val_contexts == [4]
    cfg = FinetuneConfig(data=DataConfig(val_contexts=[0, 2], val_episodes=10_000))
    _, val = build_examples(cfg, dataset(), GRID)
    assert sorted({len(e.context) for e in val.episodes}) == [0, 2]
    for bad in ([], [3], [2, 2]):
        with pytest.raises(DegustaError, match="^data.val_contexts: expected a non-empty list of distinct lengths"):
            DataConfig(val_contexts=bad)


def test_validation_images_png_and_tensorboard(tmp_path):
    """A tiny run writes the first eval.log_images episodes as PNGs and TensorBoard image summaries."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from degusta_learn.methods import run_train
    from degusta_learn.scene import save_dataset

    data = save_dataset(dataset(), tmp_path / "data")
    t0 = time.time()
    run = run_train(CONFIGS / "finetune_tiny_cpu.yaml",
                    [f"dataset={data}", f"model.name={tiny_dir('idefics3')}", f"trainer.run_dir={tmp_path / 'runs'}",
                     "trainer.run_name=t", "trainer.max_steps=1", "trainer.val_check_interval=1",
                     "trainer.progress_bar=false", "data.val_episodes=3", "data.max_train_episodes=2",
                     "data.contexts=[0]", "data.val_contexts=[0]", "data.batch_size=2", "data.render_size=64",
                     "decoding.report_unconstrained=false", "decoding.max_new_tokens=120", "eval.log_images=2",
                     "trainer.loggers=[tensorboard]"])
    assert time.time() - t0 < 60
    pngs = sorted((run / "val_images" / "step_1").glob("*.png"))
    assert len(pngs) == 2 and pngs[0].name.startswith("000_")
    events = EventAccumulator(str(next((run / "tb").rglob("events.out.tfevents.*")).parent),
                              size_guidance={"images": 0})
    events.Reload()
    assert sorted(events.Tags()["images"]) == ["val_images/000", "val_images/001"]
