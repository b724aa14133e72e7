"""Fine-tuning epoch features: contexts resampled per epoch, learning rates per part, length-grouped batches."""

from __future__ import annotations

import dataclasses

import finetune_support as fs
import pytest
import torch
from torch.utils.data import DataLoader

from degusta_learn.finetune.config import (
    DataConfig,
    FinetuneConfig,
    FinetuneOptimConfig,
    FinetuneTrainerConfig,
)
from degusta_learn.finetune.data import TrainSampler
from degusta_learn.finetune.train import build_examples, train_sampler
from degusta_learn.scene import participants_in


def _config(resample: bool = True, seed: int = 0, contexts=(2, 4), train_seed: int = 0) -> FinetuneConfig:
    return FinetuneConfig(seed=seed, data=DataConfig(contexts=list(contexts), val_episodes=6, render_size=64,
                                                     resample_contexts=resample, compose=["objects"]),
                          trainer=FinetuneTrainerConfig(seed=train_seed))


def _examples(resample: bool = True, seed: int = 0, contexts=(2, 4), train_seed: int = 0):
    return build_examples(_config(resample, seed, contexts, train_seed), fs.dataset(), fs.GRID)


def test_contexts_change_between_epochs_and_repeat_with_the_seed():
    train, val = _examples()
    k2 = [i for i, e in enumerate(train.episodes) if len(e.context) == 2]
    assert any(train.episode(i, 0).context != train.episode(i, 1).context for i in k2)
    again, _ = _examples()
    assert [again.episode(i, 3).context for i in k2] == [train.episode(i, 3).context for i in k2]
    other, _ = _examples(seed=1)  # another seed draws others (and splits participants otherwise)
    assert [other.episode(i, 1) for i in range(len(other))] != [train.episode(i, 1) for i in range(len(train))]
    fixed, _ = _examples(resample=False)
    assert all(fixed.episode(i, 0) == fixed.episode(i, 5) == fixed.episodes[i] for i in range(len(fixed)))
    assert all(val.episode(i, 0) == val.episode(i, 7) for i in range(len(val)))  # validation never changes


def test_a_training_seed_keeps_the_split_and_changes_order_and_contexts():
    train, val = _examples()
    other, other_val = _examples(train_seed=1)  # trainer.seed: a second training run on the same split
    assert other.episodes == train.episodes and other_val.episodes == val.episodes
    assert [other.episode(i, 1) for i in range(len(other))] != [train.episode(i, 1) for i in range(len(train))]
    orders = [[i for _, i in train_sampler(_config(train_seed=s), data, None)(1, 0)]
              for s, data in ((0, train), (1, other))]
    assert sorted(orders[0]) == sorted(orders[1]) and orders[0] != orders[1]


def test_resampled_contexts_stay_with_their_train_participant():
    train, _ = _examples()
    ds = fs.dataset()
    allowed = set(participants_in(ds, "train", 0))
    trials = {p: {a.trial for a in arrs} for p, arrs in ds.by_participant().items()}
    for epoch in range(4):
        for i in range(len(train)):
            ep = train.episode(i, epoch)
            assert ep.participant in allowed
            assert len(ep.context) == len(train.episodes[i].context) == len(set(ep.context))
            assert set(ep.context) <= trials[ep.participant] - {ep.target}
            assert list(ep.context) == sorted(ep.context)


def test_the_sampler_carries_the_epoch_to_the_dataset():
    train, _ = _examples()
    sampler = TrainSampler(train, seed=0)
    sampler.set_epoch(2)  # what Lightning does at each epoch start
    keys = list(sampler)
    assert sorted(i for _, i in keys) == list(range(len(train))) and {e for e, _ in keys} == {2}
    loader = DataLoader(train, batch_size=2, sampler=sampler, collate_fn=lambda xs: xs)
    first = next(iter(loader))[0]
    episode = train.episode(keys[0][1], 2)
    assert first.episode == episode.id
    assert first.prompt.text == train.prompt(keys[0][1], 2).text
    sampler.set_epoch(3)
    assert [i for _, i in sampler] != [i for _, i in keys]  # a new order each epoch


