"""The `hf` backend: a local Hugging Face VLM (zero-shot base model, or base + fine-tuned adapter).

Loads the model (`vlm.load.load_vlm`: a folder, a shipped model such as `tiny_vlm_base`, or a hub id, downloaded
into the Hugging Face cache when missing unless `HF_HUB_OFFLINE=1`: vlm/hub.py), optionally with a peft adapter (`backend.adapter`, folded into the weights for speed), and answers with
`vlm.generate.generate_answers`, optionally constrained to the answer grammar
(`backend.constrained: true`: every answer parses). A fine-tuned adapter or model folder carries
`degusta_finetune.json` (a `FinetuneRecord`, vlm/record.py, written by `degusta train`): the backend
re-applies its prompt options (image groups, composed canvases) and image budget, and refuses a different
method or grid than the one trained, so the model is prompted exactly as it was trained. A base
pretrained by degusta (`kind: pretrain`, e.g. the shipped `tiny_vlm_base`) carries `degusta_base.json` (a
`BaseRecord`) instead: its image size, grid and prompt layout are applied the same way when it runs
zero-shot. With a grid method, an image budget too coarse to show single grid cells is refused
(`backend.image_size`). Before predicting, the runner calls `check_run` with the dataset and episodes:
predicting on participants a fine-tuned model was trained or validated on (another split `seed`, or
another `dataset` with the same participant ids) is refused, and so are images rendered at another size
than in training (`image_size`).

Usage (configs/predict_hf_tiny_finetuned.yaml):
    backend: {name: hf, model: runs/tiny/idefics3, adapter: runs/finetune_tiny_cpu/adapter,
              constrained: true, device: cpu}
"""

from __future__ import annotations

import dataclasses
import functools
import threading
from dataclasses import dataclass
from typing import ClassVar, Literal

from degusta_learn.config import bounded
from degusta_learn.errors import DegustaError
from degusta_learn.prompting.backends.base import Backend, BackendConfig

DECODING_VERSION = 5
"""Bump when `vlm.generate`'s sampling or `vlm.grammar` changes what a seeded answer is (2: per-answer noise
streams, sorted cells and per-type cell limits in the grammar; 3: a constrained answer ends where the model
names an object again, `stop_on_repeat`; 4: `on_repeat`, by default an item naming an object again is written
and dropped and the answer goes on; 5: a repeated id is recognised where a token carries the space before the
number, as GPT-2-style tokenizers write " 16", which `on_repeat: stop` missed)."""


@dataclass
class HFConfig(BackendConfig):
    """The `backend:` keys of the hf backend (`model`: a hub id in the local cache or a model folder)."""

    name: str = "hf"
    max_tokens: int | Literal["auto"] = "auto"
    """Most new tokens per answer; auto: the dataset's longest ground-truth answer with this model's
    tokenizer + 10%, + the tokens closing a constrained answer reserves (`vlm.generate.answer_token_budget`)."""
    adapter: str | None = None
    """A peft LoRA adapter folder (from `degusta train`)."""
    constrained: bool = False
    """Constrain decoding to the answer grammar."""
    on_repeat: Literal["skip", "stop", "next", "substitute"] = "skip"
    """Constrained: an item naming an object the answer already placed is written and dropped by the answer
    reader, and the answer goes on (skip); the answer ends there (stop); the grammar forces the next-best unused
    id (next: a small model then invents objects until the budget runs out); the model writes it and the answer
    goes on, then the item gets the model's best unused id at that step (substitute). `vlm.generate`;
    docs/prompting.md."""
    device: str = "auto"
    """cpu, cuda, auto."""
    dtype: Literal["auto", "float32", "bfloat16", "float16"] = "auto"
    """float32, bfloat16, float16, auto."""
    image_size: int | None = bounded(None, 16, 4096)
    """The processor's image size budget (unset: the model's default)."""
    context_answers: bool | None = None
    """Each context table also written out in the answer format after its image (`vlm.prompt_options`; not the
    paper's prompt). null: as the model was trained (its degusta_finetune.json or degusta_base.json; off for
    any other model); true / false: so, whatever the training (e.g. a zero-shot row prompted as a fine-tune was)."""

    report_unconstrained: bool = True
    """Constrained: also decode without the grammar every answer the grammar changed (same noise stream), for the
    free parse rate the reports show. It costs ~30% of a fine-tuned tiny base's decoding (its free answers often
    run to the token budget); false leaves the answers as they are and reports no free parse rate."""

    answer_keys = ("adapter", "constrained", "on_repeat", "dtype", "image_size", "context_answers")
    RENAMED: ClassVar[dict[str, str]] = {"stop_on_repeat": "on_repeat (skip, stop, next or substitute; true was stop)"}

    def answer_fields(self) -> dict:
        """The base keys plus the decoding version: answers cached before a change of the sampler or the
        answer grammar are not what this code would write for the same seed, so they are not reused."""
        fields = {**super().answer_fields(), "decoding": DECODING_VERSION}
        if not self.report_unconstrained:  # answers cached without their free answers (keyed only when off, so
            fields["report_unconstrained"] = False  # the answers cached before the key existed stay valid)
        return fields


