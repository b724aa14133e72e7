"""Full-size, random-weight replicas of the models the GPU fine-tuning configs use, built offline.

No pretrained weights can be downloaded in the development environment, yet the GPU configs
(`configs/finetune_smolvlm_256m.yaml`, `finetune_smolvlm_500m.yaml`, `finetune_qwen2vl_2b.yaml`) must be
checked at their real size: parameter counts, token budgets, memory and time per step. A replica has the
published ARCHITECTURE of the model (every size below) and its published processor settings, with random
weights. Every value is written down once, here, with its source.

Sources (architecture values are public configuration files, not weights):
  [S256]  HuggingFaceTB/SmolVLM-256M-Instruct: config.json, preprocessor_config.json, processor_config.json,
          generation_config.json, tokenizer files (Apache-2.0). A copy of the real files was read from the
          shared reference folder `reference-models/SmolVLM-256M-Instruct` (NOTES-VLM.md): 256.5 M parameters.
  [S500]  HuggingFaceTB/SmolVLM-500M-Instruct: config.json / processor files (not available offline here).
          Its text model is SmolLM2-360M (hidden 960, 32 layers, 15 heads, 5 kv heads, intermediate 2560:
          cross-checked in several public repositories that pin SmolLM2-360M's config.json); vision tower,
          scale factor, image_seq_len, vocabulary (49,280 ids, the same SmolVLM tokenizer with image
          token 49190) and processor settings are those of [S256] (the SmolVLM report builds both models
          on the same SigLIP-B/16-512 tower with pixel shuffle 4). Check: the replica has 507.5 M
          parameters, the published "507M" of the model card.
  [Q2B]   Qwen/Qwen2-VL-2B(-Instruct): config.json / preprocessor_config.json (Apache-2.0). Sizes as printed in
          the model's module tree and config (hidden 1536, 28 layers, 12 heads, 2 kv heads, intermediate
          8960, vocab 151,936, tied embeddings, mrope sections [16, 24, 24]; vision depth 32, embed 1280,
          16 heads, mlp_ratio 4, patch 14, merge 2, temporal patch 2); special-token ids from its
          tokenizer_config.json; preprocessor min_pixels 56*56 = 3,136 and max_pixels 28*28*16,384 =
          12,845,056. Check: model.safetensors.index.json of Qwen2-VL-2B lists total_size 4,417,971,200
          bytes of bf16 = 2,208,985,600 parameters; the replica has exactly that many.

Tokenizers: where the real tokenizer files are at hand (`reference_dir`, SmolVLM-256M's folder, also used
for SmolVLM-500M, whose tokenizer is the same) the replica uses them, so text token counts are exact.
Otherwise it uses the project's offline tiny byte-level BPE (`common.train_tokenizer`, ~1,000 ids trained
on the task's own texts) and keeps the published vocab_size for the embedding and LM head, so parameter
counts and memory stay exact. What changes with the tiny tokenizer: IMAGE tokens are unchanged (set by the
image processor: patches and merge/pixel-shuffle), but TEXT and ANSWER token counts differ from the real
tokenizer's (measured for SmolVLM-256M in benchmarks/RESULTS.md, "Full-size replicas"); Qwen2-VL-2B
counts are therefore approximate in their text part.

Usage:
    from degusta_learn.vlm.random_models.replicas import build_replica
    build_replica("smolvlm_256m", "/tmp/repl/smolvlm_256m",
                  reference_dir="../shared/reference-models/SmolVLM-256M-Instruct")
    # then: degusta train --config configs/finetune_smolvlm_256m.yaml --set model.name=/tmp/repl/smolvlm_256m ...
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import atomic_write_json

REPLICA_VERSION = 1

_SMOLVLM_VISION = dict(  # [S256] vision_config: SigLIP-B/16 at 512 px
    hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
    patch_size=16, image_size=512, hidden_act="gelu_pytorch_tanh", layer_norm_eps=1e-6)
_SMOLVLM_PROCESSOR = dict(  # [S256] preprocessor_config.json + processor_config.json
    image_seq_len=64, do_image_splitting=True, size={"longest_edge": 2048},
    max_image_size={"longest_edge": 512}, image_mean=[0.5, 0.5, 0.5], image_std=[0.5, 0.5, 0.5], resample=1)
_SMOLVLM_IDS = dict(image_token_id=49190, bos_token_id=1, eos_token_id=2, pad_token_id=2,  # [S256] config.json
                    generation_eos_token_id=49279, generation_bos_token_id=0)  # [S256] generation_config.json


def _smolvlm(size: str, source: str, params: int, params_source: str, **text) -> dict:
    """A SmolVLM entry: the 256M and 500M share the SigLIP tower, processor and ids; only the text model differs."""
    return {
        "hub_id": f"HuggingFaceTB/SmolVLM-{size.upper()}-Instruct", "family": "idefics3",
        "configs": [f"configs/finetune_smolvlm_{size}.yaml"], "source": source,
        "published_params": params, "published_params_source": params_source, "scale_factor": 4,
        "text": dict(head_dim=64, vocab_size=49280, max_position_embeddings=8192, rope_theta=100000.0,
                     rms_norm_eps=1e-5, tie_word_embeddings=False, **text),
        "vision": _SMOLVLM_VISION, "processor": _SMOLVLM_PROCESSOR, "ids": _SMOLVLM_IDS,
    }


REPLICAS: dict[str, dict] = {
    "smolvlm_256m": _smolvlm("256m", "S256", 256_484_928, "[S256] meta-device build of the real config.json",
                             hidden_size=576, intermediate_size=1536, num_hidden_layers=30, num_attention_heads=9,
                             num_key_value_heads=3),
    "smolvlm_500m": _smolvlm("500m", "S500", 507_000_000, "[S500] model card: 507M",
                             hidden_size=960, intermediate_size=2560, num_hidden_layers=32, num_attention_heads=15,
                             num_key_value_heads=5),
    "qwen2vl_2b": {
        "hub_id": "Qwen/Qwen2-VL-2B-Instruct", "family": "qwen2vl",
        "configs": ["configs/finetune_qwen2vl_2b.yaml"], "source": "Q2B",
        "published_params": 2_208_985_600,
        "published_params_source": "[Q2B] model.safetensors.index.json total_size 4,417,971,200 B / 2 (bf16)",
        "text": dict(hidden_size=1536, intermediate_size=8960, num_hidden_layers=28, num_attention_heads=12,
                     num_key_value_heads=2, vocab_size=151936, max_position_embeddings=32768,
                     rope_theta=1000000.0, rms_norm_eps=1e-6, tie_word_embeddings=True,
                     rope_scaling={"type": "mrope", "mrope_section": [16, 24, 24]}),
        "vision": dict(depth=32, embed_dim=1280, hidden_size=1536, num_heads=16, mlp_ratio=4, in_channels=3,
                       patch_size=14, spatial_merge_size=2, temporal_patch_size=2, hidden_act="quick_gelu"),
        "processor": dict(min_pixels=3136, max_pixels=12845056, patch_size=14, merge_size=2,
                          temporal_patch_size=2),
        "ids": dict(image_token_id=151655, video_token_id=151656, vision_start_token_id=151652,
                    vision_end_token_id=151653, bos_token_id=151643, eos_token_id=151645, pad_token_id=151643),
    },
}
"""Published architecture and processor values per replica (see the module docstring for the sources)."""


def replica_spec(name: str, key: str = "replica") -> dict:
    """The REPLICAS entry `name`; an unknown name is a one-line DegustaError naming `key`."""
    if name not in REPLICAS:
        raise DegustaError(f"{key}: unknown model family {name!r}; expected one of {sorted(REPLICAS)}")
    return REPLICAS[name]


def replica_config(name: str, tokenizer=None, key: str = "replica"):
    """The transformers config of replica `name`. With `tokenizer` (not the real one) the special-token ids
    are that tokenizer's; the vocab size stays the published one (exact parameter count)."""
    spec = replica_spec(name, key)
    ids = dict(spec["ids"])
    if tokenizer is not None:
        ids = _tokenizer_ids(spec["family"], tokenizer)
    if spec["family"] == "idefics3":
        from transformers import Idefics3Config

        return Idefics3Config(
            image_token_id=ids["image_token_id"], pad_token_id=ids["pad_token_id"], scale_factor=spec["scale_factor"],
            tie_word_embeddings=spec["text"]["tie_word_embeddings"], vision_config=dict(spec["vision"]),
            text_config=dict(model_type="llama", pad_token_id=ids["pad_token_id"], bos_token_id=ids["bos_token_id"],
                             eos_token_id=ids["eos_token_id"], **spec["text"]))
    from transformers import Qwen2VLConfig

    return Qwen2VLConfig(
        image_token_id=ids["image_token_id"], video_token_id=ids["video_token_id"],
        vision_start_token_id=ids["vision_start_token_id"], vision_end_token_id=ids["vision_end_token_id"],
        tie_word_embeddings=spec["text"]["tie_word_embeddings"], vision_config=dict(spec["vision"]),
        text_config=dict(bos_token_id=ids["bos_token_id"], eos_token_id=ids["eos_token_id"],
                         pad_token_id=ids["pad_token_id"], **spec["text"]))


