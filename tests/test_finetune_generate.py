"""Constrained decoding always parses (random weights!); the grammar accepts exactly valid answers;
a tiny model overfits a few examples until its generated answer equals the target."""

from __future__ import annotations

import random

import pytest
import torch
from finetune_support import GRID, dataset, examples, load

from degusta_learn.errors import DegustaError
from degusta_learn.task.answer_format import format_answer
from degusta_learn.task.answers import AnswerItem, AnswerParseError, parse_answer
from degusta_learn.task.grammar import AnswerGrammar


def test_grammar_accepts_canonical_answers_and_rejects_invalid_ones():
    cat = dataset().catalog
    g = AnswerGrammar("grid", cat, GRID)
    ok = format_answer([AnswerItem("plate", 80, cells=["D4", "D5"], direction="N"),
                        AnswerItem("cup", 3, cells=["A1"], direction="NW")], "grid")
    assert g.is_complete(g.feed(g.start(), ok))
    assert g.is_complete(g.feed(g.start(), " " + ok))
    for bad in ["[{'type': 'plate', 'id': 3",                     # a cup id for a plate
                "[{'type': 'bowl'",                               # unknown type
                "[{'type': 'cup', 'id': 3, 'position': ['I1'",    # off the 8x8 grid
                "[{'type': 'cup', 'id': 3, 'position': ['A1', 'A1'",  # a cell twice
                "[{'type': 'cup', 'id': 3, 'position': ['A1'], 'cardinal_direction': 'NNE'",
                "[]", "plate"]:
        assert g.feed(g.start(), bad) is None, bad
    u = AnswerGrammar("unmarked", cat)
    ok_u = format_answer([AnswerItem("plate", 80, position=(0.5, 1.0), rotation=90.0)], "unmarked")
    assert u.is_complete(u.feed(u.start(), ok_u))
    assert u.feed(u.start(), "[{'type': 'plate', 'id': 80, 'position': [1.5") is None


@pytest.mark.parametrize("kind", ["grid", "unmarked"])
def test_every_text_the_grammar_allows_parses(kind):
    """Random walks through the automaton (closing mode after a while) always end in a parseable answer."""
    cat = dataset().catalog
    g = AnswerGrammar(kind, cat, GRID)
    alphabet = sorted(set("[]{}',: \n.0123456789_abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"))
    rng = random.Random(0)
    for _ in range(30):
        state, text = g.start(), ""
        for step in range(2000):
            if g.is_complete(state):
                break
            options = [c for c in alphabet if g.step(state, c, closing=step > 150) is not None]
            assert options, text
            c = rng.choice(options)
            state, text = g.step(state, c, closing=step > 150), text + c
        assert g.is_complete(state)
        parse_answer(text, kind, cat, GRID)  # raises AnswerParseError if not


@pytest.mark.parametrize("kind", ["idefics3", "qwen2vl"])
def test_constrained_decoding_always_parses_with_random_weights(kind):
    from degusta_learn.vlm.generate import generate_answers

    model, processor = load(kind)
    cat = dataset().catalog
    prompt = examples(context=2)[0].prompt
    grammar = AnswerGrammar("grid", cat, GRID)
    free = generate_answers(model, processor, prompt, n=2, temperature=1.0, max_new_tokens=120, seed=0)
    done = generate_answers(model, processor, prompt, n=4, temperature=1.5, max_new_tokens=150,
                            constrained=True, grammar=grammar, seed=0)
    for c in done:
        assert parse_answer(c.text, "grid", cat, GRID)
        assert c.output_tokens <= 150
    with pytest.raises(AnswerParseError):  # a random model does not produce answers by itself
        for c in free:
            parse_answer(c.text, "grid", cat, GRID)
    with pytest.raises(DegustaError, match="max_new_tokens"):  # too small a budget to close an answer
        generate_answers(model, processor, prompt, max_new_tokens=20, constrained=True, grammar=grammar)


@pytest.mark.slow
def test_overfit_a_few_examples_until_the_answer_equals_the_target():
    """Full fine-tuning of the tiny Idefics3 on 2 examples; greedy generation then reproduces them."""
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.loss import lm_loss
    from degusta_learn.vlm.generate import chat_format, generate_answers
    from degusta_learn.vlm.prompt_options import PromptOptions

    torch.manual_seed(0)
    model, processor = load("idefics3")
    exs = examples(context=0, options=PromptOptions(include=["target"]))
    chosen = sorted(range(len(exs)), key=lambda i: len(exs[i].answer))[:2]  # the two shortest answers
    batch_examples = [exs[i] for i in chosen]
    collate = Collator(processor, chat_format(model, processor), 4096, model.config.image_token_id)
    batch = collate(batch_examples)
    opt = torch.optim.AdamW(model.parameters(), lr=5e-3)
    model.train()
    for _step in range(300):
        loss, _ = lm_loss(model, batch)
        loss.backward()
        opt.step()
        opt.zero_grad()
        if loss.item() < 0.005:
            break
    model.eval()
    for ex in batch_examples:
        got = generate_answers(model, processor, ex.prompt, max_new_tokens=400)[0].text
        assert got == ex.answer


def test_grammar_places_each_object_once():
    g = AnswerGrammar("grid", dataset().catalog, GRID)
    first = "[{'type': 'cup', 'id': 3, 'position': ['A1'], 'cardinal_direction': 'N'}, {'type': 'cup', 'id': "
    assert g.feed(g.start(), first + "3,") is None
    assert g.feed(g.start(), first + "4,") is not None
    # Once every cup is placed, 'cup' cannot even be chosen (no dead end for the decoder).
    cups = [o.id for o in dataset().catalog.of_type("cup")]
    text = "[" + ", ".join(f"{{'type': 'cup', 'id': {i}, 'position': ['A1'], 'cardinal_direction': 'N'}}"
                           for i in cups)
    g = AnswerGrammar("grid", dataset().catalog, GRID, max_items=100)
    state = g.feed(g.start(), text + ", {'type': '")
    assert g.feed(state, "cu") is None and g.feed(state, "fork") is not None
