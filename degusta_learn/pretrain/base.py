"""The architecture of the tiny base VLM: a FastVLM (convolutional vision tower + Qwen2 decoder), tiny.

Why not SmolVLM's Idefics3 (a ViT tower)? Trained from random weights on this CPU, a ViT tower barely
learns to see small objects on textured tables: on the dense "which objects cover this cell" probe it
stays near the label prior after 20,000 images, where a small ResNet of the same cost is far below it
after 2,000 (docs/finetune.md, "Why the tiny base is a FastVLM"). ViTs lack the locality bias that
makes a CNN learn from little data; a pretrained SmolVLM brings its vision from billions of images.
FastVLM (Apple, CVPR 2025; `FastVlmForConditionalGeneration` in transformers) is the real architecture
built around a convolutional tower: any timm backbone (`TimmWrapperConfig`), its last feature map
flattened into image tokens, a 2-layer projector, a Qwen2 decoder.

Sizes: 256 px images through a ResNet (output stride 32) give an 8 x 8 feature map: 64 image tokens,
one per ~cell of the 8 x 8 grid (a GMA cell is 29 px at 256 px). The tokenizer is the domain tokenizer
(`pretrain.vocab`: ids, cells and answer literals are single tokens) with a Qwen-style chat template.

The decoder starts from an init made for copying (`tie_embeddings`, `attention_init: mimetic`,
`class_init`): tied input and output embeddings, attention heads whose queries match keys like
themselves and whose value-output maps copy, and one shared direction per class of answer tokens, so a
rare object id behaves like the other ids from the first step.

Example:
    model, processor = build_base(BaseArchitecture(), seed=0)    # random weights, ~5 M parameters
"""

from __future__ import annotations

from degusta_learn.vlm.random_models.fastvlm import OUTPUT_STRIDE, BaseArchitecture

