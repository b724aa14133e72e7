"""Load a VLM (a folder, a shipped model or a hub id) with its processor, optionally with a peft adapter.

The same code loads SmolVLM-256M-Instruct from the Hub, the shipped tiny base (`tiny_vlm_base`), a tiny
model built by `tiny.py` and a fine-tuned full model: `AutoModelForImageTextToText` + `AutoProcessor` on the
local folder `vlm/hub.py` resolves the name to (a hub id is downloaded into the standard Hugging Face cache
when missing, unless `HF_HUB_OFFLINE=1`; every problem is one line naming the config key).

Usage:
    model, processor = load_vlm("tiny_vlm_base")
    model, processor = load_vlm("HuggingFaceTB/SmolVLM-256M-Instruct", adapter="runs/run/adapter")
"""

from __future__ import annotations

import contextlib
import warnings
from pathlib import Path

from degusta_learn.devices import resolve_device
from degusta_learn.errors import DegustaError
from degusta_learn.vlm.bounds import check_adapter, check_weights
from degusta_learn.vlm.hub import check_json_files, resolve_adapter, resolve_model

DTYPES = ("auto", "float32", "bfloat16", "float16")


def quiet_transformers() -> None:
    """transformers' advisory warnings and its own progress bars (loading shards) off for this process; the
    Hub's download progress stays visible. Sets no offline mode: that is the user's `HF_HUB_OFFLINE`."""
    try:
        from transformers.utils import logging as hf_logging

        hf_logging.disable_progress_bar()
        hf_logging.set_verbosity_error()
    except ImportError:  # pragma: no cover
        pass


def resolve_dtype(dtype: str, device: str, key: str = "dtype"):
    """'auto' -> bfloat16 on a bf16-capable GPU, float32 on CPU."""
    import torch

    if dtype not in DTYPES:
        raise DegustaError(f"{key}: expected one of {list(DTYPES)}, got {dtype!r}")
    if dtype == "auto":
        if device.startswith("cuda") and torch.cuda.is_bf16_supported():
            return torch.bfloat16
        return torch.float32
    return getattr(torch, dtype)


def load_processor(model_id_or_path: str, key: str = "model", local_files_only: bool = False):
    """The processor of a model (folder, shipped name or hub id); a hub id's weights are not downloaded."""
    quiet_transformers()
    source = resolve_model(model_id_or_path, key, weights=False, local_files_only=local_files_only)
    return _processor_from(str(source), model_id_or_path, key)


def _processor_from(source: str, model_id_or_path: str, key: str):
    """The processor in the resolved local folder `source` (`resolve_model`'s answer for `model_id_or_path`)."""
    from transformers import AutoProcessor

    try:
        processor = AutoProcessor.from_pretrained(source, local_files_only=True)
    except Exception as e:  # a missing, corrupt or foreign file: whatever the library raises, one line
        raise DegustaError(f"{key}: cannot load the processor of {model_id_or_path!r}: {_first_line(e)}") from None
    tok = getattr(processor, "tokenizer", None)
    if tok is None:
        raise DegustaError(f"{key}: {model_id_or_path!r} has no tokenizer in its processor (not a VLM?)")
    tok.model_input_names = ["input_ids", "attention_mask"]  # no token_type_ids into generate()
    return processor


