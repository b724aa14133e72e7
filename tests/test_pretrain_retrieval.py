"""Attention supervision of retrieval (`pretrain/retrieval.py`): the targets say where each answer's
object is among the image tokens, and the loss is what the model's own attention weights give."""

from __future__ import annotations

import pytest
import torch
from test_pretrain_train import CONFIG, _overrides

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.finetune.collate import Collator
from degusta_learn.methods import run_train
from degusta_learn.pretrain.base import BaseArchitecture, build_base
from degusta_learn.pretrain.retrieval import RetrievalLoss, RetrievalTargets
from degusta_learn.pretrain.tasks import PerceptionExamples, TaskMix
from degusta_learn.pretrain.train import PretrainConfig
from degusta_learn.render.grid import DIRECTIONS, Grid
from degusta_learn.scene import default_catalog, default_tables
from degusta_learn.vlm.generate import chat_format

GRID = Grid(8, 8)


@pytest.fixture(scope="module")
def tiny():
    return build_base(BaseArchitecture(vision_channels=[8, 8, 16, 16], vision_stem=8, text_hidden=32, text_layers=2,
                                       text_heads=2, text_kv_heads=1, text_intermediate=64, vocab_size=2048))


def _batch(model, processor, mix: TaskMix, n: int = 3):
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    ds = PerceptionExamples(catalog, tables, GRID, 256, 0, n, mix, block=1)
    examples = [ds[i] for i in range(n)]
    batch = Collator(processor, chat_format(model, processor), 4096, model.config.image_token_id)(examples)
    targets = RetrievalTargets(catalog, processor.tokenizer, model.config.image_token_id, 64, GRID)
    return examples, batch, targets(examples, batch["input_ids"], batch["labels"])


