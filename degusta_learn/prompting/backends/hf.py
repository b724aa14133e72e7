"""The `hf` backend: a local Hugging Face VLM (zero-shot base model, or base + fine-tuned adapter).

Which model is the config's `model:` section (`vlm.settings.ModelSettings`: `model.name`, `model.adapter`,
`model.dtype`, `model.image_size`), how it decodes its `decoding:` section (`constrained`, `on_repeat`,
`max_new_tokens`, `report_unconstrained`, ...), the same keys fine-tuning's validation reads; `backend:` keeps how
the model runs here (`device`). Loads the model (`vlm.load.load_vlm`: a folder, a shipped model
such as `tiny_vlm_base`, or a hub id, downloaded into the Hugging Face cache when missing unless
`HF_HUB_OFFLINE=1`: vlm/hub.py), optionally with a peft adapter (`model.adapter`, folded into the weights for
speed), and answers with `vlm.generate.generate_answers`, constrained to the answer grammar unless
`decoding.constrained: false` (every answer parses). A fine-tuned adapter or model folder carries
`degusta_finetune.json` (a `FinetuneRecord`, vlm/record.py, written by `degusta train`): the backend
re-applies its prompt options (image groups, composed canvases) and image budget, and refuses a different
method or grid than the one trained, so the model is prompted exactly as it was trained. A base
pretrained by degusta (`kind: pretrain`, e.g. the shipped `tiny_vlm_base`) carries `degusta_base.json` (a
`BaseRecord`) instead: its image size, grid and prompt layout are applied the same way when it runs
zero-shot. With a grid method, an image budget too coarse to show single grid cells is refused
(`model.image_size`). Before predicting, the runner calls `check_run` with the dataset and episodes:
predicting on participants a fine-tuned model was trained or validated on (another split `seed`, or
another `dataset` with the same participant ids) is refused, and so are images rendered at another size
than in training (`render_size`).

Usage (configs/predict_hf_tiny_finetuned.yaml):
    backend: {name: hf, device: cpu}
    model: {name: runs/tiny/idefics3, adapter: runs/finetune_tiny_cpu/best_adapter, dtype: float32}
    decoding: {constrained: true, max_new_tokens: auto, n: 1}
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from degusta_learn.errors import DegustaError
from degusta_learn.prompting.backends.base import RENAMED_KEYS, Backend, BackendConfig
from degusta_learn.task.prompt import MODALITY_RENAMED
from degusta_learn.vlm.settings import DecodingSettings, ModelSettings

DECODING_VERSION = 5
"""Bump when `vlm.generate`'s sampling or `vlm.grammar` changes what a seeded answer is (2: per-answer noise
streams, sorted cells and per-type cell limits in the grammar; 3: a constrained answer ends where the model
names an object again, `stop_on_repeat`; 4: `on_repeat`, by default an item naming an object again is written
and dropped and the answer goes on; 5: a repeated id is recognised where a token carries the space before the
number, as GPT-2-style tokenizers write " 16", which `on_repeat: stop` missed). The keys moving to the `model:` and
`decoding:` sections changed nothing a cache key holds: the same settings key the same answers."""


@dataclass
class HFConfig(BackendConfig):
    """The `backend:` keys of the hf backend: how the local model runs (which model and how it decodes are the
    `model:` and `decoding:` sections)."""

    name: str = "hf"
    device: str = "auto"
    """cpu, cuda, auto."""

    RENAMED: ClassVar[dict[str, str]] = {**RENAMED_KEYS, "context_answers": MODALITY_RENAMED}

    def answer_fields(self, model: ModelSettings, decoding: DecodingSettings) -> dict:
        """The base keys, the model and decoding keys this backend reads, and the decoding version: answers cached
        before a change of the sampler or the answer grammar are not what this code would write for the same
        seed, so they are not reused."""
        fields = {**super().answer_fields(model, decoding), "adapter": model.adapter, "dtype": model.dtype,
                  "image_size": model.image_size, "constrained": decoding.constrained,
                  "on_repeat": decoding.on_repeat, "decoding": DECODING_VERSION}
        if not decoding.report_unconstrained:  # answers cached without their free answers (keyed only when off, so
            fields["report_unconstrained"] = False  # the answers cached before the key existed stay valid)
        return fields


class HFBackend(Backend):
    """A local transformers VLM behind the Backend protocol (generation is serialized by a lock)."""

    name = "hf"
    config_class = HFConfig
    per_sample = False  # n answers from one generate call
    cacheable = True
    takes_schema = False  # it constrains decoding itself
    schema_hint = " (the hf backend constrains decoding itself: set decoding.constrained: true)"
    key_env = None
    local_decoding = True

    @classmethod
    def is_local(cls, cfg: HFConfig) -> bool:
        return True

    @classmethod
    def image_tokens(cls, width: int, height: int, cfg: HFConfig, model: ModelSettings) -> int:
        """This model's image tokens per image at `model.image_size` (read from its processor and config,
        offline, no weights); the generic estimate when they cannot be read (a missing folder, tiling)."""
        side = _image_tokens_per_side(model.name, model.image_size)
        return side * side if side else super().image_tokens(width, height, cfg, model)

    def __init__(self, model: str, adapter: str | None = None, constrained: bool = False, device: str = "auto",
                 dtype: str = "auto", image_size: int | None = None, grid=None, catalog=None,
                 on_repeat: str = "skip", report_unconstrained: bool = True):
        from degusta_learn.vlm.generate import chat_format
        from degusta_learn.vlm.hub import resolve_adapter, resolve_model
        from degusta_learn.vlm.inputs import check_grid_resolution, set_image_budget
        from degusta_learn.vlm.load import load_vlm
        from degusta_learn.vlm.record import FinetuneRecord, locate_record, read_record

        self.model = model
        adapter = str(resolve_adapter(adapter, "model.adapter")) if adapter else None
        # how the model was trained (vlm/record.py): the adapter's record, read before the model is looked for;
        # else the model folder's (a hub id is downloaded here if missing)
        self.record_path = locate_record(adapter) or locate_record(resolve_model(model, "model.name"))
        self.record = read_record(self.record_path) if self.record_path else None
        if grid is not None and self.record is not None:
            rows, cols = self.record.grid.rows, self.record.grid.cols
            if (grid.rows, grid.cols) != (rows, cols):
                raise DegustaError(f"grid: this model was trained on a {rows}x{cols} grid, the predict config "
                                   f"asks for {grid.rows}x{grid.cols}; set grid.rows={rows} grid.cols={cols}")
        self.vlm, self.processor = load_vlm(model, adapter=adapter, device=device, dtype=dtype, key="model.name",
                                            device_key="backend.device", merge_adapter=True)
        try:  # the chat template probed now, before a run sets up its cache (vlm.generate caches the result)
            chat_format(self.vlm, self.processor)
        except DegustaError as e:
            raise DegustaError(f"model.name: {model!r}: {str(e).removeprefix('model: ')}") from None
        budget = image_size if image_size is not None else (self.record.image_size if self.record else None)
        set_image_budget(self.processor, self.vlm.config, budget, key="model.image_size")
        if grid is not None:
            check_grid_resolution(self.processor, self.vlm.config, grid, key="model.image_size")
        self.options = self.record.prompt if self.record else None  # its modality: the prompt's, when chosen
        self.trained_method = self.record.method if isinstance(self.record, FinetuneRecord) else None
        self.constrained, self.grid, self.catalog = constrained, grid, catalog
        self.on_repeat, self.report_unconstrained = on_repeat, report_unconstrained
        if constrained and catalog is None:
            raise DegustaError("decoding.constrained: constrained decoding needs the dataset catalog")
        self._grammars: dict = {}
        self._lock = threading.Lock()

    @classmethod
    def from_config(cls, cfg: HFConfig, model: ModelSettings, decoding: DecodingSettings, grid=None,
                    catalog=None) -> HFBackend:
        decoding = decoding.resolved(local=True)
        return cls(model.name, adapter=model.adapter, constrained=decoding.constrained, device=cfg.device,
                   dtype=model.dtype, image_size=model.image_size, grid=grid, catalog=catalog,
                   on_repeat=decoding.on_repeat, report_unconstrained=decoding.report_unconstrained)

    def grammar(self, method: str):
        from degusta_learn.task.answers import answer_kind
        from degusta_learn.task.grammar import AnswerGrammar

        kind = answer_kind(method)
        if kind not in self._grammars:
            self._grammars[kind] = AnswerGrammar(kind, self.catalog, self.grid)
        return self._grammars[kind]

    @classmethod
    def check_run(cls, cfg: HFConfig, model: ModelSettings, ds, episodes: list, render_size: int) -> None:
        """Before the model loads, predicting `episodes` of `ds` with images rendered at `render_size` px: refuse
        participants the model was trained or validated on, and another render size than in training."""
        from degusta_learn.scene.dataset import dataset_identity
        from degusta_learn.vlm.hub import metadata_folder
        from degusta_learn.vlm.record import locate_record, read_record

        super().check_run(cfg, model, ds, episodes, render_size)
        adapter = metadata_folder(model.adapter, "model.adapter", adapter=True)  # a hub id: fails fast if offline
        folder = metadata_folder(model.name, "model.name")
        path = locate_record(adapter, folder)  # the adapter's record first
        if path is not None:
            read_record(path).check_prediction(dataset_identity(ds), {e.participant for e in episodes}, render_size,
                                               where=str(path))

    def token_budget(self, ds, method: str) -> dict:
        """`decoding.max_new_tokens: auto`: the budget that fits every ground-truth answer of `ds` (`answer_token_budget`)."""
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


def adapter_decoding(model: ModelSettings, decoding: DecodingSettings, decoding_from: str = "config") -> DecodingSettings:
    """The decoding a predict run uses with `model.adapter`, given the validation that chose it (`vlm.record`,
    `degusta_selection.json` of a best folder, whose `decoding` is the fine-tune's `decoding:` section).

    `decoding_from: config` (the default): the config's `decoding`, as it is; when it differs from the recorded
    selection decoding on a key that changes the answers, one warning line on stderr names those keys.
    `decoding_from: adapter`: the recorded selection decoding exactly (refused, naming the key, when the adapter
    records none: no `model.adapter`, the last weights `adapter/`, or a folder exported before it was recorded)."""
    import sys

    from degusta_learn.vlm.hub import metadata_folder
    from degusta_learn.vlm.record import SELECTION_FILE, decoding_differences, selection_decoding

    if decoding_from == "adapter":
        folder = metadata_folder(model.adapter, "model.adapter", adapter=True) if model.adapter else None
        recorded = selection_decoding(folder)
        if recorded is None:
            where = f"{folder / SELECTION_FILE} has no 'decoding'" if folder else "model.adapter is not set"
            raise DegustaError(f"decoding_from: adapter needs the decoding its selection was made with ({where}: "
                               "it is written into a best folder, best_adapter/ or best_model/, by degusta train); "
                               "point model.adapter at a best folder, or set decoding_from: config")
        return recorded
    local = Path(str(model.adapter)).expanduser() if model.adapter else None  # no download to warn
    recorded = selection_decoding(local) if local is not None and local.is_dir() else None
    differing = decoding_differences(recorded, decoding) if recorded is not None else []
    if differing:
        shown = ", ".join(f"{k}: {_shown(recorded, k)} vs {_shown(decoding, k)}" for k in differing)
        line = (f"degusta: warning: decoding: differs from the validation decoding that selected model.adapter "
                f"({local / SELECTION_FILE}) on {shown} (selected vs here); decoding_from: adapter predicts as "
                "it was selected (docs/finetune.md, \"Selection that matches deployment\")")
        if line not in _WARNED:  # a config is built more than once in a run (compare checks every method first)
            _WARNED.add(line)
            print(line, file=sys.stderr)
    return decoding


_WARNED: set[str] = set()
"""The decoding warnings this process has printed: each is printed once."""


def _shown(decoding: DecodingSettings, key: str) -> str:
    value = decoding.sampling_temperature if key == "temperature" else getattr(decoding, key)
    return str(value).lower() if isinstance(value, bool) else str(value)


@functools.lru_cache(maxsize=16)
def _image_tokens_per_side(model: str, image_size: int | None) -> int | None:
    """Image tokens along one side of an image for `model` at `image_size` (None: unknown or unreadable)."""
    from transformers import AutoConfig

    from degusta_learn.vlm.hub import resolve_model
    from degusta_learn.vlm.inputs import image_tokens_per_side, set_image_budget
    from degusta_learn.vlm.load import load_processor

    try:
        folder = str(resolve_model(model, "model.name", weights=False))
        processor = load_processor(folder, "model.name")
        config = AutoConfig.from_pretrained(folder, local_files_only=True)
        set_image_budget(processor, config, image_size, key="model.image_size")
        return image_tokens_per_side(processor, config)
    except Exception:  # noqa: BLE001 - an estimate: the run itself reports a missing or broken model in one line
        return None
