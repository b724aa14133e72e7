"""LoRA / full / QLoRA setup with peft, restricted deliberately to the parts of the VLM you name.

A plain `["q_proj", "k_proj", "v_proj"]` in peft also hits the SigLIP vision tower of Idefics3, so the
targets here are matched *per part*: `targets` against the language model only, `vision_targets`
against the vision tower only, `connector: true` adds the vision-to-text projection. The matched module
names are resolved up front (a config whose targets match nothing fails with the key named) and passed
to peft as an explicit list.

Parts are found by attribute (transformers >= 4.52 layouts): Idefics3/SmolVLM `model.text_model`,
`model.vision_model`, `model.connector`; Qwen2-VL `model.language_model`, `model.visual` (its merger
`model.visual.merger` is the connector); other VLMs `model.language_model` / `model.vision_tower` /
`model.multi_modal_projector`.

Example:
    model = apply_lora(model, LoraConfig(r=8))           # PeftModel, only adapter tensors trainable
    save_adapter(model, "runs/run/adapter")       # plain PeftModel.save_pretrained
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from degusta_learn.config import bounded, check_choices
from degusta_learn.errors import DegustaError

MODES = ("lora", "full", "qlora")
MAX_TARGETS = 1000
"""Most module names in `lora.targets` / `lora.vision_targets` (each is matched against every Linear module)."""
_LANGUAGE = ("model.text_model", "model.language_model", "language_model", "model.model")
VISION_PREFIXES = ("model.vision_model", "model.visual", "model.vision_tower", "vision_tower")
CONNECTOR_PREFIXES = ("model.connector", "model.visual.merger", "model.multi_modal_projector", "multi_modal_projector")


@dataclass
class LoraConfig:
    """The `lora:` section of a finetune config."""

    mode: Literal["lora", "qlora", "full"] = "lora"
    """"lora" (adapters on a frozen base), "full" (train every weight), "qlora" (4-bit base; GPU + bitsandbytes)."""
    r: int = bounded(16, 1, 4096)
    """Adapter rank: higher = more capacity and memory."""
    alpha: int = bounded(32, 1, 1_000_000)
    """LoRA scaling numerator (effective scale alpha / r)."""
    dropout: float = 0.05
    """Dropout on the adapter input."""
    targets: list[str] = field(default_factory=lambda: ["q_proj", "k_proj", "v_proj", "o_proj", "gate_proj",
                                                        "up_proj", "down_proj"])
    """Module names adapted inside the LANGUAGE model (attention + MLP projections by default)."""
    vision_targets: list[str] = field(default_factory=list)
    """Module names adapted inside the vision tower, e.g. [q_proj, k_proj, v_proj, out_proj, fc1, fc2] (SmolVLM) or [qkv, proj, fc1, fc2] (Qwen2-VL)."""
    connector: bool = False
    """Also adapt the Linear layers of the vision-to-text connector."""
    freeze_vision: bool = False
    """full mode only: keep the vision tower frozen."""
    merge: bool = False
    """After training, also write base + adapter merged into `<run>/merged/` (a plain model folder)."""

    def __post_init__(self):
        check_choices(self, "lora")
        if self.r < 1:
            raise DegustaError(f"lora.r: expected >= 1, got {self.r}")
        if not 0 <= self.dropout < 1:
            raise DegustaError(f"lora.dropout: expected in [0, 1), got {self.dropout}")
        for key in ("targets", "vision_targets"):
            names = getattr(self, key)
            if len(names) > MAX_TARGETS:
                raise DegustaError(f"lora.{key}: {len(names):,} module names (at most {MAX_TARGETS:,}: names match "
                                   "every layer, e.g. q_proj)")
            bad = next((n for n in names if not isinstance(n, str) or not n or len(n) > 200), None)
            if bad is not None:
                raise DegustaError(f"lora.{key}: expected module names of 1 to 200 characters, got {bad!r}"[:200])


def find_part(model, candidates: tuple[str, ...], exclude: str | None = None) -> str | None:
    names = dict(model.named_modules())
    return next((c for c in candidates if c in names and c != exclude), None)


def resolve_targets(model, cfg: LoraConfig) -> list[str]:
    """Full names of the Linear modules to adapt; DegustaError naming the key if a target matches nothing."""
    import torch.nn as nn

    linear = [n for n, m in model.named_modules() if isinstance(m, nn.Linear)]
    language = find_part(model, _LANGUAGE)
    vision = find_part(model, VISION_PREFIXES)
    connector = find_part(model, CONNECTOR_PREFIXES)
    out: list[str] = []

    def pick(key: str, prefix: str | None, names: list[str], skip: str | None = None) -> None:
        if not names:
            return
        if prefix is None:
            raise DegustaError(f"lora.{key}: this model has no part the toolkit recognises for it "
                               f"(looked for {', '.join(_LANGUAGE if key == 'targets' else VISION_PREFIXES)})")
        inside = [n for n in linear if n.startswith(prefix + ".") and not (skip and n.startswith(skip + "."))]
        for target in names:
            hits = [n for n in inside if n == target or n.endswith("." + target)]
            if not hits:
                short = sorted({n.rsplit(".", 1)[-1] for n in inside})
                raise DegustaError(f"lora.{key}: {target!r} matches no Linear module in {prefix} "
                                   f"(its Linear names: {', '.join(short)})")
            out.extend(hits)

    pick("targets", language, cfg.targets)
    pick("vision_targets", vision, cfg.vision_targets, skip=connector)
    if cfg.connector:
        if connector is None:
            raise DegustaError("lora.connector: this model has no connector the toolkit recognises")
        out.extend(n for n in linear if n.startswith(connector + "."))
    return sorted(set(out))


def apply_lora(model, cfg: LoraConfig):
    """Wrap `model` for training per `cfg.mode`; returns the PeftModel (lora/qlora) or the model (full)."""
    if cfg.mode == "full":
        for name, p in model.named_parameters():
            p.requires_grad = not (cfg.freeze_vision and _is_vision(model, name))
        return model
    import peft

    targets = resolve_targets(model, cfg)
    if cfg.mode == "qlora":
        model = peft.prepare_model_for_kbit_training(model, use_gradient_checkpointing=False)
    pc = peft.LoraConfig(r=cfg.r, lora_alpha=cfg.alpha, lora_dropout=cfg.dropout, target_modules=targets,
                         bias="none", task_type="CAUSAL_LM")
    from degusta_learn.vlm.load import quiet_peft

    with quiet_peft():
        return peft.get_peft_model(model, pc)


def _is_vision(model, name: str) -> bool:
    vision = find_part(model, VISION_PREFIXES)
    return bool(vision) and name.startswith(vision + ".")


def check_qlora() -> None:
    """QLoRA needs a CUDA GPU and bitsandbytes; say so instead of failing deep inside peft."""
    import importlib.util

    import torch

    if not torch.cuda.is_available():
        raise DegustaError("lora.mode: qlora needs a CUDA GPU (none visible); use lora or full")
    if importlib.util.find_spec("bitsandbytes") is None:
        raise DegustaError("lora.mode: qlora needs the bitsandbytes package (pip install bitsandbytes); "
                           "use lora or full")


def quantization_config():
    """The 4-bit NF4 BitsAndBytesConfig QLoRA loads the base model with."""
    import torch
    from transformers import BitsAndBytesConfig

    return BitsAndBytesConfig(load_in_4bit=True, bnb_4bit_quant_type="nf4", bnb_4bit_use_double_quant=True,
                              bnb_4bit_compute_dtype=torch.bfloat16)


def save_adapter(model, out: str | Path) -> Path:
    """`PeftModel.save_pretrained(out)`: adapter_config.json + adapter_model.safetensors only."""
    out = Path(out)
    model.save_pretrained(str(out))
    return out


def merge_and_save(model, processor, out: str | Path) -> Path:
    """Merge the adapter into a copy of the base weights and save a plain model folder (+ processor)."""
    import copy

    merged = copy.deepcopy(model).merge_and_unload()
    out = Path(out)
    merged.save_pretrained(str(out))
    processor.save_pretrained(str(out))
    return out


def trainable_summary(model) -> dict:
    """{"trainable": n, "total": n, "fraction": f} parameter counts."""
    total = sum(p.numel() for p in model.parameters())
    train = sum(p.numel() for p in model.parameters() if p.requires_grad)
    return {"trainable": train, "total": total, "fraction": train / max(total, 1)}


def lora_regex_hint(names: list[str]) -> str:
    """A compact regex equivalent of an explicit target list (for docs and logs)."""
    tails = sorted({n.rsplit(".", 1)[-1] for n in names})
    heads = sorted({re.sub(r"\.\d+\.", r".\\d+.", n.rsplit(".", 1)[0]) for n in names})
    return f"({'|'.join(heads)})\\.({'|'.join(tails)})"
