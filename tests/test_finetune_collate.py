"""Label masking: only answer + end-of-turn are supervised; no double BOS; never truncated; no NaN."""

from __future__ import annotations

import math

import pytest
import torch
from finetune_support import GRID, dataset, examples, load

from degusta_learn.errors import DegustaError
from degusta_learn.finetune.collate import IGNORE, Collator, supervised_text
from degusta_learn.finetune.loss import lm_loss
from degusta_learn.task.answers import parse_answer
from degusta_learn.vlm.inputs import ChatFormat
from degusta_learn.vlm.prompt_options import PromptOptions

END = {"idefics3": "<end_of_utterance>", "qwen2vl": "<|im_end|>"}
LEAD = {"idefics3": " ", "qwen2vl": ""}  # what each chat template puts between "Assistant:" and the answer


@pytest.fixture(scope="module", params=["idefics3", "qwen2vl"])
def setup(request):
    model, processor = load(request.param)
    fmt = ChatFormat(processor, model.generation_config)
    return request.param, model, processor, fmt


def test_supervised_tokens_are_exactly_the_answer_and_end_token(setup):
    kind, model, processor, fmt = setup
    exs = examples(context=2)
    batch = Collator(processor, fmt, 4096, model.config.image_token_id)([exs[0], exs[3]])
    tok = processor.tokenizer
    for row, ex in enumerate([exs[0], exs[3]]):
        assert supervised_text(tok, batch, row) == LEAD[kind] + ex.answer + END[kind]
        labels, ids = batch["labels"][row], batch["input_ids"][row]
        sup = labels != IGNORE
        # Supervised labels equal the inputs at the same positions (unshifted: the loss shifts once) ...
        assert torch.equal(labels[sup], ids[sup])
        # ... and form one contiguous block right after the prompt, ending with the end-of-turn token.
        pos = sup.nonzero().flatten()
        assert pos.max() - pos.min() + 1 == len(pos)
        assert int(ids[pos.max()]) == tok.convert_tokens_to_ids(END[kind])
        assert int(ids[pos.max()]) in fmt.stop_ids
        # Image, padding and prompt tokens are never supervised.
        assert not sup[ids == model.config.image_token_id].any()
        assert not sup[batch["attention_mask"][row] == 0].any()
        # The answer parses back to the ground truth items.
        items = parse_answer(ex.answer, "grid", dataset().catalog, GRID)
        target = dataset().arrangement(exs.episodes[row * 3].participant, exs.episodes[row * 3].target)
        assert [it.id for it in items] == [p.object for p in target.placements]


def test_no_double_bos(setup):
    kind, model, processor, fmt = setup
    batch = Collator(processor, fmt, 4096, model.config.image_token_id)([examples(context=0)[0]])
    bos = processor.tokenizer.bos_token_id
    if bos is not None:
        assert int((batch["input_ids"][0] == bos).sum()) == 1
        assert int(batch["input_ids"][0, 0]) == bos
    else:  # Qwen: no BOS at all, the template starts with <|im_start|>
        assert processor.tokenizer.convert_ids_to_tokens(int(batch["input_ids"][0, 0])) == "<|im_start|>"


def test_image_tokens_per_example_match_the_images(setup):
    kind, model, processor, fmt = setup
    from degusta_learn.vlm.inputs import tokens_per_image

    per_image = tokens_per_image(processor, fmt, model.config.image_token_id)
    for ctx, opts, n_images in [(2, PromptOptions(compose=["objects"]), 1 + 2 + 1),
                                (2, PromptOptions(), 5 + 2 + 1),
                                (4, PromptOptions(compose=["all"]), 1),
                                (2, PromptOptions(include=["target"]), 1)]:
        ex = examples(context=ctx, options=opts)[0]
        assert len(ex.prompt.images) == n_images
        batch = Collator(processor, fmt, 8192, model.config.image_token_id)([ex])
        assert int((batch["input_ids"] == model.config.image_token_id).sum()) == n_images * per_image
        with torch.no_grad():
            loss, n = lm_loss(model, batch)
        completion = processor.tokenizer(fmt.completion_text(ex.answer), add_special_tokens=False)["input_ids"]
        assert math.isfinite(float(loss)) and n == len(completion)


def test_over_budget_is_an_error_naming_the_key_never_truncation(setup):
    kind, model, processor, fmt = setup
    ex = examples(context=4, options=PromptOptions())[0]
    with pytest.raises(DegustaError, match=r"data.max_length: episode .* needs \d+ tokens \(\d+ image tokens"):
        Collator(processor, fmt, 300, model.config.image_token_id)([ex])


def test_zero_supervised_tokens_give_a_finite_zero_loss(setup):
    kind, model, processor, fmt = setup
    batch = Collator(processor, fmt, 4096, model.config.image_token_id)([examples(context=0)[0]])
    batch["labels"][:] = IGNORE
    loss, n = lm_loss(model, batch)
    assert n == 0 and loss.item() == 0.0 and not math.isnan(loss.item())
    loss.backward()  # still part of the graph


