"""Tiny random-weight VLMs built offline, saved like hub models (for CPU tests and smoke runs).

No pretrained weights can be downloaded here, so tests and the CPU configs use tiny models that have
the *architecture* of the real ones: a tiny Idefics3 (the architecture of SmolVLM-256M/500M-Instruct)
and a tiny Qwen2-VL. Each comes with a byte-level BPE tokenizer trained in well under a second with
the `tokenizers` library on the task vocabulary (the prompt texts, answer lists, digits, brackets, cell
ids, type and direction words), the model's special tokens, its image processor and a chat template
shaped like the real one. Everything is written with `save_pretrained`, so `load_vlm(folder)` loads it
through the same Auto classes as a hub id.

Usage:
    from degusta_learn.vlm.random_models.tiny import build_tiny_idefics3
    path = build_tiny_idefics3("runs/tiny/idefics3")   # ~1 MB, a few seconds
    model, processor = load_vlm(path)

Sizes follow NOTES-VLM.md: vocab_size == len(tokenizer); image_token_id and pad id overridden;
image_size / patch_size divisible by scale_factor; one tile per image (do_image_splitting=False), so an
image costs exactly (image_size / patch_size)^2 / scale_factor^2 tokens (+ 3 wrapper tokens).
"""

from __future__ import annotations

from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import atomic_write_json
from degusta_learn.vlm.random_models.common import set_generation_ids, train_tokenizer, wrap_tokenizer

TINY_KINDS = ("idefics3", "qwen2vl")
TINY_VERSION = 3  # bump when the tiny builders change, so stale cached folders are rebuilt


IDEFICS3_SPECIAL = ["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<end_of_utterance>",
                    "<fake_token_around_image>", "<image>", "<global-img>",
                    *[f"<row_{r}_col_{c}>" for r in range(1, 7) for c in range(1, 7)]]
QWEN2VL_SPECIAL = ["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<|vision_start|>", "<|vision_end|>",
                   "<|vision_pad|>", "<|image_pad|>", "<|video_pad|>"]

