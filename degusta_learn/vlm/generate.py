"""Generate answers to a `Prompt` with a local VLM, optionally constrained to the answer grammar.

`generate_answers` is what the hf backend calls; `generate_batch` answers several prompts in one `generate`
call (left padding, the same sampler and grammar row by row), which the validation loop uses. Generation stops at the
template's end-of-turn token (always among the stop ids, see `ChatFormat`). Tokens are picked by
`constrain.Sampler` (exact sampling at the temperature, argmax at 0, one seeded noise stream per answer).
With `constrained=True` a `GrammarLogitsProcessor` keeps every sample inside the answer grammar, so every
completion parses; unconstrained generation stays available and its parse rate is what `parse_rate`
reports.

What decoding did is recorded in each `Completion.decoding`:

- constrained: `constrained: true`, `forced_close` (the token budget closed the answer early: in closing
  mode it refused the token the grammar alone allowed), `grammar_changed` (the grammar refused a token
  free decoding would have picked), and with `free_pass=True` the free answer of every answer the grammar
  changed (`free_text`, `free_cut`: it ran out of tokens): generated again without the grammar on the same
  noise streams, so it is exactly what `constrained=False` with the same seed writes. An answer the
  grammar did not change is its own free answer (`free_text` null), so the free parse rate costs only
  the answers the grammar changed;
  An item naming an object the answer already placed is handled by `on_repeat` (constrained only):
  "skip" (the default) lets the model write it (`AnswerGrammar.allowing_repeats`) and go on, and the answer
  reader drops it, so the answer is the free answer's objects, each once; "stop" ends the answer there
  (`repeat_stop`, see `constrain.Sampler`), keeping the items before it; "next" lets the grammar force the
  next-best unused id (a small model then invents objects until the budget runs out);
  "substitute" decodes as "skip" (the model's own tokens), then gives each repeated item
  placed elsewhere than the item it repeats the best id the model scored at that step that no item names (an
  item repeating id and places, a loop, is dropped as with "skip"; `substitute_repeats`; `substituted`:
  [item, named id, given id or None] per repeated item; the model's own text is the answer's `free_text`). The
  list keeps the model's length and places; only a repeated id changes. Exact where the tokenizer writes an
  id as one token (the tiny base's); where it writes digits one by one, the ranking sees only the last digit's
  choices;
- free: `constrained: false`, `cut` (the answer ran out of `max_new_tokens` before its end-of-turn).

`answer_token_budget` derives `max_new_tokens` from a dataset's ground-truth answers and the tokenizer
(`decoding.max_new_tokens: auto` of the hf backend and of fine-tuning's validation).

Example:
    model, processor = load_vlm("runs/tiny/idefics3", adapter="runs/tiny_lora/adapter")
    grammar = AnswerGrammar("grid", ds.catalog, Grid(8, 8))
    completions = generate_answers(model, processor, prompt, n=5, temperature=1.0, max_new_tokens=256,
                                   constrained=True, grammar=grammar, free_pass=True)
    completions[0].decoding   # {'constrained': True, 'forced_close': False, 'grammar_changed': True, ...}
"""

from __future__ import annotations

import math
import re

import torch

from degusta_learn.errors import DegustaError
from degusta_learn.vlm.inputs import ChatFormat, encode_prompt, prompt_messages

BUDGET_MARGIN = 0.1
"""`answer_token_budget` leaves this fraction above the longest ground-truth answer (another tokenization
of the same text, a longer answer than any target)."""
ON_REPEAT = ("skip", "stop", "next", "substitute")
"""What constrained decoding does with an item naming an object again (module docstring)."""


def chat_format(model, processor) -> ChatFormat:
    """The processor's `ChatFormat`, probed once and cached on the processor."""
    fmt = getattr(processor, "_degusta_chat_format", None)
    if fmt is None:
        fmt = ChatFormat(processor, getattr(model, "generation_config", None))
        processor._degusta_chat_format = fmt
    return fmt


def _row_seeds(seed: int | None, rows: int) -> list[int]:
    """One noise-stream seed per answer: from `seed`, or drawn from torch's global generator."""
    base = int(torch.randint(0, 2**62, ()).item()) if seed is None else int(seed)
    return [(base * 1_000_003 + r) % 2**63 for r in range(rows)]


