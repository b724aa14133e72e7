"""Bounds on every size a model or adapter folder states, checked before anything is built or allocated.

A model folder is data from whoever made it, and its JSON files size what the libraries build: transformers makes
`num_hidden_layers` layers (a million take hours to construct) and initialises at random every weight the files
lack (a config with a thousand layers over the weights of two allocates the other 998); the image processor resizes
every image to its `longest_edge` (a million pixels a side: terabytes); peft allocates every LoRA matrix at the
config's `r` before it reads the weights; a regex in `target_modules` is matched against every module name.

`check_folder` (called by `hub.check_json_files`, so by every model and adapter load, the dry run included) refuses,
in one line naming the file, the key and the bound:

- a JSON file larger than `MAX_JSON_FILE_BYTES` (`tokenizer.json`: `MAX_TOKENIZER_BYTES`), before it is read;
- in `config.json` (every nested sub-config): layer, head, width, vocabulary, position, image, patch and expert
  sizes beyond `CONFIG_BOUNDS` (the largest real models, with a wide margin: e.g. at most 1,024 layers, 65,536
  hidden units, 2^21 tokens, 2^24 positions, 8,192 px images, 2^18 patches an image);
- in `preprocessor_config.json` / `processor_config.json`: image edges beyond 4,096 px (pixel counts beyond 2^24
  for the Qwen and GLM processors, whose `size` is an area), image tokens beyond 2^16 an image (also as derived
  from the sizes and the model's patches), tiles, frames;
- in `generation_config.json`: `max_new_tokens`, `max_length`, beams, returned sequences, n-gram sizes;
- in `adapter_config.json`: `r` and the `rank_pattern` ranks beyond 4,096 (as `lora.r`), `lora_alpha` beyond
  10^6, more than 10,000 target modules or patterns, module names that are not names where peft pastes them into
  a regex, `layer_replication`, LoftQ iterations;
- chat templates (`chat_template.jinja`, `chat_template.json`, `tokenizer_config.json`, `processor_config.json`)
  that break the rendering bounds of `vlm/chat_template.py` on a plain conversation.

Then, with the weights at hand and still before anything is allocated:

- `check_weights` (called by `load_vlm`): the model config.json describes is built on PyTorch's meta device
  (no memory) and its parameters are counted; more than the safetensors files hold (their headers give the
  shapes without reading any data) by over 10% + 4M is refused: weights would be made up at random;
- `check_adapter` (called by `load_adapter`): a rank above the largest rank of the adapter's safetensors is
  refused, and regex `target_modules`, `exclude_modules` and `rank_pattern` / `alpha_pattern` keys are matched
  against the model's module names here, with a time limit (`regex` module), and handed to peft as the exact
  names they match (peft would otherwise run Python's `re`, which has no time limit, on them).
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from pathlib import Path
from typing import Any

from degusta_learn.errors import DegustaError

MAX_JSON_FILE_BYTES = 16 * 2**20
"""Largest model or adapter JSON file (real configs are a few KB; tokenizer_config.json with its added tokens ~1 MB)."""
MAX_TOKENIZER_BYTES = 64 * 2**20
"""Largest tokenizer.json (the largest real vocabularies, Gemma 3 and Llama 4, are ~35 MB)."""
MAX_TEMPLATE_FILE_BYTES = 4 * 2**20
"""Largest chat_template.jinja / chat_template.json."""
MAX_SAFETENSORS_HEADER = 100 * 2**20
"""Largest safetensors header (the safetensors library's own limit)."""
MAX_IMAGE_EDGE = 4096
"""Longest image side an image processor may resize to (the toolkit's image sizes stop there too)."""
MAX_IMAGE_PIXELS = 2**24
"""Largest image area (Qwen's and GLM's `size`, `max_pixels`: Qwen2-VL's default is 12,845,056)."""
MAX_IMAGE_TOKENS = 2**16
"""Most image tokens one image may cost (Qwen2-VL at its default maximum: 16,384)."""
MAX_PATCHES = 2**18
"""Most vision patches (position embeddings) of one image in config.json: (image_size / patch_size)^2."""
MAX_LAYER_EXPERTS = 2**16
"""Most layers x experts (Kimi K2: 61 x 384 = 23,424)."""
MAX_TARGETS = 10_000
"""Most target modules, excluded modules, modules to save and rank / alpha patterns of an adapter."""
MAX_PARAMETER_SLACK = 0.10, 2**22
"""How many more parameters config.json may describe than its weights hold: 10% + 4M (a head initialised anew)."""
MAX_BUFFER_ELEMENTS = 2**26
"""Most elements of the buffers a model config describes (position ids, rotary tables): 256 MB in float32."""
REGEX_SECONDS = 2.0
"""Time limit of matching an adapter's regexes against the module names of the model."""

_LAYERS, _WIDTH, _FFN, _HEADS = (0, 1024), (1, 65_536), (1, 2**19), (1, 1024)
CONFIG_BOUNDS: dict[str, tuple[int, int]] = {
    **dict.fromkeys(("num_hidden_layers", "num_layers", "n_layer", "n_layers", "depth", "encoder_layers",
                     "decoder_layers", "num_encoder_layers", "num_decoder_layers", "depths"), _LAYERS),
    **dict.fromkeys(("hidden_size", "embed_dim", "d_model", "n_embd", "hidden_dim", "projection_dim",
                     "vision_embed_dim", "text_embed_dim", "mm_hidden_size", "hidden_sizes", "embed_dims",
                     "num_channels", "in_channels", "out_hidden_size"), _WIDTH),
    **dict.fromkeys(("intermediate_size", "ffn_dim", "n_inner", "mlp_dim", "moe_intermediate_size",
                     "shared_expert_intermediate_size", "encoder_ffn_dim", "decoder_ffn_dim"), _FFN),
    **dict.fromkeys(("num_attention_heads", "num_heads", "n_head", "num_key_value_heads", "num_kv_heads",
                     "encoder_attention_heads", "decoder_attention_heads"), _HEADS),
    **dict.fromkeys(("head_dim", "kv_channels"), (1, 8192)),
    "vocab_size": (1, 2**21),
    **dict.fromkeys(("max_position_embeddings", "n_positions", "max_sequence_length", "seq_length",
                     "original_max_position_embeddings"), (1, 2**24)),
    "image_size": (1, 8192),
    "patch_size": (1, 1024),
    **dict.fromkeys(("scale_factor", "spatial_merge_size", "temporal_patch_size", "merge_size"), (1, 64)),
    **dict.fromkeys(("image_seq_length", "image_seq_len", "mm_tokens_per_image", "num_image_tokens",
                     "num_query_tokens"), (1, MAX_IMAGE_TOKENS)),
    **dict.fromkeys(("num_experts", "num_local_experts", "n_routed_experts", "moe_num_experts"), (1, 4096)),
    **dict.fromkeys(("num_experts_per_tok", "n_shared_experts"), (0, 4096)),
    **dict.fromkeys(("num_labels", "num_classes"), (0, 2**17)),
}
"""config.json keys (in any sub-config) and their bounds; an integer or a list of integers, or null."""
_FLOAT_OK = {"scale_factor"}  # a factor some families write as a float
_TIMM_ARGS = {"channels": _WIDTH, "layers": _LAYERS, "stem_width": _WIDTH}  # a timm tower's `model_args`

_AREA_FAMILIES = ("qwen", "glm")
"""Image processors whose `size` (`longest_edge`, `shortest_edge`) is a number of pixels, not a side."""
_EDGE_KEYS = {"longest_edge", "shortest_edge", "height", "width", "max_height", "max_width"}
PROCESSOR_BOUNDS: dict[str, tuple[int, int]] = {
    **dict.fromkeys(("max_pixels", "min_pixels"), (1, MAX_IMAGE_PIXELS)),
    **dict.fromkeys(("image_seq_len", "image_seq_length", "num_image_tokens", "mm_tokens_per_image",
                     "num_additional_image_tokens"), (0, MAX_IMAGE_TOKENS)),
    "patch_size": (1, 1024),
    **dict.fromkeys(("merge_size", "temporal_patch_size", "spatial_merge_size", "scale_factor"), (1, 64)),
    **dict.fromkeys(("max_image_tiles", "max_num_tiles", "max_patches", "max_dynamic_patch", "min_dynamic_patch",
                     "max_num_crops"), (0, 1024)),
    **dict.fromkeys(("max_frames", "min_frames", "num_frames"), (0, 2**16)),
    "max_video_tokens": (0, 2**20),
}
GENERATION_BOUNDS: dict[str, tuple[int, int]] = {
    "max_new_tokens": (0, 2**20), "min_new_tokens": (0, 2**20), "max_length": (0, 2**24), "min_length": (0, 2**24),
    "num_beams": (1, 64), "num_beam_groups": (1, 64), "num_return_sequences": (1, 64), "top_k": (0, 2**21),
    "no_repeat_ngram_size": (0, 1024), "encoder_no_repeat_ngram_size": (0, 1024), "num_assistant_tokens": (0, 1024),
    "prompt_lookup_num_tokens": (0, 1024), "max_matching_ngram_size": (0, 1024), "max_cache_len": (1, 2**24),
}
_PLAIN_NAME = re.compile(r"^[\w.\-]{1,200}$")
_TEMPLATE_FILES = ("chat_template.jinja", "chat_template.json")


def _refuse(key: str, path: Path, what: str) -> DegustaError:
    return DegustaError(f"{key}: {path}: {what}"[:600])


def _show(value: Any) -> str:
    if isinstance(value, int) and not isinstance(value, bool):
        return f"{value:,}" if value.bit_length() < 200 else f"an integer of {len(str(value))} digits"
    text = json.dumps(value) if isinstance(value, (str, list, dict, bool, type(None))) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _check_number(value: Any, bounds: tuple[int, int], name: str, key: str, path: Path, floats: bool = False,
                  why: str = "beyond what a real model has") -> None:
    """`value`: null, an integer (a finite float where `floats`) or a list of them, each within `bounds`."""
    lo, hi = bounds
    items = value if isinstance(value, list) else [value]
    if len(items) > 4096:
        raise _refuse(key, path, f"{name} lists {len(items):,} values (at most 4,096)")
    for v in items:
        if v is None and not isinstance(value, list):
            continue
        ok = isinstance(v, int) and not isinstance(v, bool) or floats and isinstance(v, float) and math.isfinite(v)
        if not ok:
            raise _refuse(key, path, f"{name} is {_show(v)}, expected {'a number' if floats else 'an integer'}"
                                     f" from {lo:,} to {hi:,}")
        if not lo <= v <= hi:
            raise _refuse(key, path, f"{name} is {_show(v)}, {why} (expected {lo:,} to {hi:,})")


def _walk(data: Any, prefix: str = ""):
    """(dotted name, key, value) of every entry of nested dicts (dicts inside lists included)."""
    stack = [(data, prefix)]
    while stack:
        node, at = stack.pop()
        if isinstance(node, dict):
            for k, v in node.items():
                name = f"{at}.{k}" if at else str(k)
                yield name, k, v
                if isinstance(v, (dict, list)):
                    stack.append((v, name))
        elif isinstance(node, list):
            for i, v in enumerate(node[:4096]):
                if isinstance(v, (dict, list)):
                    stack.append((v, f"{at}[{i}]"))


def check_config(data: dict, path: Path, key: str) -> None:
    """config.json: every size key within CONFIG_BOUNDS, patches per image within MAX_PATCHES, layers x experts."""
    for name, k, v in _walk(data):
        if k in CONFIG_BOUNDS and not isinstance(v, dict):
            _check_number(v, CONFIG_BOUNDS[k], name, key, path, floats=k in _FLOAT_OK)
        elif k == "model_args" and isinstance(v, dict):
            for arg, bounds in _TIMM_ARGS.items():
                if arg in v:
                    _check_number(v[arg], bounds, f"{name}.{arg}", key, path)
    for where, _, v in _walk({"": data}):
        if not isinstance(v, dict):
            continue
        image, patch = v.get("image_size"), v.get("patch_size")
        if _int(image) and _int(patch) and patch > 0 and (image // patch) ** 2 > MAX_PATCHES:
            raise _refuse(key, path, f"{where + '.' if where else ''}image_size {image:,} / patch_size {patch:,} "
                                     f"gives {(image // patch) ** 2:,} patches an image (at most {MAX_PATCHES:,})")
        layers = next((v[x] for x in ("num_hidden_layers", "num_layers", "depth") if _int(v.get(x))), None)
        experts = next((v[x] for x in ("num_experts", "num_local_experts", "n_routed_experts") if _int(v.get(x))), None)
        if layers and experts and layers * experts > MAX_LAYER_EXPERTS:
            raise _refuse(key, path, f"{where + ': ' if where else ''}{layers:,} layers x {experts:,} experts "
                                     f"(at most {MAX_LAYER_EXPERTS:,} in all)")


def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _area_family(processor: dict, outer: dict) -> bool:
    names = " ".join(str(d.get(k, "")) for d in (processor, outer)
                     for k in ("image_processor_type", "processor_class", "video_processor_type")).lower()
    return any(f in names for f in _AREA_FAMILIES)


def check_processor(data: dict, path: Path, key: str) -> None:
    """preprocessor_config.json / processor_config.json: image sides (or areas), tokens, tiles and frames."""
    parts = [("", data)] + [(k, v) for k, v in data.items()
                            if k in ("image_processor", "video_processor") and isinstance(v, dict)]
    for prefix, part in parts:
        area = _area_family(part, data)
        for name, k, v in _walk(part, prefix):
            if prefix == "" and name.split(".")[0] in ("image_processor", "video_processor"):
                continue  # checked with their own family
            if k in PROCESSOR_BOUNDS and not isinstance(v, dict):
                _check_number(v, PROCESSOR_BOUNDS[k], name, key, path)
            elif k in _EDGE_KEYS and not isinstance(v, (dict, list)):
                bound = (0, MAX_IMAGE_PIXELS) if area else (0, MAX_IMAGE_EDGE)
                what = "pixels an image" if area else "px an image side"
                _check_number(v, bound, name, key, path, why=f"more {what} than any model takes")
            elif k in ("size", "crop_size", "max_image_size", "pad_size") and _int(v):
                _check_number(v, (0, MAX_IMAGE_PIXELS if area else MAX_IMAGE_EDGE), name, key, path,
                              why="larger than any model takes")
        _check_derived_tokens(part, prefix, area, data, path, key)


def _check_derived_tokens(part: dict, prefix: str, area: bool, outer: dict, path: Path, key: str) -> None:
    """Image tokens an image costs as the sizes imply: side/patch squared, or pixels/(patch x merge)^2."""
    patch = part.get("patch_size", outer.get("patch_size"))
    if not _int(patch) or patch <= 0:
        return
    size = part.get("size") if isinstance(part.get("size"), dict) else {}
    dot = f"{prefix}." if prefix else ""
    if area:
        merge = part.get("merge_size", 1) if _int(part.get("merge_size")) else 1
        pixels = part.get("max_pixels") if _int(part.get("max_pixels")) else size.get("longest_edge")
        if _int(pixels) and pixels // (patch * max(merge, 1)) ** 2 > MAX_IMAGE_TOKENS:
            raise _refuse(key, path, f"{dot}size / max_pixels {pixels:,} at patch_size {patch} x merge_size {merge} "
                                     f"gives {pixels // (patch * merge) ** 2:,} image tokens an image "
                                     f"(at most {MAX_IMAGE_TOKENS:,})")
        return
    h, w = size.get("height"), size.get("width")
    if _int(h) and _int(w) and (h // patch) * (w // patch) > MAX_IMAGE_TOKENS:
        raise _refuse(key, path, f"{dot}size {h} x {w} at patch_size {patch} gives {(h // patch) * (w // patch):,} "
                                 f"image tokens an image (at most {MAX_IMAGE_TOKENS:,})")


def check_idefics3_budget(config: dict, processor: dict, path: Path, key: str) -> None:
    """Idefics3 / SmolVLM: image tokens of one tile, (max_image_size / patch)^2 / scale^2, and tiles per image."""
    vision = config.get("vision_config") if isinstance(config.get("vision_config"), dict) else {}
    patch, scale = vision.get("patch_size"), config.get("scale_factor")
    ip = processor.get("image_processor") if isinstance(processor.get("image_processor"), dict) else processor
    tile = (ip.get("max_image_size") or {}).get("longest_edge") if isinstance(ip.get("max_image_size"), dict) else None
    edge = (ip.get("size") or {}).get("longest_edge") if isinstance(ip.get("size"), dict) else None
    if not (_int(patch) and _int(scale) and patch > 0 and scale > 0):
        return
    if _int(tile) and tile > 0:
        tokens = (tile // patch) ** 2 // scale**2
        if tokens > MAX_IMAGE_TOKENS:
            raise _refuse(key, path, f"max_image_size.longest_edge {tile:,} at patch_size {patch} and scale_factor "
                                     f"{scale} gives {tokens:,} image tokens a tile (at most {MAX_IMAGE_TOKENS:,})")
        if _int(edge) and math.ceil(edge / tile) ** 2 > 1024:
            raise _refuse(key, path, f"size.longest_edge {edge:,} over max_image_size.longest_edge {tile:,} gives "
                                     f"{math.ceil(edge / tile) ** 2:,} tiles an image (at most 1,024)")


def check_generation(data: dict, path: Path, key: str) -> None:
    """generation_config.json: lengths, beams, sequences and n-gram sizes within GENERATION_BOUNDS."""
    for name, k, v in _walk(data):
        if k in GENERATION_BOUNDS and not isinstance(v, (dict, list)):
            _check_number(v, GENERATION_BOUNDS[k], name, key, path, why="beyond any generation degusta runs")


def check_adapter_config(data: dict, path: Path, key: str) -> None:
    """adapter_config.json: ranks, alphas, module lists and patterns, layer replication, LoftQ."""
    rank, alpha = (1, 4096), (-1e6, 1e6)
    if "r" in data:
        _check_number(data["r"], rank, "r", key, path, why="beyond the ranks degusta trains (lora.r)")
    if "lora_alpha" in data:
        _check_number(data["lora_alpha"], alpha, "lora_alpha", key, path, floats=True,
                      why="beyond what a real adapter has (lora.alpha is at most 1,000,000)")
    for name, bounds, floats in (("rank_pattern", rank, False), ("alpha_pattern", alpha, True)):
        pattern = data.get(name)
        if pattern in (None, {}):
            continue
        if not isinstance(pattern, dict):
            raise _refuse(key, path, f"{name} is {_show(pattern)}, expected an object of module patterns")
        if len(pattern) > MAX_TARGETS:
            raise _refuse(key, path, f"{name} has {len(pattern):,} patterns (at most {MAX_TARGETS:,})")
        for k, v in pattern.items():
            _check_number(v, bounds, f"{name}[{_show(k)}]", key, path, floats=floats,
                          why="beyond the ranks degusta trains (lora.r)" if name == "rank_pattern" else
                          "beyond what a real adapter has")
            _check_regex_text(k, f"{name} key", key, path)
    for name in ("target_modules", "exclude_modules"):
        value = data.get(name)
        if isinstance(value, str):
            _check_regex_text(value, name, key, path)
        elif isinstance(value, list):
            if len(value) > MAX_TARGETS:
                raise _refuse(key, path, f"{name} lists {len(value):,} modules (at most {MAX_TARGETS:,})")
            bad = next((m for m in value if not isinstance(m, str) or len(m) > 1000), None)
            if bad is not None:
                raise _refuse(key, path, f"{name} holds {_show(bad)}, expected module names")
        elif value is not None:
            raise _refuse(key, path, f"{name} is {_show(value)}, expected a module name list or a regex")
    for name in ("modules_to_save", "layers_pattern"):  # peft pastes these into regexes: plain names only
        value = data.get(name)
        values = [value] if isinstance(value, str) else value if isinstance(value, list) else []
        if value is not None and not isinstance(value, (str, list)):
            raise _refuse(key, path, f"{name} is {_show(value)}, expected module names")
        if len(values) > MAX_TARGETS:
            raise _refuse(key, path, f"{name} lists {len(values):,} entries (at most {MAX_TARGETS:,})")
        bad = next((m for m in values if not isinstance(m, str) or not _PLAIN_NAME.match(m)), None)
        if bad is not None:
            raise _refuse(key, path, f"{name} holds {_show(bad)}: expected plain module names (letters, digits, "
                                     "_ . -), which peft matches as regex text")
    layers = data.get("layers_to_transform")
    if layers is not None:
        _check_number(layers, (0, 1023), "layers_to_transform", key, path)
    replication = data.get("layer_replication")
    if replication is not None:
        pairs = replication if isinstance(replication, list) else None
        if pairs is None or len(pairs) > 64 or not all(isinstance(p, list) and len(p) == 2 for p in pairs):
            raise _refuse(key, path, f"layer_replication is {_show(replication)}, expected at most 64 [start, end] "
                                     "pairs")
        for i, p in enumerate(pairs):
            _check_number(p, (0, 1024), f"layer_replication[{i}]", key, path)
        if sum(max(0, e - s) for s, e in pairs) > 1024:
            raise _refuse(key, path, "layer_replication repeats more than 1,024 layers in all")
    loftq = data.get("loftq_config")
    if isinstance(loftq, dict):
        if "loftq_iter" in loftq:
            _check_number(loftq["loftq_iter"], (0, 100), "loftq_config.loftq_iter", key, path)
        if "loftq_bits" in loftq:
            _check_number(loftq["loftq_bits"], (1, 8), "loftq_config.loftq_bits", key, path)
    tokens = data.get("trainable_token_indices")
    if isinstance(tokens, list):
        _check_number(tokens if len(tokens) <= 4096 else tokens[:4097], (0, 2**21), "trainable_token_indices",
                      key, path)
    elif isinstance(tokens, dict):
        for k, v in list(tokens.items())[:64]:
            _check_number(v if isinstance(v, list) else [v], (0, 2**21), f"trainable_token_indices[{_show(k)}]",
                          key, path)


def _check_regex_text(text: str, name: str, key: str, path: Path) -> None:
    if not isinstance(text, str) or len(text) > 10_000:
        raise _refuse(key, path, f"{name} is {_show(text)}: expected a module pattern of at most 10,000 characters")
    try:
        re.compile(text)
    except (re.error, RecursionError, OverflowError) as e:
        raise _refuse(key, path, f"{name} {_show(text)} is not a valid regex ({e})") from None


# -- files of a folder ------------------------------------------------------------------------------------------
def file_limit(name: str) -> int:
    """The largest size a model folder's JSON or template file `name` may have."""
    if name == "tokenizer.json":
        return MAX_TOKENIZER_BYTES
    if name in _TEMPLATE_FILES:
        return MAX_TEMPLATE_FILE_BYTES
    return MAX_JSON_FILE_BYTES


def check_size(path: Path, key: str) -> None:
    """Refuse a file over its `file_limit` before it is read."""
    try:
        size = path.stat().st_size
    except OSError:
        return  # the reader reports it
    limit = file_limit(path.name)
    if size > limit:
        raise _refuse(key, path, f"{size:,} bytes, larger than any real one (at most {limit:,})")


CHECKS = {"config.json": check_config, "preprocessor_config.json": check_processor,
          "processor_config.json": check_processor, "generation_config.json": check_generation,
          "adapter_config.json": check_adapter_config}


def check_json(path: Path, data: dict, key: str) -> None:
    """The bounds of the JSON file `path` (parsed as `data`), by its name."""
    check = CHECKS.get(path.name)
    if check is not None:
        check(data, path, key)


def check_folder(folder: Path, key: str, parsed: dict[str, dict]) -> None:
    """The bounds that need several files (an Idefics3 image budget) and the folder's chat templates.
    `parsed` holds the folder's JSON files by name, each already checked by `check_json`."""
    config = parsed.get("config.json") or {}
    for name in ("processor_config.json", "preprocessor_config.json"):
        if name not in parsed or not config:
            continue
        if config.get("model_type") == "idefics3":
            check_idefics3_budget(config, parsed[name], folder / name, key)
        check_processor_matches(config, parsed[name], folder / name, key)
    check_chat_templates(folder, key, parsed)


def _image_part(processor: dict) -> dict:
    return processor.get("image_processor") if isinstance(processor.get("image_processor"), dict) else processor


def image_tokens(config: dict, processor: dict) -> int | None:
    """Image tokens one image costs as the processor's sizes say (Qwen / GLM: pixels over (patch x merge)^2;
    Idefics3: tokens a tile times tiles; else side / patch squared); None where unknown."""
    ip = _image_part(processor)
    size = ip.get("size") if isinstance(ip.get("size"), dict) else {}
    patch = ip.get("patch_size", processor.get("patch_size"))
    if config.get("model_type") == "idefics3":
        vision = config.get("vision_config") if isinstance(config.get("vision_config"), dict) else {}
        patch, scale = vision.get("patch_size"), config.get("scale_factor")
        tile = (ip.get("max_image_size") or {}).get("longest_edge") if isinstance(ip.get("max_image_size"), dict) \
            else None
        edge = size.get("longest_edge")
        if not (_int(patch) and _int(scale) and _int(tile) and patch > 0 and scale > 0 and tile > 0):
            return None
        tiles = math.ceil(edge / tile) ** 2 + 1 if ip.get("do_image_splitting") and _int(edge) else 1
        return tiles * ((tile // patch) ** 2 // scale**2)
    if not _int(patch) or patch <= 0:
        return None
    if _area_family(ip, processor):
        merge = ip.get("merge_size") if _int(ip.get("merge_size")) and ip.get("merge_size") > 0 else 1
        pixels = ip.get("max_pixels") if _int(ip.get("max_pixels")) else size.get("longest_edge")
        return pixels // (patch * merge) ** 2 if _int(pixels) else None
    h, w = size.get("height"), size.get("width")
    return (h // patch) * (w // patch) if _int(h) and _int(w) else None


def context_positions(config: dict) -> int | None:
    """The language model's positions (max_position_embeddings of text_config, or of the config itself)."""
    text = config.get("text_config") if isinstance(config.get("text_config"), dict) else config
    n = text.get("max_position_embeddings", config.get("max_position_embeddings"))
    return n if _int(n) and n > 0 else None


def check_processor_matches(config: dict, processor: dict, path: Path, key: str) -> None:
    """The processor agrees with the model: Qwen's patch, merge and temporal sizes equal the vision config's, and
    one image costs no more image tokens than the language model has positions."""
    ip = _image_part(processor)
    vision = config.get("vision_config") if isinstance(config.get("vision_config"), dict) else {}
    if str(config.get("model_type", "")).startswith("qwen"):
        for mine, theirs in (("patch_size", "patch_size"), ("merge_size", "spatial_merge_size"),
                             ("temporal_patch_size", "temporal_patch_size")):
            a, b = ip.get(mine), vision.get(theirs)
            if _int(a) and _int(b) and a != b:
                raise _refuse(key, path, f"{mine} is {a:,}, but config.json's vision_config.{theirs} is {b:,}: the "
                                         "processor belongs to another model")
    tokens, positions = image_tokens(config, processor), context_positions(config)
    if tokens is not None and positions is not None and tokens > positions:
        raise _refuse(key, path, f"its sizes make one image cost {tokens:,} image tokens, more than the model's "
                                 f"{positions:,} positions (config.json max_position_embeddings)")


def check_chat_templates(folder: Path, key: str, parsed: dict[str, dict]) -> None:
    """Every chat template the folder holds renders a plain conversation within the bounds of vlm/chat_template.py."""
    from degusta_learn.vlm.chat_template import check_template

    texts: list[tuple[str, Any]] = []
    for name in ("tokenizer_config.json", "processor_config.json"):
        template = (parsed.get(name) or {}).get("chat_template")
        if isinstance(template, list):  # [{"name": ..., "template": ...}]
            texts += [(f"{name} chat_template[{_show(t.get('name'))}]", t.get("template")) for t in template[:64]
                      if isinstance(t, dict)]
        elif template is not None:
            texts.append((f"{name} chat_template", template))
    jinja = [folder / "chat_template.jinja", *sorted((folder / "additional_chat_templates").glob("*.jinja"))[:64]]
    for path in jinja:
        if path.is_file():
            check_size(path, key)
            texts.append((str(path.relative_to(folder)), path.read_text(encoding="utf-8", errors="replace")))
    path = folder / "chat_template.json"
    if path.is_file():
        check_size(path, key)
        try:
            template = json.loads(path.read_bytes()).get("chat_template")
        except (ValueError, AttributeError, RecursionError):
            template = None  # unreadable: the processor's loader reports it
        if template is not None:
            texts.append(("chat_template.json chat_template", template))
    for where, text in texts:
        if not isinstance(text, str):
            raise _refuse(key, folder / where.split(" ")[0], f"{where.split(' ', 1)[-1]} is {_show(text)}, "
                                                             "expected the template's text")
        check_template(text, f"{key}: {folder / where.split(' ')[0]}"
                             + (f" ({where.split(' ', 1)[1]})" if " " in where else ""))


# -- weights ----------------------------------------------------------------------------------------------------
def safetensors_header(path: Path, key: str) -> dict:
    """The header of a safetensors file: {tensor name: {"dtype", "shape", "data_offsets"}}, read without its data."""
    try:
        with open(path, "rb") as f:
            raw = f.read(8)
            size = os.fstat(f.fileno()).st_size
            n = int.from_bytes(raw, "little") if len(raw) == 8 else -1
            if n < 2 or n > MAX_SAFETENSORS_HEADER or n > size - 8:
                raise _refuse(key, path, f"not a safetensors file (its header length field reads {n:,}; the file "
                                         f"has {size:,} bytes)")
            header = json.loads(f.read(n))
    except OSError as e:
        raise _refuse(key, path, f"cannot read ({e.strerror or e})") from None
    except (ValueError, RecursionError):
        raise _refuse(key, path, "not a safetensors file (its header is not JSON)") from None
    if not isinstance(header, dict):
        raise _refuse(key, path, "not a safetensors file (its header is not a JSON object)")
    return header


def _shape(entry: Any, name: str, path: Path, key: str) -> list[int]:
    shape = entry.get("shape") if isinstance(entry, dict) else None
    if not isinstance(shape, list) or len(shape) > 16 or not all(_int(d) and 0 <= d < 2**40 for d in shape):
        raise _refuse(key, path, f"tensor {_show(name)} has no valid shape ({_show(shape)})")
    return shape


def weight_files(folder: Path) -> list[Path]:
    """The model's safetensors files: the shards its index names, else the top-level *.safetensors (adapters
    excluded)."""
    index = folder / "model.safetensors.index.json"
    if index.is_file():
        try:
            names = set(json.loads(index.read_bytes()).get("weight_map", {}).values())
        except (ValueError, AttributeError, RecursionError, OSError):
            names = set()
        files = [folder / n for n in sorted(names) if isinstance(n, str) and "/" not in n and (folder / n).is_file()]
        if files:
            return files
    return sorted(p for p in folder.glob("*.safetensors") if not p.name.startswith("adapter_model"))


def stored_parameters(files: list[Path], key: str) -> int:
    """How many numbers the safetensors `files` hold (from their headers)."""
    total = 0
    for path in files:
        for name, entry in safetensors_header(path, key).items():
            if name != "__metadata__":
                total += math.prod(_shape(entry, name, path, key))
    return total


def described_parameters(folder: Path) -> tuple[int, int]:
    """(parameters, buffer elements) of the model config.json describes, built on the meta device (no memory)."""
    import torch
    from transformers import AutoConfig, AutoModelForImageTextToText

    config = AutoConfig.from_pretrained(str(folder), local_files_only=True)
    with torch.device("meta"):
        model = AutoModelForImageTextToText.from_config(config)
    return sum(p.numel() for p in model.parameters()), sum(b.numel() for b in model.buffers())


def check_weights(folder: Path, key: str, config: dict | None = None) -> None:
    """Refuse a config.json that describes more parameters than the folder's weights hold (see the module doc)."""
    files = weight_files(folder)
    if not files:
        return  # no safetensors: the loader says so
    if config is None:
        try:
            config = json.loads((folder / "config.json").read_bytes())
        except (OSError, ValueError, RecursionError):
            return
    if not isinstance(config, dict) or config.get("quantization_config"):
        return  # packed weights: their shapes are not the parameters' shapes
    stored = stored_parameters(files, key)
    try:
        params, buffers = described_parameters(folder)
    except Exception:  # noqa: BLE001 - a config transformers cannot build: from_pretrained reports it
        return
    slack = max(int(stored * MAX_PARAMETER_SLACK[0]), MAX_PARAMETER_SLACK[1])
    shown = files[0].name if len(files) == 1 else f"{len(files)} safetensors files"
    if params > stored + slack:
        raise _refuse(key, folder / "config.json",
                      f"describes a model of {params:,} parameters, but its weights ({shown}) hold {stored:,}; the "
                      f"missing {params - stored:,} would be made up at random (sizes or layer counts that do not "
                      "match the weights)")
    if buffers > MAX_BUFFER_ELEMENTS:
        raise _refuse(key, folder / "config.json", f"describes a model with {buffers:,} buffer elements (at most "
                                                   f"{MAX_BUFFER_ELEMENTS:,}; max_position_embeddings or image sizes?)")


def check_adapter(folder: Path, module_names: list[str], key: str):
    """Check an adapter against its weights and the model (`module_names`); returns the peft config to load it with
    (regexes resolved to the names they match) when something was resolved, else None."""
    path = folder / "adapter_config.json"
    try:
        data = json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError):
        return None  # check_json_files reported it
    weights = folder / "adapter_model.safetensors"
    if weights.is_file():
        ranks = [_shape(e, n, weights, key)[0] for n, e in safetensors_header(weights, key).items()
                 if n != "__metadata__" and (".lora_A." in n or ".lora_embedding_A" in n) and _shape(e, n, weights, key)]
        wanted = [v for v in [data.get("r"), *(data.get("rank_pattern") or {}).values()] if _int(v)]
        if ranks and wanted and max(wanted) > max(ranks):
            which = "r" if data.get("r") == max(wanted) else "rank_pattern"
            raise _refuse(key, path, f"{which} asks for rank {max(wanted):,}, but the adapter's weights "
                                     f"({weights.name}) have rank {max(ranks):,} at most")
    resolved = _resolve_patterns(data, module_names, path, key)
    if not resolved:
        return None
    from peft import PeftConfig

    config = PeftConfig.from_pretrained(str(folder))
    for name, value in resolved.items():
        setattr(config, name, value)
    return config


def _resolve_patterns(data: dict, module_names: list[str], path: Path, key: str) -> dict:
    """The regex entries of an adapter config as exact module names: {config attribute: new value}."""
    import regex

    deadline = time.monotonic() + REGEX_SECONDS
    out: dict[str, Any] = {}

    def matching(pattern: str, names: list[str], what: str, full: bool) -> list[str]:
        try:
            compiled = regex.compile(pattern if full else rf"(.*\.)?({pattern})$")
            hits = []
            for n in names:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError
                if (compiled.fullmatch(n, timeout=left) if full else compiled.match(n, timeout=left)):
                    hits.append(n)
            return hits
        except TimeoutError:
            raise _refuse(key, path, f"{what} {_show(pattern)} takes more than {REGEX_SECONDS:g} s to match the "
                                     f"model's {len(names):,} module names (a regex that backtracks without end?)") \
                from None
        except regex.error as e:
            raise _refuse(key, path, f"{what} {_show(pattern)} is not a valid regex ({e})") from None

    for name in ("target_modules", "exclude_modules"):
        value = data.get(name)
        if isinstance(value, str) and value != "all-linear":
            out[name] = matching(value, module_names, name, full=True)
    for name in ("rank_pattern", "alpha_pattern"):
        pattern = data.get(name)
        if not pattern:
            continue
        hits = {p: set(matching(p, module_names, f"{name} key", full=False)) for p in pattern}
        exact = {}
        for module in module_names:  # peft takes the first pattern (in order) that matches a module
            first = next((p for p in pattern if module in hits[p]), None)
            if first is not None:
                exact[re.escape(module)] = pattern[first]
        out[name] = exact
    return out
