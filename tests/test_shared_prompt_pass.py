"""n answers to one prompt share one pass over it (`vlm.generate.shared_prompt_pass`): the same answers as
`generate`'s own `num_return_sequences`, which runs the decoder over the prompt n times."""

from __future__ import annotations

import pytest
import torch
from finetune_support import GRID, dataset, examples, load

from degusta_learn.task.grammar import AnswerGrammar
from degusta_learn.vlm import generate as gen

ARCH = dict(vision_channels=[8, 8, 16, 16], vision_stem=8, text_hidden=32, text_layers=2, text_heads=4,
            text_kv_heads=1, text_intermediate=64, vocab_size=2048)


def _model(kind: str, tmp_path):
    if kind == "idefics3":
        return load("idefics3")
    from degusta_learn.pretrain.base import BaseArchitecture
    from degusta_learn.pretrain.export import save_random_base
    from degusta_learn.vlm.load import load_vlm

    folder = save_random_base(tmp_path / "base", BaseArchitecture(**ARCH))
    return load_vlm(str(folder), device="cpu", dtype="float32")


def _answers(model, processor, prompts, constrained: bool):
    grammar = AnswerGrammar("grid", dataset().catalog, GRID) if constrained else None
    with torch.no_grad():
        out = gen.generate_batch(model, processor, prompts, n=3, temperature=1.0, max_new_tokens=120,
                                 constrained=constrained, grammar=grammar, seeds=list(range(len(prompts))),
                                 free_pass=constrained)
    return [[(c.text, c.input_tokens, c.output_tokens, c.decoding) for c in row] for row in out]


@pytest.mark.parametrize("kind", ["fast_vlm", "idefics3"])
def test_shared_pass_gives_the_answers_of_n_copies_and_reads_the_prompt_once(kind, tmp_path, monkeypatch):
    model, processor = _model(kind, tmp_path)
    assert model.config.model_type == kind and gen.shares_prompt_pass(model)
    exs = examples(context=2)
    one, two = [exs[0].prompt], [exs[0].prompt, exs[1].prompt]  # one prompt; two, left-padded into one batch
    prompt_rows = []  # rows of every decoder pass over more than one position (a prompt, not a new token)

    def spy(module, args, kwargs):
        embeds = kwargs.get("inputs_embeds")
        if embeds is not None and embeds.shape[1] > 1:
            prompt_rows.append(embeds.shape[0])

    model.get_decoder().register_forward_pre_hook(spy, with_kwargs=True)

    def run_all():
        answers, rows = {}, {}
        for prompts, constrained in ((one, False), (two, True)):
            prompt_rows.clear()
            answers[len(prompts), constrained] = _answers(model, processor, prompts, constrained)
            rows[len(prompts), constrained] = prompt_rows[0]  # the first pass (a free pass adds its own)
        return answers, rows

    shared, rows = run_all()
    assert rows == {(1, False): 1, (2, True): 2}  # not x3: the answers share it
    monkeypatch.setattr(gen, "SHARED_PASS_MODELS", ())  # generate's own expansion: the prompt three times
    plain, rows = run_all()
    assert rows == {(1, False): 3, (2, True): 6}
    assert shared == plain
    assert any(d["grammar_changed"] for row in shared[(2, True)] for *_, d in row)  # the free pass ran too


def test_a_model_with_its_own_positions_is_not_shared():
    """Qwen2-VL's multimodal RoPE is set up in its own first generation step: it keeps generate's expansion."""
    model, _ = load("qwen2vl")
    assert not gen.shares_prompt_pass(model)