def load_vlm(model_id_or_path: str, adapter: str | None = None, device: str = "auto", dtype: str = "auto",
             trainable_adapter: bool = False, key: str = "model", quantization_config=None,
             merge_adapter: bool = False, local_files_only: bool = False, device_key: str | None = None):
    """Load (model, processor) through the Auto classes, with an optional peft adapter.

    Args:
        model_id_or_path: a saved model folder, a shipped model name, or a hub id (downloaded into the Hugging
            Face cache when missing; refused in one line when offline: vlm/hub.py).
        adapter: a folder written by `PeftModel.save_pretrained` (degusta writes `<run>/adapter/`).
        device: "auto", "cpu", "cuda", "cuda:1", ...
        dtype: "auto" (bf16 on a capable GPU, else fp32), "float32", "bfloat16", "float16".
        trainable_adapter: keep the adapter weights trainable (resume training) instead of inference mode.
        key: config key named in error messages (`model.name`: the dtype and adapter keys are `model.dtype`,
            `model.adapter`, its section's).
        device_key: the config key of `device` (None: `device` in `key`'s section).
        quantization_config: a `BitsAndBytesConfig` (QLoRA); the model is then loaded straight onto the GPU.
        merge_adapter: fold the adapter into the base weights (`merge_and_unload`) for inference: the same
            function up to float rounding, without a LoRA pass beside every adapted layer (predicting with
            the tiny base's adapter ~1.2x faster on a CPU: benchmarks/RESULTS.md). Not with a trainable
            adapter or a quantized base (rounding a merged 4-bit weight changes the model).

    Returns:
        (model in eval mode on `device`, processor).
    """
    quiet_transformers()
    from transformers import AutoModelForImageTextToText

    source = str(resolve_model(model_id_or_path, key, local_files_only=local_files_only))
    section = key.rpartition(".")[0]  # model.name -> model.dtype, model.adapter
    device = resolve_device(device, device_key or (f"{section}.device" if section else "device"))
    torch_dtype = resolve_dtype(dtype, device, f"{section}.dtype" if section else "dtype")
    processor = _processor_from(source, model_id_or_path, key)  # the folder's files were checked above
    check_weights(Path(source), key)  # config.json describes no more than the weights hold (built on meta first)
    extra = {}
    if quantization_config is not None:
        extra = {"quantization_config": quantization_config, "device_map": {"": device}}
    try:
        model = AutoModelForImageTextToText.from_pretrained(source, dtype=torch_dtype, local_files_only=True, **extra)
    except Exception as e:  # corrupt weights, a config that does not match them, a missing library (timm), ...
        raise DegustaError(f"{key}: cannot load {model_id_or_path!r} as an image-text-to-text model: "
                           f"{_first_line(e)}") from None
    if source != str(model_id_or_path):  # a shipped name or a hub id read from its cached snapshot: the name stays
        model.config._name_or_path = str(model_id_or_path)  # what peft records as base_model_name_or_path
    n_vocab = len(processor.tokenizer)
    emb = model.get_input_embeddings()
    if emb is not None and emb.num_embeddings < n_vocab:  # a processor from another model: ids would overflow
        raise DegustaError(f"{key}: {model_id_or_path!r}: its tokenizer has {n_vocab} tokens but the model embeds "
                           f"only {emb.num_embeddings}; the processor files belong to another model")
    _check_image_token(model.config, processor, model_id_or_path, key)
    if adapter:
        adapter_key = f"{key.rsplit('.', 1)[0]}.adapter" if "." in key else "adapter"  # model.name -> model.adapter
        model = load_adapter(model, adapter, trainable=trainable_adapter, key=adapter_key)
        if merge_adapter and not trainable_adapter and quantization_config is None \
                and not getattr(model, "is_loaded_in_4bit", False) and not getattr(model, "is_loaded_in_8bit", False):
            model = model.merge_and_unload()
    if quantization_config is None:
        model = model.to(device)
    return model.eval(), processor


def _check_image_token(config, processor, name: str, key: str) -> None:
    """The processor writes its image placeholder as the token id the model replaces with image features; a
    config.json from another model (or an edited id) failed only at the first answer, with transformers' "Image
    features and image tokens do not match, tokens: 0"."""
    token = getattr(processor, "image_token", None)
    wanted = getattr(config, "image_token_id", None)
    if wanted is None:
        wanted = getattr(config, "image_token_index", None)
    if not token or not isinstance(wanted, int):
        return
    written = processor.tokenizer.convert_tokens_to_ids(str(token))
    if written != wanted:
        raise DegustaError(f"{key}: {name!r}: config.json's image_token_id is {wanted}, but the processor writes its "
                           f"image placeholder {str(token)!r} as token {written}; the config and the processor files "
                           f"belong to different models")


def _first_line(e: Exception) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}"[:400]


@contextlib.contextmanager
def quiet_peft():
    """Silence the FutureWarning peft's PeftModel constructor triggers in transformers (it reads the deprecated
    `is_gradient_checkpointing`): not the user's to act on, and it printed on every adapter load."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"`is_gradient_checkpointing` is deprecated", category=FutureWarning)
        yield


def load_adapter(model, adapter: str | Path, trainable: bool = False, key: str = "adapter"):
    """Wrap `model` with the peft adapter saved in `adapter` (plain `PeftModel.from_pretrained`); a folder that
    is not one, a corrupt file or an adapter of another model is a DegustaError naming `key` and the folder."""
    from peft import PeftModel

    path = resolve_adapter(adapter, key)
    if not (path / "adapter_config.json").is_file():
        raise DegustaError(f"{key}: {path} has no adapter_config.json (expected a folder written by "
                           "PeftModel.save_pretrained, e.g. runs/<run>/adapter)")
    check_json_files(path, key)
    # the ranks against the adapter's weights, its regexes resolved to module names with a time limit (vlm/bounds.py)
    config = check_adapter(path, [name for name, _ in model.named_modules()], key)
    try:
        with quiet_peft():
            return PeftModel.from_pretrained(model, str(path), is_trainable=trainable,
                                             **({"config": config} if config is not None else {}))
    except Exception as e:  # a corrupt file, or an adapter of another model: whatever peft raises, one line
        raise DegustaError(f"{key}: cannot load the adapter in {path} onto this model: {_first_line(e)}") from None