class HFBackend(Backend):
    """A local transformers VLM behind the Backend protocol (generation is serialized by a lock)."""

    name = "hf"
    config_class = HFConfig
    per_sample = False  # n answers from one generate call
    cacheable = True
    takes_schema = False  # it constrains decoding itself
    schema_hint = " (the hf backend constrains decoding itself: set backend.constrained: true)"
    key_env = None

    @classmethod
    def is_local(cls, cfg: HFConfig) -> bool:
        return True

    @classmethod
    def image_tokens(cls, width: int, height: int, cfg: HFConfig) -> int:
        """This model's image tokens per image at `backend.image_size` (read from its processor and config,
        offline, no weights); the generic estimate when they cannot be read (a missing folder, tiling)."""
        side = _image_tokens_per_side(cfg.model, cfg.image_size)
        return side * side if side else super().image_tokens(width, height, cfg)

    def __init__(self, model: str, adapter: str | None = None, constrained: bool = False, device: str = "auto",
                 dtype: str = "auto", image_size: int | None = None, grid=None, catalog=None,
                 on_repeat: str = "skip", context_answers: bool | None = None, report_unconstrained: bool = True):
        from degusta_learn.vlm.generate import chat_format
        from degusta_learn.vlm.hub import resolve_adapter, resolve_model
        from degusta_learn.vlm.inputs import check_grid_resolution, set_image_budget
        from degusta_learn.vlm.load import load_vlm
        from degusta_learn.vlm.record import FinetuneRecord, locate_record, read_record

        self.model = model
        adapter = str(resolve_adapter(adapter, "backend.adapter")) if adapter else None
        # how the model was trained (vlm/record.py): the adapter's record, read before the model is looked for;
        # else the model folder's (a hub id is downloaded here if missing)
        self.record_path = locate_record(adapter) or locate_record(resolve_model(model, "backend.model"))
        self.record = read_record(self.record_path) if self.record_path else None
        if grid is not None and self.record is not None:
            rows, cols = self.record.grid.rows, self.record.grid.cols
            if (grid.rows, grid.cols) != (rows, cols):
                raise DegustaError(f"grid: this model was trained on a {rows}x{cols} grid, the predict config "
                                   f"asks for {grid.rows}x{grid.cols}; set grid.rows={rows} grid.cols={cols}")
        self.vlm, self.processor = load_vlm(model, adapter=adapter, device=device, dtype=dtype, key="backend.model",
                                            merge_adapter=True)
        try:  # the chat template probed now, before a run sets up its cache (vlm.generate caches the result)
            chat_format(self.vlm, self.processor)
        except DegustaError as e:
            raise DegustaError(f"backend.model: {model!r}: {str(e).removeprefix('model: ')}") from None
        budget = image_size if image_size is not None else (self.record.image_size if self.record else None)
        set_image_budget(self.processor, self.vlm.config, budget, key="backend.image_size")
        if grid is not None:
            check_grid_resolution(self.processor, self.vlm.config, grid, key="backend.image_size")
        self.options = self.record.prompt if self.record else None
        if context_answers is not None:
            from degusta_learn.vlm.prompt_options import PromptOptions

            self.options = dataclasses.replace(self.options or PromptOptions(), context_answers=context_answers)
        self.trained_method = self.record.method if isinstance(self.record, FinetuneRecord) else None
        self.constrained, self.grid, self.catalog = constrained, grid, catalog
        self.on_repeat, self.report_unconstrained = on_repeat, report_unconstrained
        if constrained and catalog is None:
            raise DegustaError("backend.constrained: constrained decoding needs the dataset catalog")
        self._grammars: dict = {}
        self._lock = threading.Lock()

    @classmethod
    def from_config(cls, cfg, grid=None, catalog=None) -> HFBackend:
        return cls(cfg.model, adapter=cfg.adapter, constrained=cfg.constrained, device=cfg.device,
                   dtype=cfg.dtype, image_size=cfg.image_size, grid=grid, catalog=catalog,
                   on_repeat=cfg.on_repeat, context_answers=cfg.context_answers,
                   report_unconstrained=cfg.report_unconstrained)

    def grammar(self, method: str):
        from degusta_learn.task.answers import answer_kind
        from degusta_learn.task.grammar import AnswerGrammar

        kind = answer_kind(method)
        if kind not in self._grammars:
            self._grammars[kind] = AnswerGrammar(kind, self.catalog, self.grid)
        return self._grammars[kind]

    @classmethod
    def check_run(cls, cfg: HFConfig, ds, episodes: list, image_size: int) -> None:
        """Before the model loads, predicting `episodes` of `ds` with images rendered at `image_size` px: refuse
        participants the model was trained or validated on, and another render size than in training."""
        from degusta_learn.scene.dataset import dataset_identity
        from degusta_learn.vlm.hub import metadata_folder
        from degusta_learn.vlm.record import locate_record, read_record

        super().check_run(cfg, ds, episodes, image_size)
        adapter = metadata_folder(cfg.adapter, "backend.adapter", adapter=True)  # a hub id: fails fast if offline
        model = metadata_folder(cfg.model, "backend.model")
        path = locate_record(adapter, model)  # the adapter's record first
        if path is not None:
            read_record(path).check_prediction(dataset_identity(ds), {e.participant for e in episodes}, image_size,
                                               where=str(path))

    def token_budget(self, ds, method: str) -> dict:
        """`max_tokens: auto`: the budget that fits every ground-truth answer of `ds` (`answer_token_budget`)."""
        from degusta_learn.task.answers import answer_kind
        from degusta_learn.vlm.generate import answer_token_budget

        return answer_token_budget(self.processor.tokenizer, ds, answer_kind(method), self.grid,
                                   grammar=self.grammar(method) if self.constrained else None)

    def complete(self, prompt, n: int, temperature: float, max_tokens: int, seed: int | None = None) -> list:
        from degusta_learn.vlm.generate import generate_answers
        from degusta_learn.vlm.prompt_options import adapt_prompt

        if self.trained_method and prompt.method != self.trained_method:
            raise DegustaError(f"method: this model was fine-tuned on {self.trained_method} prompts, the predict "
                               f"config runs {prompt.method}")
        if self.options is not None:
            prompt = adapt_prompt(prompt, self.options)
        grammar = self.grammar(prompt.method) if self.constrained else None
        with self._lock:
            return generate_answers(self.vlm, self.processor, prompt, n=n, temperature=temperature,
                                    max_new_tokens=max_tokens, constrained=self.constrained, grammar=grammar,
                                    seed=seed, on_repeat=self.on_repeat,
                                    free_pass=self.report_unconstrained)  # free answers where the grammar changed one


@functools.lru_cache(maxsize=16)
def _image_tokens_per_side(model: str, image_size: int | None) -> int | None:
    """Image tokens along one side of an image for `model` at `image_size` (None: unknown or unreadable)."""
    from transformers import AutoConfig

    from degusta_learn.vlm.hub import resolve_model
    from degusta_learn.vlm.inputs import image_tokens_per_side, set_image_budget
    from degusta_learn.vlm.load import load_processor

    try:
        folder = str(resolve_model(model, "backend.model", weights=False))
        processor = load_processor(folder, "backend.model")
        config = AutoConfig.from_pretrained(folder, local_files_only=True)
        set_image_budget(processor, config, image_size, key="backend.image_size")
        return image_tokens_per_side(processor, config)
    except Exception:  # noqa: BLE001 - an estimate: the run itself reports a missing or broken model in one line
        return None