def _cells_of_targets(batch, sup, n: int, image_token_id: int) -> tuple[int, list[str]]:
    """(image index, grid cells) that query n's targets point at, read back from the token positions."""
    where = (batch["input_ids"][sup["retrieval_rows"][n]] == image_token_id).nonzero().flatten().tolist()
    hits = [where.index(p) for p in sup["retrieval_targets"][n].nonzero().flatten().tolist()]
    images = {h // 64 for h in hits}
    assert len(images) == 1, "one query's targets lie in one image"
    return images.pop(), sorted(GRID.cells[h % 64] for h in hits)


@pytest.mark.parametrize("mix", [
    TaskMix(lists=0, describe=1, gomo=0, locate=0, describe_questions=4),
    TaskMix(lists=0, describe=0, gomo=0, locate=1, scenes=[0, 0, 0, 1], objects_sheet=1.0, empty_table=1.0),
    TaskMix(lists=1, describe=0, gomo=0, locate=0, scenes=[0, 1, 0, 0], objects_sheet=1.0, reading_order=1.0),
], ids=["describe", "locate", "list"])
def test_each_answer_cell_and_direction_points_at_the_image_tokens_of_the_object_it_names(tiny, mix):
    model, processor = tiny
    tok = processor.tokenizer
    examples, batch, sup = _batch(model, processor, mix)
    copied = {tok.convert_tokens_to_ids(t) for t in list(GRID.cells) + list(DIRECTIONS)}
    labels = batch["labels"]
    assert sup["retrieval_targets"].shape == (len(sup["retrieval_rows"]), labels.shape[1])
    # every supervised cell or direction of every answer is a query, and nothing else is
    expected = sum(int(labels[b, t + 1]) in copied for b in range(labels.shape[0]) for t in range(labels.shape[1] - 1)
                   if labels[b, t + 1] != -100)
    assert len(sup["retrieval_rows"]) == expected > 0
    for n, (b, t) in enumerate(zip(sup["retrieval_rows"].tolist(), sup["retrieval_queries"].tolist())):
        ex = examples[b]
        image, cells = _cells_of_targets(batch, sup, n, model.config.image_token_id)
        assert image == ex.meta["asked_image"] and ex.meta["cell_labels"][image] is not None
        # the object is the answer item's: the last supervised id at or before the query
        named = next(int(tok.decode([int(labels[b, s])])) for s in range(t, -1, -1)
                     if labels[b, s] != -100 and tok.decode([int(labels[b, s])]).strip().isdigit())
        truth = [item for item in ex.meta["truth"] if item["id"] == named]
        if ex.meta["task"] == "describe":  # follow-up answers are not in meta["truth"]: read the cell labels
            truth = truth or [{"cells": [GRID.cells[k] for k, objs in enumerate(ex.meta["cell_labels"][0])
                                         if any(oid == named for oid, _ in objs)]}]
        assert cells == sorted(truth[0]["cells"])


def test_mark_sheet_questions_have_nothing_to_retrieve(tiny):
    model, processor = tiny
    _, _, sup = _batch(model, processor, TaskMix(lists=0, describe=0, gomo=1, locate=0))
    assert sup["retrieval_rows"].numel() == 0 and sup["retrieval_targets"].shape[0] == 0


def test_loss_is_minus_log_of_the_heads_own_attention_on_the_targets(tiny):
    model, processor = tiny
    examples, batch, sup = _batch(model, processor, TaskMix(lists=0, describe=1, gomo=0, locate=0,
                                                             describe_questions=3), n=2)
    loss_of = RetrievalLoss(model, layer=1, head=1)
    decoder = model.model.language_model
    decoder.config._attn_implementation = "eager"  # the model's own attention weights, as a reference
    try:
        out = model(**{k: v for k, v in batch.items() if k != "labels"}, output_attentions=True)
    finally:
        decoder.config._attn_implementation = "sdpa"
    loss = loss_of.loss(sup["retrieval_rows"], sup["retrieval_queries"], sup["retrieval_targets"])
    weights = out.attentions[1][:, 1]  # layer 1, head 1: (B, T, T)
    mass = torch.stack([weights[b, t][sup["retrieval_targets"][n]].sum()
                        for n, (b, t) in enumerate(zip(sup["retrieval_rows"], sup["retrieval_queries"]))])
    assert torch.allclose(loss, -mass.log().mean(), rtol=1e-4, atol=1e-5)
    loss.backward()  # it shapes that head's queries and keys
    attn = decoder.layers[1].self_attn
    assert attn.q_proj.weight.grad[32 // 2:].abs().sum() > 0 and attn.q_proj.weight.grad[:16].abs().sum() == 0
    assert attn.k_proj.weight.grad.abs().sum() > 0
    model.zero_grad()
    assert loss_of.loss(sup["retrieval_rows"], sup["retrieval_queries"], sup["retrieval_targets"]) is None  # used once


def test_retrieval_settings_are_checked_before_anything_is_written(tmp_path):
    with pytest.raises(DegustaError, match="data.retrieval_layer: layer 4, head 2 is not in the decoder"):
        load_config(PretrainConfig, CONFIG, ["data.retrieval_layer=4"])
    with pytest.raises(DegustaError, match="data.retrieval_head"):
        load_config(PretrainConfig, CONFIG, ["data.retrieval_head=4"])
    with pytest.raises(DegustaError, match="data.retrieval_weight"):
        load_config(PretrainConfig, CONFIG, ["data.retrieval_weight=-1"])
    load_config(PretrainConfig, CONFIG, ["data.retrieval_layer=9", "data.retrieval_weight=0"])  # off: not checked
    small = _overrides(tmp_path, 1) + ["model.vocab_size=600", "data.teacher_steps=0"]
    with pytest.raises(DegustaError, match="data.readout_weight: the tokenizer splits"):  # the shipped readout first
        run_train(CONFIG, small)
    with pytest.raises(DegustaError, match="data.retrieval_weight: the tokenizer splits"):
        run_train(CONFIG, small + ["data.readout_weight=0"])
    assert not (tmp_path / "runs" / "p" / "init").exists()