# SmolVLM-Instruct's template, shortened; <|im_start|> is its BOS and comes from the template only.
IDEFICS3_CHAT_TEMPLATE = (
    "<|im_start|>{% for message in messages %}{{ message['role'] | capitalize }}"
    "{% if message['content'][0]['type'] == 'image' %}{{ ':' }}{% else %}{{ ': ' }}{% endif %}"
    "{% for line in message['content'] %}{% if line['type'] == 'text' %}{{ line['text'] }}"
    "{% elif line['type'] == 'image' %}{{ '<image>' }}{% endif %}{% endfor %}<end_of_utterance>\n"
    "{% endfor %}{% if add_generation_prompt %}{{ 'Assistant:' }}{% endif %}"
)
# Qwen2-VL-Instruct's template without the video branch.
QWEN2VL_CHAT_TEMPLATE = (
    "{% for message in messages %}{% if loop.first and message['role'] != 'system' %}"
    "<|im_start|>system\nYou are a helpful assistant.<|im_end|>\n{% endif %}"
    "<|im_start|>{{ message['role'] }}\n{% if message['content'] is string %}{{ message['content'] }}"
    "<|im_end|>\n{% else %}{% for content in message['content'] %}"
    "{% if content['type'] == 'image' %}<|vision_start|><|image_pad|><|vision_end|>"
    "{% elif content['type'] == 'text' %}{{ content['text'] }}{% endif %}{% endfor %}<|im_end|>\n"
    "{% endif %}{% endfor %}{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)


def build_tiny_idefics3(out_dir: str | Path, image_size: int = 64, patch_size: int = 4, hidden: int = 64,
                        layers: int = 2, seed: int = 0) -> Path:
    """Build and save a random-weight tiny Idefics3 (SmolVLM architecture) with its processor.

    Args:
        out_dir: folder to write (created; existing files are overwritten).
        image_size: side of the one square tile per image, in pixels.
        patch_size: vision patch side; image_size / patch_size must divide by the scale factor 2. The
            defaults give 8 x 8 image tokens per image: enough to resolve an 8 x 8 grid.
        hidden: text hidden size (the vision tower uses hidden // 2).
        layers: text decoder layers.
        seed: weight initialisation seed.

    Returns:
        `out_dir` as a Path, loadable with `load_vlm`.
    """
    from transformers import PreTrainedTokenizerFast

    tokenizer = wrap_tokenizer(train_tokenizer(IDEFICS3_SPECIAL), PreTrainedTokenizerFast, IDEFICS3_SPECIAL,
                      **IDEFICS3_ROLES)
    model, processor = idefics3(tokenizer, image_size, patch_size, 2,
                                vision=dict(hidden_size=hidden // 2, intermediate_size=hidden, num_hidden_layers=2,
                                            num_attention_heads=4),
                                text=dict(hidden_size=hidden, intermediate_size=2 * hidden, num_hidden_layers=layers,
                                          num_attention_heads=4, num_key_value_heads=2), seed=seed)
    return _save(out_dir, model, processor, "idefics3")


IDEFICS3_ROLES = dict(bos_token="<|im_start|>", eos_token="<end_of_utterance>", pad_token="<|im_end|>",
                      unk_token="<|endoftext|>")


def idefics3(tokenizer, image_size: int, patch_size: int, scale_factor: int, vision: dict, text: dict,
             seed: int = 0):
    """(random-weight Idefics3ForConditionalGeneration, Idefics3Processor) of the given sizes.

    One tile per image (no splitting): an image costs (image_size / patch_size)^2 / scale_factor^2 image
    tokens + 3 wrapper tokens. `vision` / `text` are extra Idefics3 vision / llama text config values.
    """
    import torch
    from transformers import (
        Idefics3Config,
        Idefics3ForConditionalGeneration,
        Idefics3ImageProcessor,
        Idefics3Processor,
    )

    if image_size % patch_size or (image_size // patch_size) % scale_factor:
        raise DegustaError(f"image_size {image_size} / patch_size {patch_size} must be a whole number "
                           f"divisible by the scale factor {scale_factor}")
    ids = {t: tokenizer.convert_tokens_to_ids(t) for t in IDEFICS3_SPECIAL}
    image_seq_len = (image_size // patch_size) ** 2 // scale_factor**2
    config = Idefics3Config(
        image_token_id=ids["<image>"], pad_token_id=ids["<|im_end|>"], scale_factor=scale_factor,
        vision_config=dict(image_size=image_size, patch_size=patch_size, **vision),
        text_config=dict(model_type="llama", vocab_size=len(tokenizer), max_position_embeddings=4096,
                         pad_token_id=ids["<|im_end|>"], bos_token_id=ids["<|im_start|>"],
                         eos_token_id=ids["<end_of_utterance>"], tie_word_embeddings=False, **text),
    )
    torch.manual_seed(seed)
    model = Idefics3ForConditionalGeneration(config)
    set_generation_ids(model, tokenizer, ids["<end_of_utterance>"], ids["<|im_end|>"])
    image_processor = Idefics3ImageProcessor(
        do_image_splitting=False, size={"longest_edge": image_size}, max_image_size={"longest_edge": image_size})
    processor = Idefics3Processor(image_processor=image_processor, tokenizer=tokenizer,
                                  image_seq_len=image_seq_len, chat_template=IDEFICS3_CHAT_TEMPLATE)
    return model, processor


def build_tiny_qwen2vl(out_dir: str | Path, image_size: int = 224, hidden: int = 32, layers: int = 4,
                       seed: int = 0) -> Path:
    """Build and save a random-weight tiny Qwen2-VL with a Qwen2 tokenizer and its processor.

    `image_size` must be a multiple of 28 (patch 14 x spatial merge 2); an image costs
    (image_size / 28)^2 tokens (the default 224 px: 8 x 8, enough to resolve an 8 x 8 grid). Needs torchvision (the Qwen2-VL video processor).
    """
    import torch
    from transformers import (
        Qwen2TokenizerFast,
        Qwen2VLConfig,
        Qwen2VLForConditionalGeneration,
        Qwen2VLImageProcessor,
        Qwen2VLProcessor,
        Qwen2VLVideoProcessor,
    )

    if image_size % 28:
        raise DegustaError(f"image_size {image_size}: a tiny Qwen2-VL needs a multiple of 28")
    tokenizer = wrap_tokenizer(train_tokenizer(QWEN2VL_SPECIAL), Qwen2TokenizerFast, QWEN2VL_SPECIAL,
                      eos_token="<|im_end|>", pad_token="<|endoftext|>", unk_token=None)
    ids = {t: tokenizer.convert_tokens_to_ids(t) for t in QWEN2VL_SPECIAL}
    head_dim = hidden // 4
    config = Qwen2VLConfig(
        image_token_id=ids["<|image_pad|>"], video_token_id=ids["<|video_pad|>"],
        vision_start_token_id=ids["<|vision_start|>"], vision_end_token_id=ids["<|vision_end|>"],
        vision_config=dict(depth=2, embed_dim=32, hidden_size=hidden, num_heads=4, mlp_ratio=2, patch_size=14,
                           spatial_merge_size=2, temporal_patch_size=2),
        text_config=dict(vocab_size=len(tokenizer), hidden_size=hidden, intermediate_size=2 * hidden,
                         num_hidden_layers=layers, num_attention_heads=4, num_key_value_heads=2,
                         max_position_embeddings=4096, bos_token_id=None, eos_token_id=ids["<|im_end|>"],
                         pad_token_id=ids["<|endoftext|>"],
                         rope_scaling={"type": "mrope", "mrope_section": [head_dim // 4, head_dim // 8,
                                                                          head_dim // 8]}),
    )
    torch.manual_seed(seed)
    model = Qwen2VLForConditionalGeneration(config)
    set_generation_ids(model, tokenizer, ids["<|im_end|>"], ids["<|endoftext|>"])
    pixels = image_size * image_size
    image_processor = Qwen2VLImageProcessor(min_pixels=pixels, max_pixels=pixels)
    video_processor = Qwen2VLVideoProcessor(min_pixels=pixels, max_pixels=pixels)
    processor = Qwen2VLProcessor(image_processor=image_processor, tokenizer=tokenizer,
                                 video_processor=video_processor, chat_template=QWEN2VL_CHAT_TEMPLATE)
    return _save(out_dir, model, processor, "qwen2vl")


def ensure_tiny(path: str | Path, kind: str) -> Path:
    """Build the tiny model `kind` at `path` unless a current build is already there."""
    if kind not in TINY_KINDS:
        raise DegustaError(f"model.build_tiny: expected one of {list(TINY_KINDS)}, got {kind!r}")
    path = Path(path)
    marker = path / "degusta_tiny.json"
    if marker.is_file() and f'"version": {TINY_VERSION}' in marker.read_text():
        return path
    if path.exists() and any(path.iterdir()) and not marker.is_file():
        raise DegustaError(f"model.build_tiny: {path} exists and is not a tiny model built by degusta_learn; "
                           "choose another model.name or remove the folder")
    return (build_tiny_idefics3 if kind == "idefics3" else build_tiny_qwen2vl)(path)


def _save(out_dir, model, processor, kind: str) -> Path:
    from degusta_learn.vlm.load import quiet_transformers

    quiet_transformers()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model.save_pretrained(out)
    processor.save_pretrained(out)
    atomic_write_json(out / "degusta_tiny.json", {"kind": kind, "version": TINY_VERSION,
                                                 "note": "random weights, built offline by degusta_learn"})
    return out