def generate_answers(model, processor, prompt, n: int = 1, temperature: float = 0.0, max_new_tokens: int = 256,
                     constrained: bool = False, grammar=None, seed: int | None = None,
                     free_pass: bool = False, on_repeat: str = "skip") -> list:
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
        seed: seed of the answers' noise streams (reproducible samples; None: from torch's generator).
        free_pass: constrained only: also generate, without the grammar, every answer the grammar changed
            (`decoding.free_text`; see the module docstring).
        on_repeat: constrained only: an item naming an object again is written and dropped by the reader ("skip"),
            ends the answer ("stop"), is forced onto the next unused id ("next") or written and then given the
            model's best unused id ("substitute"); module docstring.

    Returns:
        n `Completion`s (text without special tokens, prompt and answer token counts, `decoding`).
    """
    return generate_batch(model, processor, [prompt], n, temperature, max_new_tokens, constrained, grammar, [seed],
                          free_pass, on_repeat)[0]


def encode_prompts(processor, fmt: ChatFormat, prompts: list):
    """Model inputs for `prompts`: one prompt as `encode_prompt` gives it, several left-padded into one batch
    (every row's new tokens then start at the same position, which the grammar and `generate` need)."""
    if len(prompts) == 1:
        return encode_prompt(processor, fmt, prompts[0])
    texts, images = [], []
    for prompt in prompts:
        messages, ims = prompt_messages(prompt)
        texts.append(fmt.prompt_text(messages))
        images.append(ims)
    if any(images) and not all(images):
        raise DegustaError("generate: a batch of prompts must all have images or all have none")
    return processor(text=texts, images=images if any(images) else None, padding=True, padding_side="left",
                     add_special_tokens=False, return_tensors="pt")


def generate_batch(model, processor, prompts: list, n: int = 1, temperature: float = 0.0, max_new_tokens: int = 256,
                   constrained: bool = False, grammar=None, seeds: list[int | None] | None = None,
                   free_pass: bool = False, on_repeat: str = "skip") -> list[list]:
    """`generate_answers` for several prompts in ONE `generate` call (left padding): `n` answers per prompt.

    Every answer keeps its own noise stream (`seeds[i]` gives prompt i's answers the streams
    `generate_answers(..., seed=seeds[i])` would), and the grammar and the sampler work row by row, so each
    prompt gets what `generate_answers` gives it alone, up to the padding's floating-point effect on the
    logits (greedy answers of the tiny models are identical: tests/test_finetune_validation.py). The free pass
    (`free_pass`) runs prompt by prompt, for the answers the grammar changed only. One prompt is exactly
    `generate_answers`.

    Returns:
        One list of n `Completion`s per prompt, in order.
    """
    from transformers import LogitsProcessorList

    from degusta_learn.task.prompt import Completion
    from degusta_learn.vlm.constrain import GrammarLogitsProcessor, Sampler

    if constrained and grammar is None:
        raise DegustaError("decoding.constrained: constrained decoding needs the answer grammar (catalog and grid)")
    if on_repeat not in ON_REPEAT:
        raise DegustaError(f"on_repeat: expected one of {list(ON_REPEAT)}, got {on_repeat!r}")
    if constrained and on_repeat in ("skip", "substitute"):
        grammar = grammar.allowing_repeats()
    seeds = [None] * len(prompts) if seeds is None else list(seeds)
    if len(seeds) != len(prompts):
        raise DegustaError(f"generate: {len(prompts)} prompts but {len(seeds)} seeds")
    fmt = chat_format(model, processor)
    tok = processor.tokenizer
    device = next(model.parameters()).device
    dtype = next(p for p in model.parameters() if p.is_floating_point()).dtype
    stops = set(fmt.stop_ids)

    def run(batch: list, row_seeds: list[int], with_grammar: bool):
        """(text, prompt tokens, answer tokens, cut) per row (`len(row_seeds) / len(batch)` rows a prompt, in
        prompt order), and the sampler (what it recorded)."""
        inputs = encode_prompts(processor, fmt, batch)
        inputs = {k: (v.to(device, dtype) if v.is_floating_point() else v.to(device)) for k, v in inputs.items()}
        prompt_len = inputs["input_ids"].shape[1]
        per_prompt = len(row_seeds) // len(batch)
        proc = (GrammarLogitsProcessor(grammar, tok, prompt_len, fmt.stop_ids, max_new_tokens)
                if with_grammar else None)
        sampler = Sampler(temperature, row_seeds, fmt.stop_ids, proc, on_repeat=on_repeat)
        # The sampler picks each token and hands `generate` a one-hot distribution: nothing may reshape it.
        # num_beams=1: one row per returned sequence, whatever the folder's generation_config.json says
        kwargs = dict(max_new_tokens=max_new_tokens, eos_token_id=fmt.stop_ids, do_sample=True, temperature=1.0,
                      top_k=0, top_p=1.0, use_cache=True, num_return_sequences=per_prompt, num_beams=1,
                      pad_token_id=tok.pad_token_id if tok.pad_token_id is not None else fmt.end_id,
                      logits_processor=LogitsProcessorList([sampler]))
        with torch.no_grad():
            if per_prompt > 1 and shares_prompt_pass(model):
                inputs, kwargs["num_return_sequences"] = shared_prompt_pass(model, inputs, per_prompt), 1
            out = model.generate(**inputs, **kwargs)
        lengths = inputs["attention_mask"].sum(dim=1).tolist() if "attention_mask" in inputs else [prompt_len]
        rows = []
        for r, row in enumerate(out[:, prompt_len:].tolist()):
            end = next((i for i, t in enumerate(row) if t in stops), None)
            text = tok.decode(row[:end], skip_special_tokens=True, clean_up_tokenization_spaces=False).strip()
            if sampler.repeat_stop[r] and "}" in text:  # the items before the repeat (a valid answer)
                text = text[:text.rindex("}") + 1] + "]"
            rows.append((text, int(lengths[r // per_prompt]), len(row) if end is None else end + 1,
                         end is None))
        return rows, sampler

    k = n if temperature > 0 else 1
    prompt_seeds = [_row_seeds(s, k) for s in seeds]
    rows, sampler = run(prompts, [s for ps in prompt_seeds for s in ps], constrained)
    if constrained:
        decoding = [{"constrained": True, "forced_close": sampler.forced_close[r],
                     "grammar_changed": sampler.grammar_changed[r], "repeat_stop": sampler.repeat_stop[r],
                     "free_text": None, "free_cut": False, **({} if free_pass else {"free_pass": False})}
                    for r in range(len(rows))]
        if on_repeat == "substitute":
            for r, (own, *rest) in enumerate(rows):
                text, decoding[r]["substituted"] = substitute_repeats(own, sampler.alternatives[r])
                rows[r] = (text, *rest)
                if text != own and not sampler.grammar_changed[r]:  # every token the model's own: so is the
                    decoding[r].update(grammar_changed=True, free_text=own)  # free answer, no second pass
        for i, prompt in enumerate(prompts):
            changed = [j for j in range(k) if sampler.grammar_changed[i * k + j]]
            if free_pass and changed:
                free, _ = run([prompt], [prompt_seeds[i][j] for j in changed], False)
                for j, (text, _, _, cut) in zip(changed, free):
                    decoding[i * k + j].update(free_text=text, free_cut=cut)
    else:
        decoding = [{"constrained": False, "cut": cut} for *_, cut in rows]
    out = []
    for i in range(len(prompts)):
        completions = [Completion(text=text, input_tokens=length, output_tokens=tokens, decoding=d)
                       for (text, length, tokens, _), d in zip(rows[i * k:(i + 1) * k], decoding[i * k:(i + 1) * k])]
        if temperature <= 0:
            completions = [Completion(c.text, c.input_tokens, c.output_tokens, dict(c.decoding))
                           for c in completions * n]
        out.append(completions)
    return out


SHARED_PASS_MODELS = ("fast_vlm", "idefics3")
"""Model types whose n answers to one prompt share one pass over the prompt (`shared_prompt_pass`), checked to give
the same answers (tests/test_shared_prompt_pass.py; SmolVLM-256M is an Idefics3): their positions are plain 1-D
counts. Others (e.g. Qwen2-VL, whose 3-D multimodal RoPE is set up in its own first generation step) go through
`generate`'s `num_return_sequences`, which runs the decoder over the prompt n times."""


def shares_prompt_pass(model) -> bool:
    """True when `model`'s n answers to a prompt may share one pass over it (`SHARED_PASS_MODELS`)."""
    return getattr(getattr(model, "config", None), "model_type", None) in SHARED_PASS_MODELS


def shared_prompt_pass(model, inputs: dict, k: int) -> dict:
    """`generate` inputs for k answers per prompt row that run the decoder over the prompt once.

    `generate` with `num_return_sequences=k` copies every prompt k times before its first step (the images are
    encoded once), so the decoder's pass over a prompt of ~1,500 tokens runs k times for answers that differ only
    from their first new token on. Here the prompt, all but its last token, runs once; its key/value cache is
    repeated k times per row (`Cache.batch_repeat_interleave`, the order `num_return_sequences` gives) and
    `generate` continues from it, its first step being the prompt's last token. Positions are those `generate`
    gives a left-padded prompt (the attention mask's running count). The answers are those of the plain path
    (tests/test_shared_prompt_pass.py compares them, free and constrained, one prompt and a left-padded batch).

    Returns:
        input_ids and attention_mask repeated k times per row, and `cache` (no pixel values: the cache holds them).
    """
    ids = inputs["input_ids"]
    mask = inputs.get("attention_mask")
    mask = torch.ones_like(ids) if mask is None else mask
    positions = (mask.long().cumsum(-1) - 1).masked_fill(mask == 0, 0)
    rest = {key: v for key, v in inputs.items() if key not in ("input_ids", "attention_mask")}
    out = model(input_ids=ids[:, :-1], attention_mask=mask[:, :-1], position_ids=positions[:, :-1], use_cache=True,
                **rest)
    cache = out.cache if getattr(out, "cache", None) is not None else out.past_key_values
    cache.batch_repeat_interleave(k)
    return {"input_ids": ids.repeat_interleave(k, dim=0), "attention_mask": mask.repeat_interleave(k, dim=0),
            "cache": cache}


_ITEM = re.compile(r"'id': (\d+), 'position': (\[[^\]]*\])")


def substitute_repeats(text: str, alternatives: list[list[str]]) -> tuple[str, list[list]]:
    """`on_repeat: substitute`: every item of a constrained answer `text` that names an object an earlier item
    named, at other places than that item, gets the first of its `alternatives` (one ranked list of ids per
    repeated item, in order: the sampler's `Sampler.alternatives`) that no item names: the model put another
    object there and could not tell which. An item that repeats an earlier one's id *and* places (a model
    looping on one item) keeps its id, as does one with no alternative left: the reader drops both.

    Returns:
        (the answer, [[item index, the id it named, the id it was given or None], ...] one per repeated item).
    """
    matches = list(_ITEM.finditer(text))
    named = {m.group(1) for m in matches}
    placed: dict[str, set[str]] = {}  # id -> the position lists its items gave
    swaps, pieces, last = [], [], 0
    for item, m in enumerate(matches):
        id_, where = m.group(1), m.group(2)
        if id_ not in placed:
            placed[id_] = {where}
            continue
        options = alternatives[len(swaps)] if len(swaps) < len(alternatives) else []
        given = None if where in placed[id_] else next((a for a in options if a not in named), None)
        placed[id_].add(where)
        swaps.append([item, int(id_), None if given is None else int(given)])
        if given is not None:
            named.add(given)
            placed[given] = {where}
            pieces += [text[last:m.start(1)], given]
            last = m.end(1)
    return "".join(pieces) + text[last:], swaps


def answer_token_budget(tokenizer, ds, kind: str, grid=None, grammar=None, margin: float = BUDGET_MARGIN) -> dict:
    """The new-token budget that lets a model write any ground-truth answer of `ds`, from its tokenizer.

    Every arrangement's canonical answer of `kind` (`format_answer`, as fine-tuning targets are written)
    is tokenized; the budget is the longest plus `margin` of it, plus the end-of-turn token, plus, with a
    `grammar` (constrained decoding), the tokens its closing mode reserves (`max_chars_to_close`): so
    closing mode never starts before an answer as long as the longest target is written.

    Returns:
        {"max_new_tokens": budget, "answer_max": longest answer, "answer_mean": mean, "answers": count,
         "close_reserve": tokens reserved for closing (0 without grammar)}.
    """
    from degusta_learn.task.answer_format import answer_items, format_answer

    if not ds.arrangements:
        raise DegustaError("decoding.max_new_tokens: auto: the dataset has no arrangements to size the answers from")
    texts = [format_answer(answer_items(list(a.placements), ds.catalog, kind, grid), kind) for a in ds.arrangements]
    lengths = [len(ids) for ids in tokenizer(texts, add_special_tokens=False)["input_ids"]]
    reserve = grammar.max_chars_to_close if grammar is not None else 0
    longest = max(lengths)
    return {"max_new_tokens": math.ceil(longest * (1 + margin)) + 1 + reserve, "answer_max": longest,
            "answer_mean": round(sum(lengths) / len(lengths), 1), "answers": len(lengths), "close_reserve": reserve}


def parse_rate(texts: list[str], kind: str, catalog, grid) -> float:
    """Fraction of texts that `parse_answer` reads (the number unconstrained runs report)."""
    from degusta_learn.task.answers import AnswerParseError, parse_answer
    ok = 0
    for t in texts:
        try:
            parse_answer(t, kind, catalog, grid)
            ok += 1
        except AnswerParseError:
            pass
    return ok / max(len(texts), 1)