def test_loss_matches_the_models_own_loss(setup):
    """lm_loss (LM head on supervised positions only) equals transformers' loss on full logits."""
    kind, model, processor, fmt = setup
    exs = examples(context=2)
    batch = Collator(processor, fmt, 4096, model.config.image_token_id)([exs[0], exs[1]])
    with torch.no_grad():
        ours, n = lm_loss(model, batch)
        reference = model(**batch).loss
    assert n > 0 and torch.allclose(ours, reference, atol=1e-5)


def test_follow_up_turns_supervise_each_answer_and_none_of_the_questions(setup):
    import dataclasses

    kind, model, processor, fmt = setup
    ex = examples(context=0)[0]
    follow = dataclasses.replace(ex, followups=(("And the second?", "[]"), ("The third?", ex.answer)))
    collate = Collator(processor, fmt, 8192, model.config.image_token_id)
    batch = collate([follow, ex])
    tok = processor.tokenizer
    lead, end = LEAD[kind], END[kind]
    assert supervised_text(tok, batch, 0) == lead + ex.answer + end + lead + "[]" + end + lead + ex.answer + end
    assert supervised_text(tok, batch, 1) == lead + ex.answer + end  # the plain example is unchanged
    ids = batch["input_ids"][0][batch["attention_mask"][0].bool()]
    text = tok.decode(ids, skip_special_tokens=False)
    # the conversation is the one the chat template renders, questions included (as unsupervised tokens)
    messages = [{"role": "user", "content": [{"type": "text", "text": "x"}]}]
    assert text.count("And the second?") == 1 and text.index("And the second?") < text.index("The third?")
    assert "And the second?" not in supervised_text(tok, batch, 0)
    full = processor.apply_chat_template(messages + [
        {"role": "assistant", "content": [{"type": "text", "text": "A"}]},
        {"role": "user", "content": [{"type": "text", "text": "And the second?"}]}], add_generation_prompt=True,
        tokenize=False)
    assert full.endswith(fmt.followup_text("And the second?"))
    counts = collate.token_counts([follow, ex])
    assert counts[0]["answer"] > 2 * counts[1]["answer"] and counts[0]["total"] == int(batch["attention_mask"][0].sum())


def test_list_end_weight_weighs_the_tokens_that_set_the_lists_length(setup):
    """data.list_end_weight: the tokens going on to another item or closing the list (never a cell list's "]")
    carry the weight; the loss is the weighted mean, by hand; weight 1 is the plain loss and adds no key."""
    import torch.nn.functional as F

    from degusta_learn.finetune.collate import list_decisions

    kind, model, processor, fmt = setup
    tok = processor.tokenizer
    exs = examples(context=2)
    ids = tok(exs[0].answer, add_special_tokens=False)["input_ids"]
    marks = list_decisions(tok, ids)
    n_items = len(parse_answer(exs[0].answer, "grid", dataset().catalog, GRID))
    assert len(marks) == n_items  # a "," after every item but the last, and the closing "]"
    texts = [tok.decode([ids[i]]) for i in marks]
    assert all("," in t for t in texts[:-1]) and "]" in texts[-1] and marks[-1] == max(
        i for i, t in enumerate(ids) if "]" in tok.decode([t]))
    assert list_decisions(tok, tok("Sure: [", add_special_tokens=False)["input_ids"]) == []

    plain = Collator(processor, fmt, 4096, model.config.image_token_id)
    heavy = Collator(processor, fmt, 4096, model.config.image_token_id, list_end_weight=5.0)
    b1, b5 = plain([exs[0], exs[1]]), heavy([exs[0], exs[1]])
    assert "label_weights" not in b1 and "label_weights" in b5
    w = b5["label_weights"]
    assert set(w[b5["labels"] == IGNORE].tolist()) == {0.0} and set(w[b5["labels"] != IGNORE].tolist()) == {1.0, 5.0}
    with torch.no_grad():
        base, n = lm_loss(model, b1)
        weighted, n5 = lm_loss(model, b5)
        logits = model(**{k: v for k, v in b1.items() if k != "labels"}).logits[:, :-1]
        target = b1["labels"][:, 1:]
        sel = target != IGNORE
        ce = F.cross_entropy(logits[sel].float(), target[sel], reduction="none")
        ws = w[:, 1:][sel]
    assert n == n5 and not torch.allclose(base, weighted)
    assert torch.allclose(weighted, (ce * ws).sum() / ws.sum(), atol=1e-5)


@pytest.mark.parametrize("value", [-1.0, "heavy", 1e6])
def test_list_end_weight_out_of_range_names_the_key(small_dataset_dir, value):
    from degusta_learn.config import load_config
    from degusta_learn.finetune.config import FinetuneConfig

    with pytest.raises(DegustaError, match="data.list_end_weight"):
        load_config(FinetuneConfig, data={"dataset": str(small_dataset_dir), "data": {"list_end_weight": value}})