def test_sampler_shards_ranks_without_overlap():
    train, _ = _examples()
    n = len(train)
    ranks = [list(TrainSampler(train, 0, num_replicas=3, rank=r, lengths=list(range(n)), batch_size=2))
             for r in range(3)]
    assert all(len(r) == -(-n // 3) for r in ranks)
    seen = [i for r in ranks for _, i in r]
    assert set(seen) == set(range(n)) and len(seen) - n == len(seen) - len(set(seen))  # repeats only as padding


def _padding(lengths, order, batch_size):
    pad = total = 0
    for start in range(0, len(order), batch_size):
        batch = [lengths[i] for _, i in order[start:start + batch_size]]
        pad += max(batch) * len(batch) - sum(batch)
        total += max(batch) * len(batch)
    return pad / total


def test_length_grouped_batches_pad_less_than_random_ones():
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.token_count import count_tokens
    from degusta_learn.vlm.inputs import ChatFormat

    model, processor = fs.load("idefics3")
    collator = Collator(processor, ChatFormat(processor, model.generation_config), 8192, model.config.image_token_id)
    train, _ = _examples(contexts=(0, 2, 4))
    lengths = [c["total"] for c in count_tokens(train, collator)]
    assert max(lengths) > 1.5 * min(lengths)
    cfg = _config(contexts=(0, 2, 4))
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, group_by_length=True))
    assert train_sampler(cfg, train, collator)(1, 0).lengths == lengths  # the run's own count (token_budget)
    grouped = TrainSampler(train, 0, lengths=lengths, batch_size=4)
    plain = TrainSampler(train, 0)
    for epoch in range(3):
        grouped.set_epoch(epoch)
        plain.set_epoch(epoch)
        assert _padding(lengths, list(grouped), 4) < 0.5 * _padding(lengths, list(plain), 4)
    assert sorted(i for _, i in grouped) == list(range(len(train)))


def _groups(lora_cfg, optim):
    from degusta_learn.finetune.lora import apply_lora
    from degusta_learn.finetune.module import param_groups

    model, _ = fs.load("idefics3")
    holder = torch.nn.Module()
    holder.model = apply_lora(model, lora_cfg)
    return {g["name"]: g for g in param_groups(holder, optim)}, holder


@pytest.mark.parametrize("mode", ["lora", "full"])
def test_vision_and_connector_get_their_own_learning_rates(mode):
    from degusta_learn.finetune.lora import LoraConfig

    lora_cfg = LoraConfig(mode=mode, vision_targets=["q_proj", "fc1"] if mode == "lora" else [],
                          connector=mode == "lora")
    groups, holder = _groups(lora_cfg, FinetuneOptimConfig(lr=1e-3, vision_lr=1e-5, connector_lr=3e-4))
    assert {k: g["lr"] for k, g in groups.items()} == {"language": 1e-3, "vision": 1e-5, "connector": 3e-4}
    names = {id(p): n for n, p in holder.named_parameters()}
    assert all(".vision_model." in names[id(p)] for p in groups["vision"]["params"])
    assert all(".connector." in names[id(p)] for p in groups["connector"]["params"])
    assert all(".vision_model." not in names[id(p)] and ".connector." not in names[id(p)]
               for p in groups["language"]["params"])
    trained = [p for p in holder.parameters() if p.requires_grad]
    assert sum(len(g["params"]) for g in groups.values()) == len(trained)
    if mode == "lora":
        assert all("lora_" in names[id(p)] for g in groups.values() for p in g["params"])
    same, _ = _groups(lora_cfg, FinetuneOptimConfig(lr=2e-4))  # null: optim.lr
    assert {g["lr"] for g in same.values()} == {2e-4}


def test_language_only_lora_has_one_group_and_bad_rates_are_refused():
    from degusta_learn.errors import DegustaError
    from degusta_learn.finetune.lora import LoraConfig

    groups, _ = _groups(LoraConfig(), FinetuneOptimConfig(lr=1e-3, vision_lr=1e-5))
    assert list(groups) == ["language"]
    with pytest.raises(DegustaError, match="optim.connector_lr"):
        FinetuneOptimConfig(connector_lr=0.0)


def test_the_budget_check_fits_the_heaviest_context_any_epoch_could_draw():
    """With contexts redrawn each epoch, `check_budget` collates the item whose context could be heaviest,
    shown the participant's other trials with the most objects (not just epoch 0's draw)."""
    from degusta_learn.finetune.train import check_budget

    train, _ = _examples(contexts=(2,))
    ds = fs.dataset()
    seen = []
    check_budget(train, lambda batch: seen.extend(batch))
    (ex,) = seen
    i = next(j for j, e in enumerate(train.episodes) if e.participant == ex.participant and e.target == ex.target)
    others = sorted((a for a in ds.by_participant()[ex.participant] if a.trial != ex.target),
                    key=lambda a: -len(a.placements))
    heaviest = train.heaviest(i)
    assert sum(len(ds.arrangement(ex.participant, t).placements) for t in heaviest.context) == \
        sum(len(a.placements) for a in others[:2])
    assert ex.episode == heaviest.id and ex.prompt.text == train.example(i, heaviest).prompt.text

    def total(ep) -> int:
        return sum(len(ds.arrangement(ep.participant, t).placements) for t in (*ep.context, ep.target))

    assert all(total(train.episode(j, e)) <= total(heaviest) for j in range(len(train)) for e in range(3))
