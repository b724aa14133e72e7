"""The sizes of the tiny base's FastVLM (a convolutional timm tower + a Qwen2 decoder): `BaseArchitecture`.

It is the `model:` section of a pretrain config (`pretrain.base.build_base` builds the model from it with random
weights) and the `architecture` of a saved base's `degusta_base.json` (`vlm.record` checks a record against its
bounds), so it lives below both.
"""

from __future__ import annotations

from dataclasses import dataclass

from degusta_learn.config import bounded
from degusta_learn.errors import DegustaError

OUTPUT_STRIDE = 32  # a timm ResNet's last feature map is 1/32 of the image side


ATTENTION_INITS = ("mimetic", "random")


@dataclass
class BaseArchitecture:
    """The `model:` section of a pretrain config: sizes of the FastVLM built from random weights."""

    image_size: int = bounded(256, 32, 4096)
    """Pixels per (square) image side; lifted images are drawn at this size. image_size / 32 tokens per side."""
    vision_channels: list[int] = bounded(lo=1, hi=4096, factory=lambda: [32, 64, 128, 256])
    """Widths of the four ResNet stages (timm `resnet18` with these channels); the last is the feature size."""
    vision_layers: list[int] = bounded(lo=1, hi=64, factory=lambda: [1, 1, 2, 1])
    """Residual blocks per stage."""
    vision_stem: int = bounded(32, 1, 4096)
    """Width of the ResNet stem."""
    text_hidden: int = bounded(256, 1, 16_384)
    """Language model (Qwen2) width."""
    text_layers: int = bounded(4, 1, 256)
    """Language model depth."""
    text_heads: int = bounded(4, 1, 256)
    """Language model attention heads."""
    text_kv_heads: int = bounded(2, 1, 256)
    """Key/value heads (grouped-query attention)."""
    text_intermediate: int = bounded(768, 1, 65_536)
    """Language model MLP width."""
    vocab_size: int = bounded(2048, 1, 262_144)
    """BPE merges budget of the domain tokenizer (+ special tokens and answer literals)."""
    tie_embeddings: bool = True
    """Share the input embeddings with the output layer, so a head that moves a token's embedding along can
    name that token at once (copying ids and cells from the prompt)."""
    attention_init: str = "mimetic"
    """"mimetic": every attention head starts with W_q ~ W_k and W_v W_o ~ a positive projection (Trockman &
    Kolter 2023), so from step 0 a head attends to tokens like its query and copies what it attends to;
    "random": the plain Qwen2 init."""
    class_init: float = 1.0
    """Token-class initialization: each class of answer tokens (object types, numbers, grid cells, directions)
    gets one shared random direction, this many times the init scale, added to its members' input and output
    embeddings; 0: plain random init. A decoder trained from scratch copies an id from the question after
    ~250 steps with it, not within 300 without it (docs/tiny_base.md)."""

    previous_token_head: bool = True
    """Start head 0 of the first decoder layer as a previous-token head (`previous_token_head`): a positional
    head that moves each token's embedding one position on. An answer's first cell follows its object id
    (`..., 'id': 48, 'position': ['D4'`): with this head the position that names the cell already holds the
    id, and finding that id among the image tokens is one attention hop, learned in a few hundred steps;
    a decoder from scratch otherwise has to discover both heads together."""

    def __post_init__(self):
        for key in ("image_size", "vision_stem", "text_hidden", "text_layers", "text_heads", "text_kv_heads",
                    "text_intermediate", "vocab_size"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise DegustaError(f"model.{key}: expected a positive integer, got {value!r}")
        for key in ("vision_channels", "vision_layers"):
            value = getattr(self, key)
            if len(value) != 4 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in value):
                raise DegustaError(f"model.{key}: expected 4 positive integers (one per ResNet stage), got {value!r}")
        if self.attention_init not in ATTENTION_INITS:
            raise DegustaError(f"model.attention_init: expected one of {list(ATTENTION_INITS)}, got {self.attention_init!r}")
        for key in ("tie_embeddings", "previous_token_head"):
            if not isinstance(getattr(self, key), bool):
                raise DegustaError(f"model.{key}: expected true or false, got {getattr(self, key)!r}")
        if isinstance(self.class_init, bool) or not isinstance(self.class_init, (int, float)) or self.class_init < 0:
            raise DegustaError(f"model.class_init: expected a number >= 0, got {self.class_init!r}")
        if self.image_size % OUTPUT_STRIDE:
            raise DegustaError(f"model.image_size: {self.image_size} must be a multiple of {OUTPUT_STRIDE} "
                               "(the vision tower's output stride)")
        if self.text_hidden % self.text_heads or self.text_heads % self.text_kv_heads:
            raise DegustaError(f"model.text_heads: {self.text_heads} must divide model.text_hidden "
                               f"{self.text_hidden} and be divisible by model.text_kv_heads {self.text_kv_heads}")

    @property
    def tokens_per_side(self) -> int:
        return self.image_size // OUTPUT_STRIDE

    @property
    def tokens_per_image(self) -> int:
        return self.tokens_per_side**2
