"""The `hf` backend: a local Hugging Face VLM (zero-shot base model, or base + fine-tuned adapter).

Loads the model offline (`vlm.load.load_vlm`: hub id from the local cache or a folder, never a
download), optionally with a peft adapter (`backend.adapter`), and answers with
`vlm.generate.generate_answers`, optionally constrained to the answer grammar
(`backend.constrained: true`: every answer parses). A fine-tuned adapter or model folder carries
`degusta_finetune.json` (written by `degusta train`): the backend re-applies its prompt options (image
groups, composed canvases) and image budget, and refuses a different method or grid than the one
trained, so the model is prompted exactly as it was trained. A base pretrained by degusta
(`kind: pretrain`, e.g. checkpoints/tiny_vlm_base) carries `degusta_base.json` instead: its image size,
grid and prompt layout are applied the same way when it runs zero-shot. With a grid method, an image
budget too coarse to show single grid cells is refused (`backend.image_size`).

Usage (configs/predict_hf_tiny_finetuned.yaml):
    backend: {name: hf, model: checkpoints/tiny/idefics3, adapter: checkpoints/finetune_tiny_cpu/adapter,
              constrained: true, device: cpu}
"""

from __future__ import annotations

import threading
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.fileio import read_json

META_FILE = "degusta_finetune.json"
BASE_META_FILE = "degusta_base.json"  # a base pretrained by degusta (finetune/pretrain): how it sees images


def read_meta(*folders: str | None) -> dict | None:
    """How a model expects to be prompted: the fine-tuning metadata of the first folder that has it
    (adapter first, then model), else a degusta-pretrained base's (its image size, grid and prompt layout)."""
    for name in (META_FILE, BASE_META_FILE):
        for folder in folders:
            if folder and (Path(folder) / name).is_file():
                return read_json(Path(folder) / name)
    return None


class HFBackend:
    """A local transformers VLM behind the Backend protocol (generation is serialized by a lock)."""

    name = "hf"

    def __init__(self, model: str, adapter: str | None = None, constrained: bool = False, device: str = "auto",
                 dtype: str = "auto", image_size: int | None = None, grid=None, catalog=None):
        from degusta_learn.vlm.prompt_options import PromptOptions
        from degusta_learn.vlm.inputs import check_grid_resolution, set_image_budget
        from degusta_learn.vlm.load import load_vlm

        self.model = model
        self.meta = read_meta(adapter, model)
        if grid is not None and self.meta and self.meta.get("grid"):
            rows, cols = self.meta["grid"]["rows"], self.meta["grid"]["cols"]
            if (grid.rows, grid.cols) != (rows, cols):
                raise DegustaError(f"grid: this model was trained on a {rows}x{cols} grid, the predict config "
                                   f"asks for {grid.rows}x{grid.cols}; set grid.rows={rows} grid.cols={cols}")
        self.vlm, self.processor = load_vlm(model, adapter=adapter, device=device, dtype=dtype, key="backend.model")
        budget = image_size if image_size is not None else (self.meta or {}).get("image_size")
        set_image_budget(self.processor, self.vlm.config, budget, key="backend.image_size")
        if grid is not None:
            check_grid_resolution(self.processor, self.vlm.config, grid, key="backend.image_size")
        prompt = (self.meta or {}).get("prompt")
        self.options = PromptOptions(**prompt) if prompt else None
        self.constrained, self.grid, self.catalog = constrained, grid, catalog
        if constrained and catalog is None:
            raise DegustaError("backend.constrained: constrained decoding needs the dataset catalog")
        self._grammars: dict = {}
        self._lock = threading.Lock()

    @classmethod
    def from_config(cls, cfg, grid=None, catalog=None) -> HFBackend:
        return cls(cfg.model, adapter=cfg.adapter, constrained=cfg.constrained, device=cfg.device,
                   dtype=cfg.dtype, image_size=cfg.image_size, grid=grid, catalog=catalog)

    def grammar(self, method: str):
        from degusta_learn.vlm.grammar import AnswerGrammar
        from degusta_learn.prompting.answers import answer_kind

        kind = answer_kind(method)
        if kind not in self._grammars:
            self._grammars[kind] = AnswerGrammar(kind, self.catalog, self.grid)
        return self._grammars[kind]

    def complete(self, prompt, n: int, temperature: float, max_tokens: int, seed: int | None = None) -> list:
        from degusta_learn.vlm.prompt_options import adapt_prompt
        from degusta_learn.vlm.generate import generate_answers

        if self.meta and self.meta.get("method") and prompt.method != self.meta["method"]:
            raise DegustaError(f"method: this model was fine-tuned on {self.meta['method']} prompts, the predict "
                               f"config runs {prompt.method}")
        if self.options is not None:
            prompt = adapt_prompt(prompt, self.options)
        grammar = self.grammar(prompt.method) if self.constrained else None
        with self._lock:
            return generate_answers(self.vlm, self.processor, prompt, n=n, temperature=temperature,
                                    max_new_tokens=max_tokens, constrained=self.constrained, grammar=grammar,
                                    seed=seed)