def meta_replica(name: str, key: str = "replica"):
    """Replica `name` built on the meta device (shapes only, no memory): for parameter counts."""
    import torch
    from transformers import AutoModelForImageTextToText

    config = replica_config(name, key=key)
    with torch.device("meta"):
        return AutoModelForImageTextToText.from_config(config)


def _tokenizer_ids(family: str, tok) -> dict:
    c = tok.convert_tokens_to_ids
    if family == "idefics3":
        return dict(image_token_id=c("<image>"), bos_token_id=c("<|im_start|>"), eos_token_id=c("<end_of_utterance>"),
                    pad_token_id=c("<|im_end|>"), generation_eos_token_id=c("<end_of_utterance>"),
                    generation_bos_token_id=c("<|im_start|>"))
    return dict(image_token_id=c("<|image_pad|>"), video_token_id=c("<|video_pad|>"),
                vision_start_token_id=c("<|vision_start|>"), vision_end_token_id=c("<|vision_end|>"),
                bos_token_id=None, eos_token_id=c("<|im_end|>"), pad_token_id=c("<|endoftext|>"))


@contextlib.contextmanager
def _default_dtype(dtype):
    import torch

    old = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(old)


def build_replica(name: str, out_dir: str | Path, reference_dir: str | Path | None = None, seed: int = 0,
                  key: str = "replica", weights: bool = True) -> Path:
    """Build replica `name` (random bf16 weights, published sizes) with its processor; save it like a hub model.

    Args:
        name: a key of REPLICAS ("smolvlm_256m", "smolvlm_500m", "qwen2vl_2b").
        out_dir: folder to write (created).
        reference_dir: a folder holding the model family's REAL tokenizer / processor files (SmolVLM-256M's
            also serves SmolVLM-500M); None: the offline tiny tokenizer (text token counts then differ).
        seed: weight initialisation seed.
        weights: False writes the config and processor only (enough for `degusta train --dry-run`: seconds,
            no memory), not a loadable model.

    Returns:
        `out_dir` as a Path, loadable with `load_vlm` and usable as `model.name`.
    """
    import torch
    from transformers import AutoModelForImageTextToText

    from degusta_learn.vlm.load import quiet_transformers

    quiet_transformers()
    spec = replica_spec(name, key)
    processor, real = _processor(spec, reference_dir, key)
    tok = processor.tokenizer
    config = replica_config(name, None if real else tok, key)
    ids = spec["ids"] if real else _tokenizer_ids(spec["family"], tok)
    torch.manual_seed(seed)
    with _default_dtype(torch.bfloat16), (contextlib.nullcontext() if weights else torch.device("meta")):
        model = AutoModelForImageTextToText.from_config(config)  # bf16: the published torch_dtype
    gc = model.generation_config
    gc.eos_token_id = ids.get("generation_eos_token_id", ids["eos_token_id"])
    gc.bos_token_id = ids.get("generation_bos_token_id", ids["bos_token_id"])
    gc.pad_token_id = ids["pad_token_id"]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if weights:
        model.save_pretrained(out)
    else:
        model.config.save_pretrained(out)
        gc.save_pretrained(out)
    processor.save_pretrained(out)
    n = sum(p.numel() for p in model.parameters())
    del model
    atomic_write_json(out / "degusta_replica.json", {
        "replica": name, "hub_id": spec["hub_id"], "version": REPLICA_VERSION, "parameters": n, "weights": weights,
        "tokenizer": "real" if real else "tiny offline BPE (text token counts differ from the real model's)",
        "note": "random weights, published architecture, built offline by degusta_learn.vlm.random_models.replicas"})
    return out


