"""Generate answers to a `Prompt` with a local VLM, optionally constrained to the answer grammar.

`generate_answers` is what the hf backend and the validation loop call. Generation stops at the
template's end-of-turn token (always among the stop ids, see `ChatFormat`). With `constrained=True`
a `GrammarLogitsProcessor` keeps every sample inside the answer grammar, so every completion parses;
unconstrained generation stays available and its parse rate is what `parse_rate` reports.

Example:
    model, processor = load_vlm("checkpoints/tiny/idefics3", adapter="checkpoints/tiny_lora/adapter")
    grammar = AnswerGrammar("grid", ds.catalog, Grid(8, 8))
    completions = generate_answers(model, processor, prompt, n=5, temperature=1.0, max_new_tokens=256,
                                   constrained=True, grammar=grammar)
"""

from __future__ import annotations

import torch

from degusta_learn.errors import DegustaError
from degusta_learn.vlm.inputs import ChatFormat, encode_prompt


def chat_format(model, processor) -> ChatFormat:
    """The processor's `ChatFormat`, probed once and cached on the processor."""
    fmt = getattr(processor, "_degusta_chat_format", None)
    if fmt is None:
        fmt = ChatFormat(processor, getattr(model, "generation_config", None))
        processor._degusta_chat_format = fmt
    return fmt


def generate_answers(model, processor, prompt, n: int = 1, temperature: float = 0.0, max_new_tokens: int = 256,
                     constrained: bool = False, grammar=None, seed: int | None = None) -> list:
    """Sample `n` answers to `prompt`.

    Args:
        model: a VLM from `load_vlm` (with or without adapter), in eval mode.
        processor: its processor (image budget already set).
        prompt: a `prompting.Prompt`.
        n: number of answers; with temperature 0 (greedy) one is generated and repeated.
        temperature: 0 = greedy, > 0 = sampling at that temperature.
        max_new_tokens: most new tokens per answer.
        constrained: restrict decoding to `grammar` (an `AnswerGrammar`).
        grammar: required when constrained.
        seed: torch seed for sampling (reproducible samples).

    Returns:
        n `Completion`s (text without special tokens, prompt and answer token counts).
    """
    from transformers import LogitsProcessorList

    from degusta_learn.vlm.constrain import GrammarLogitsProcessor
    from degusta_learn.prompting.prompt import Completion

    if constrained and grammar is None:
        raise DegustaError("backend.constrained: constrained decoding needs the answer grammar (catalog and grid)")
    fmt = chat_format(model, processor)
    tok = processor.tokenizer
    device = next(model.parameters()).device
    dtype = next(p for p in model.parameters() if p.is_floating_point()).dtype
    inputs = encode_prompt(processor, fmt, prompt)
    inputs = {k: (v.to(device, dtype) if v.is_floating_point() else v.to(device)) for k, v in inputs.items()}
    prompt_len = inputs["input_ids"].shape[1]
    sample = temperature > 0
    rows = n if sample else 1
    kwargs = dict(max_new_tokens=max_new_tokens, eos_token_id=fmt.stop_ids, do_sample=sample, use_cache=True,
                  num_return_sequences=rows, pad_token_id=tok.pad_token_id if tok.pad_token_id is not None
                  else fmt.end_id)
    if sample:
        kwargs.update(temperature=temperature, top_k=0, top_p=1.0)
    if constrained:
        kwargs["logits_processor"] = LogitsProcessorList(
            [GrammarLogitsProcessor(grammar, tok, prompt_len, fmt.stop_ids, max_new_tokens)])
    if seed is not None:
        torch.manual_seed(seed)
    with torch.no_grad():
        out = model.generate(**inputs, **kwargs)
    completions = []
    stops = set(fmt.stop_ids)
    for row in out[:, prompt_len:].tolist():
        end = next((i for i, t in enumerate(row) if t in stops), len(row))
        text = tok.decode(row[:end], skip_special_tokens=True, clean_up_tokenization_spaces=False)
        completions.append(Completion(text=text.strip(), input_tokens=prompt_len, output_tokens=min(end + 1, len(row))))
    return completions if sample else completions * n


def parse_rate(texts: list[str], kind: str, catalog, grid) -> float:
    """Fraction of texts that `parse_answer` reads (the number unconstrained runs report)."""
    from degusta_learn.prompting import AnswerParseError, parse_answer

    ok = 0
    for t in texts:
        try:
            parse_answer(t, kind, catalog, grid)
            ok += 1
        except AnswerParseError:
            pass
    return ok / max(len(texts), 1)
