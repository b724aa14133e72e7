"""One spelling for a VLM in every config kind: the `model:` section (which model) and the `decoding:` section
(how its answers are generated), the same keys in `degusta train` (kind finetune; pretrain's validation) and in
`degusta predict` (every zero-shot backend, API ones included).

- `model:` (`ModelSettings`): name, dtype, image_size (the processor's image budget, not the size the lifted
  images are rendered at: that is `render_size` / `data.render_size`), adapter. Fine-tuning's section adds its own
  training keys (`finetune.config.ModelConfig`) and refuses an adapter.
- `decoding:` (`DecodingSettings`): constrained, on_repeat, max_new_tokens, n, aggregation, temperature,
  report_unconstrained. `constrained`, `on_repeat` and `report_unconstrained` steer a local model's own decoding
  (the hf backend, validation); an API backend decodes on the server: there `constrained` is false and the other
  two stay at their defaults (any other value is refused in one line by the predict config).

`max_new_tokens: auto` is the dataset's longest ground-truth answer in the model's own tokenizer + 10%, + the
tokens closing a constrained answer reserves (`vlm.generate.answer_token_budget`) for the hf backend and for
fine-tuning's validation; `API_MAX_NEW_TOKENS` (1024) for an API backend, whose tokenizer is the service's.

Usage (a predict config; fine-tuning's `model:` / `decoding:` read the same):
    model: {name: tiny_vlm_base, adapter: runs/finetune_tiny_base_cpu/best_adapter, dtype: float32}
    decoding: {constrained: true, n: 5, temperature: 0.5, aggregation: greedy_votes_pooled, max_new_tokens: auto}
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar, Literal

from degusta_learn.config import bounded, check_choices
from degusta_learn.errors import DegustaError
from degusta_learn.task.aggregate import ANCHORED, Aggregation

API_MAX_NEW_TOKENS = 1024
"""What `decoding.max_new_tokens: auto` is for an API backend (openai, anthropic, gemini; replay ignores it): the
tokenizer is the service's, so nothing is sized from the data here; a 10-object grid answer is ~300 tokens."""

ON_REPEAT_RENAMED = "decoding.on_repeat (skip, stop, next or substitute; true was stop)"
"""Where the old `stop_on_repeat` key went, in every section that had it."""


@dataclass
class ModelSettings:
    """The `model:` section: which VLM answers (or is trained), in what dtype, with what image budget."""

    name: str = ""
    """Hub id, model folder or shipped model (tiny_vlm_base), or an API's model id; empty: the backend's (openai: gpt-4o)."""
    dtype: Literal["auto", "float32", "bfloat16", "float16"] = "auto"
    """Weights' dtype of a local model: auto (bf16 on a bf16 GPU, else fp32), float32, bfloat16, float16."""
    image_size: int | None = bounded(None, 16, 4096)
    """The processor's image budget, pixels per image side the model sees; null: the trained or model default."""
    adapter: str | None = None
    """A peft LoRA adapter folder or hub id (from `degusta train`) put on a local model; null: none."""

    def __post_init__(self):
        check_choices(self, "model")  # dtype: a section built in Python too (the loader checks YAML)


@dataclass
class DecodingSettings:
    """The `decoding:` section: how answers are generated, sampled and combined."""

    constrained: bool | None = None
    """Decode inside the answer grammar (every answer parses); null: true for a local model, false for an API one."""
    on_repeat: Literal["skip", "stop", "next", "substitute"] = "skip"
    """Constrained: an item naming a placed object is dropped (skip), ends the answer (stop), or gets another id (next, substitute)."""
    max_new_tokens: int | Literal["auto"] = bounded("auto", 1, 131_072)
    """Most new tokens per answer; auto: sized from the dataset (local models) or API_MAX_NEW_TOKENS (API backends)."""
    n: int = bounded(1, 1, 1000)
    """Answers per episode, aggregated into one plan (the paper: 5)."""
    aggregation: Aggregation = "steps"
    """n > 1: how the answers become one plan (task/aggregate.py): steps (the paper's) or greedy_votes_pooled."""
    temperature: float | None = bounded(None, 0.0, 10.0)
    """Sampling temperature; null: 0 (greedy) at n = 1, 1.0 at n > 1."""
    report_unconstrained: bool = True
    """Constrained: also decode freely (hf: the answers the grammar changed; validation: all), for the free parse rate."""

    RENAMED: ClassVar[dict[str, str]] = {"stop_on_repeat": ON_REPEAT_RENAMED, "max_tokens": "decoding.max_new_tokens"}

    @property
    def sampling_temperature(self) -> float:
        """The temperature answers are sampled at (`temperature`, or its default for `n`)."""
        if self.temperature is not None:
            return float(self.temperature)
        return 1.0 if self.n > 1 else 0.0

    def resolved(self, local: bool) -> DecodingSettings:
        """This section with `constrained` decided for a local model (`local`: its null is true) or an API one."""
        if self.constrained is not None:
            return self
        return dataclasses.replace(self, constrained=local)

    def __post_init__(self):
        check_choices(self, "decoding")  # on_repeat, aggregation: a section built in Python too
        if self.aggregation in ANCHORED and self.sampling_temperature == 0:
            raise DegustaError(f"decoding.aggregation: {self.aggregation} lengthens a greedy answer by sampled ones; "
                               "set decoding.n > 1 (or decoding.temperature > 0)")


API_REFUSED = (("model.adapter", lambda m, d: m.adapter, None), ("model.dtype", lambda m, d: m.dtype, "auto"),
               ("model.image_size", lambda m, d: m.image_size, None),
               ("decoding.on_repeat", lambda m, d: d.on_repeat, "skip"),
               ("decoding.report_unconstrained", lambda m, d: d.report_unconstrained, True))
"""The keys that steer a local model's own loading and decoding, with the value an API backend takes (its default)."""


def check_api_settings(model: ModelSettings, decoding: DecodingSettings, backend: str) -> None:
    """Refuse (one line naming the key) a local-model setting given to a backend that calls a service or replays
    recorded answers: `decoding.constrained: true`, or a non-default value of the keys of `API_REFUSED`."""
    if decoding.constrained:
        raise DegustaError(f"decoding.constrained: the {backend} backend cannot constrain decoding to the answer "
                           "grammar (a local model can: backend.name hf); set decoding.constrained: false, or "
                           "backend.structured_output: true for answers forced to a JSON schema")
    for key, get, default in API_REFUSED:
        if get(model, decoding) != default:
            raise DegustaError(f"{key}: steers a local model (the hf backend), not the {backend} backend; remove "
                               f"it (default: {'null' if default is None else str(default).lower()})")