def _processor(spec: dict, reference_dir, key: str):
    """(processor with the published settings, True when it carries the real tokenizer)."""
    from degusta_learn.vlm.random_models import tiny
    from degusta_learn.vlm.random_models.common import train_tokenizer, wrap_tokenizer

    ps = spec["processor"]
    if reference_dir is not None:
        ref = Path(reference_dir)
        cfg = ref / "config.json"
        if not cfg.is_file():
            raise DegustaError(f"{key}: reference folder {ref} has no config.json")
        family = {"idefics3": "idefics3", "qwen2_vl": "qwen2vl"}.get(json.loads(cfg.read_text()).get("model_type"))
        if family != spec["family"]:
            raise DegustaError(f"{key}: reference folder {ref} holds a {family or 'foreign'} model, not {spec['family']}")
        from transformers import AutoProcessor

        processor = AutoProcessor.from_pretrained(str(ref), local_files_only=True)
        processor.tokenizer.model_input_names = ["input_ids", "attention_mask"]
        if spec["family"] == "idefics3":  # the published settings (the files' own, set again to be sure)
            ip = processor.image_processor
            ip.do_image_splitting, ip.size, ip.max_image_size = (ps["do_image_splitting"], dict(ps["size"]),
                                                                dict(ps["max_image_size"]))
            processor.image_seq_len = ps["image_seq_len"]
        return processor, True
    if spec["family"] == "idefics3":
        from transformers import Idefics3ImageProcessor, Idefics3Processor, PreTrainedTokenizerFast

        tok = wrap_tokenizer(train_tokenizer(tiny.IDEFICS3_SPECIAL), PreTrainedTokenizerFast, tiny.IDEFICS3_SPECIAL,
                         **tiny.IDEFICS3_ROLES)
        ip = Idefics3ImageProcessor(do_image_splitting=ps["do_image_splitting"], size=dict(ps["size"]),
                                    max_image_size=dict(ps["max_image_size"]), image_mean=ps["image_mean"],
                                    image_std=ps["image_std"], resample=ps["resample"])
        return Idefics3Processor(image_processor=ip, tokenizer=tok, image_seq_len=ps["image_seq_len"],
                                 chat_template=tiny.IDEFICS3_CHAT_TEMPLATE), False
    from transformers import (
        Qwen2TokenizerFast,
        Qwen2VLImageProcessor,
        Qwen2VLProcessor,
        Qwen2VLVideoProcessor,
    )

    tok = wrap_tokenizer(train_tokenizer(tiny.QWEN2VL_SPECIAL), Qwen2TokenizerFast, tiny.QWEN2VL_SPECIAL,
                     eos_token="<|im_end|>", pad_token="<|endoftext|>", unk_token=None)
    common = dict(min_pixels=ps["min_pixels"], max_pixels=ps["max_pixels"], patch_size=ps["patch_size"],
                  merge_size=ps["merge_size"], temporal_patch_size=ps["temporal_patch_size"])
    return Qwen2VLProcessor(image_processor=Qwen2VLImageProcessor(**common), tokenizer=tok,
                            video_processor=Qwen2VLVideoProcessor(**common),
                            chat_template=tiny.QWEN2VL_CHAT_TEMPLATE), False