SPECIAL = ["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<image>"]
ROLES = dict(eos_token="<|im_end|>", pad_token="<|endoftext|>", unk_token=None)
MIMETIC_QK_STD, MIMETIC_V_STD, MIMETIC_OV_GAIN = 0.06, 0.06, 0.25  # the pilot's values (docs/tiny_base.md)
# Qwen2-VL-Instruct's chat template without system prompt and video branch; <image> expands to the tokens.
CHAT_TEMPLATE = (
    "{% for message in messages %}<|im_start|>{{ message['role'] }}\n{% if message['content'] is string %}"
    "{{ message['content'] }}{% else %}{% for c in message['content'] %}{% if c['type'] == 'image' %}<image>"
    "{% elif c['type'] == 'text' %}{{ c['text'] }}{% endif %}{% endfor %}{% endif %}<|im_end|>\n{% endfor %}"
    "{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)


def token_classes(tokenizer) -> list[list[int]]:
    """Ids of the single-token members of each answer token class: object types, numbers 0-255, grid cells
    (up to 12 x 12), directions. (Types are the default catalog's; a word split into pieces is left out.)"""
    from degusta_learn.render.grid import DIRECTIONS
    from degusta_learn.scene import default_catalog

    words = [list(default_catalog().types), [str(i) for i in range(256)],
             [f"{chr(65 + c)}{r}" for c in range(12) for r in range(1, 13)], list(DIRECTIONS)]
    classes = []
    for members in words:
        ids = [tokenizer.encode(w, add_special_tokens=False) for w in members]
        classes.append([i[0] for i in ids if len(i) == 1])
    return classes


def init_token_classes(model, tokenizer, scale: float) -> None:
    """Add one shared random direction per token class (`token_classes`) to its members' input and output
    embeddings, `scale` times the model's init std: rare tokens such as object ids then share what the
    decoder learns about their class from the first steps (where a number sits, that it is copied)."""
    import torch

    std = model.config.get_text_config().initializer_range
    tables = [model.get_input_embeddings().weight, model.get_output_embeddings().weight]
    if tables[1] is tables[0]:  # tied: one table
        tables = tables[:1]
    with torch.no_grad():
        for members in token_classes(tokenizer):
            if not members:
                continue
            for weight in tables:
                weight[members] += scale * std * torch.randn(1, weight.shape[1])


def mimetic_attention(model) -> None:
    """Mimetic initialization of every decoder attention layer: W_q = W_k + noise (a head's query matches
    keys like itself) and W_o = W_v^T scaled so that W_v W_o is about MIMETIC_OV_GAIN times a projection
    (it copies what it attends to). With grouped-query attention the heads of a group share its W_k, W_v."""
    import torch

    text = model.config.get_text_config()
    heads, kv = text.num_attention_heads, text.num_key_value_heads
    d = text.hidden_size // heads
    layers = model.model.language_model.layers
    with torch.no_grad():
        for layer in layers:
            attn = layer.self_attn
            attn.k_proj.weight.normal_(0.0, MIMETIC_QK_STD)
            attn.v_proj.weight.normal_(0.0, MIMETIC_V_STD)
            for h in range(heads):
                g = slice((h // (heads // kv)) * d, (h // (heads // kv) + 1) * d)
                attn.q_proj.weight[h * d:(h + 1) * d] = attn.k_proj.weight[g] + text.initializer_range * \
                    torch.randn(d, text.hidden_size)
                attn.o_proj.weight[:, h * d:(h + 1) * d] = attn.v_proj.weight[g].T * (
                    MIMETIC_OV_GAIN / (MIMETIC_V_STD**2 * d))


def previous_token_head(model, head: int = 0, pairs: int = 8, margin: float = 12.0) -> None:
    """Make `head` of the first decoder layer attend to the previous position, whatever the tokens: its
    query and key weights are zeroed and their biases set on the `pairs` fastest rotary frequencies, the
    key's rotated one step ahead, so that with RoPE the score is sum_i c cos((m - n - 1) theta_i): largest at
    n = m - 1, `margin` logits above every other position up to the model's maximum length. The heads that
    share its key group stop reading those key dimensions (their query weights there are zeroed). The
    value/output maps are left as they are (mimetic init: they copy). Qwen2 has q/k biases; this assumes it."""
    import math

    import numpy as np
    import torch

    text = model.config.get_text_config()
    heads, kv = text.num_attention_heads, text.num_key_value_heads
    d = text.hidden_size // heads
    theta = float(text.rope_parameters["rope_theta"])
    pairs = min(pairs, d // 4)  # the heads sharing its key group keep at least half their dimensions
    freqs = [theta ** (-2 * i / d) for i in range(pairs)]
    offsets = np.arange(text.max_position_embeddings, dtype=np.float64)  # m - n: 0 (itself), 1, 2, ... (numpy:
    score = sum(np.cos((offsets - 1) * f) for f in freqs)  # also under a meta-device build); per unit of c
    c = margin * math.sqrt(d) / float(score[1] - np.delete(score, 1).max())  # aliasing far back included
    attn = model.model.language_model.layers[0].self_attn
    group = head // (heads // kv)
    rows = list(range(pairs)) + [i + d // 2 for i in range(pairs)]  # RoPE pairs dims (i, i + d/2)
    with torch.no_grad():
        attn.q_proj.weight[head * d:(head + 1) * d] = 0.0
        attn.q_proj.bias[head * d:(head + 1) * d] = 0.0
        for h in range(group * (heads // kv), (group + 1) * (heads // kv)):
            attn.q_proj.weight[[h * d + r for r in rows]] = 0.0
            attn.q_proj.bias[[h * d + r for r in rows]] = 0.0
        attn.k_proj.weight[[group * d + r for r in rows]] = 0.0
        for i, f in enumerate(freqs):
            attn.q_proj.bias[head * d + i] = math.sqrt(c)
            attn.k_proj.bias[group * d + i] = math.sqrt(c) * math.cos(f)
            attn.k_proj.bias[group * d + i + d // 2] = math.sqrt(c) * math.sin(f)


def build_base(arch: BaseArchitecture, seed: int = 0):
    """(random-weight FastVlmForConditionalGeneration, LlavaProcessor with the domain tokenizer) per `arch`."""
    import torch
    from transformers import (
        CLIPImageProcessor,
        FastVlmConfig,
        FastVlmForConditionalGeneration,
        LlavaProcessor,
        PreTrainedTokenizerFast,
        TimmWrapperConfig,
    )

    from degusta_learn.pretrain.vocab import domain_tokenizer
    from degusta_learn.vlm.random_models.common import set_generation_ids, wrap_tokenizer

    tokenizer = wrap_tokenizer(domain_tokenizer(SPECIAL, arch.vocab_size), PreTrainedTokenizerFast, SPECIAL, **ROLES)
    ids = {t: tokenizer.convert_tokens_to_ids(t) for t in SPECIAL}
    vision = TimmWrapperConfig(architecture="resnet18", do_pooling=False, hidden_size=arch.vision_channels[-1],
                               model_args={"channels": list(arch.vision_channels), "layers": list(arch.vision_layers),
                                           "stem_width": arch.vision_stem})
    config = FastVlmConfig(
        vision_config=vision, image_token_index=ids["<image>"], image_seq_length=arch.tokens_per_image,
        text_config=dict(model_type="qwen2", vocab_size=len(tokenizer), hidden_size=arch.text_hidden,
                         intermediate_size=arch.text_intermediate, num_hidden_layers=arch.text_layers,
                         num_attention_heads=arch.text_heads, num_key_value_heads=arch.text_kv_heads,
                         max_position_embeddings=4096, bos_token_id=None, eos_token_id=ids["<|im_end|>"],
                         pad_token_id=ids["<|endoftext|>"], tie_word_embeddings=arch.tie_embeddings),
        tie_word_embeddings=arch.tie_embeddings)
    torch.manual_seed(seed)
    model = FastVlmForConditionalGeneration(config)
    if arch.attention_init == "mimetic":
        mimetic_attention(model)
    if arch.class_init > 0:
        init_token_classes(model, tokenizer, arch.class_init)
    if arch.previous_token_head:
        previous_token_head(model)
    set_generation_ids(model, tokenizer, ids["<|im_end|>"], ids["<|endoftext|>"])
    side = {"height": arch.image_size, "width": arch.image_size}
    image_processor = CLIPImageProcessor(size=dict(side), crop_size=dict(side), do_center_crop=False,
                                         image_mean=[0.5, 0.5, 0.5], image_std=[0.5, 0.5, 0.5])
    processor = LlavaProcessor(image_processor=image_processor, tokenizer=tokenizer, patch_size=OUTPUT_STRIDE,
                               vision_feature_select_strategy="full", image_token="<image>",
                               num_additional_image_tokens=0, chat_template=CHAT_TEMPLATE)
    return model, processor
