"""Unbounded sizes (hardening, second pass): hostile sizes in model folders, adapters and records are one-line
refusals naming the file and the key, before anything is allocated; chat templates that loop, recurse or explode
are stopped within seconds; rendering stays bounded at the largest accepted image size.

Most cases check folders without loading a model (the checks run before any model is built); the folders are
copies of the shipped base with one value changed.
"""

from __future__ import annotations

import json
import shutil
import time
import tracemalloc
from pathlib import Path

import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import MAX_JSON_BYTES
from degusta_learn.shipped import shipped_model

BASE = shipped_model("tiny_vlm_base")
FAST_S = 1.0  # a refusal of a file's value takes well under this (no model is built)
TEMPLATE_S = 4.0  # MAX_SECONDS (2 s) of a render, with room for a loaded machine


def _set(data: dict, dotted: str, value) -> None:
    *head, last = dotted.split(".")
    for k in head:
        data = data.setdefault(k, {})
    data[last] = value


@pytest.fixture
def base_copy(tmp_path):
    """A copy of the shipped base (its weights linked, not copied) whose files a test edits."""
    out = tmp_path / "model"
    out.mkdir()
    for f in BASE.iterdir():
        if f.suffix == ".safetensors":
            (out / f.name).symlink_to(f)
        elif f.is_file():
            shutil.copy(f, out / f.name)
    return out


def _edit(folder: Path, name: str, dotted: str, value) -> None:
    path = folder / name
    data = json.loads(path.read_text())
    _set(data, dotted, value)
    path.write_text(json.dumps(data))


def _refused_fast(fn, *words: str, reader_buffer: int = 0) -> str:
    """`fn()` raises a one-line DegustaError naming every word, within FAST_S and without allocating 50 MB (beyond
    `reader_buffer`: the buffer `files.jsonio.read_json` reserves for any file, its MAX_JSON_BYTES)."""
    tracemalloc.start()
    t = time.perf_counter()
    try:
        with pytest.raises(DegustaError) as e:
            fn()
        took = time.perf_counter() - t
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    msg = str(e.value)
    assert "\n" not in msg, msg
    for w in words:
        assert w in msg, (w, msg)
    assert took < FAST_S, (took, msg)
    assert peak < 50 * 2**20 + reader_buffer, (peak, msg)
    return msg


def _check(folder: Path):
    from degusta_learn.vlm.hub import resolve_model

    return lambda: resolve_model(str(folder), key="model.name")


# -- config.json -----------------------------------------------------------------------------------------------
CONFIG_CASES = [
    ("text_config.vocab_size", 10**9), ("text_config.vocab_size", -5), ("text_config.vocab_size", "many"),
    ("text_config.vocab_size", True), ("text_config.hidden_size", 1e30), ("text_config.hidden_size", 10**6),
    ("text_config.num_hidden_layers", 10**6), ("text_config.intermediate_size", 10**9),
    ("text_config.max_position_embeddings", 10**12), ("text_config.num_attention_heads", 0),
    ("text_config.head_dim", 10**5), ("vision_config.hidden_size", 10**7), ("image_seq_length", 10**9),
    ("vision_config.model_args.channels", [10**6, 64, 128, 256]), ("vision_config.model_args.layers", [10**6, 1, 2, 1]),
    ("vision_config.num_classes", 10**9), ("text_config.num_experts", 10**6),
    ("vision_config.image_size", 10**6), ("vision_config.patch_size", 0), ("vision_config.patch_size", 10**7),
    ("text_config.num_hidden_layers", [1] * 5000),
]


@pytest.mark.parametrize("dotted,value", CONFIG_CASES, ids=[f"{k}={str(v)[:12]}" for k, v in CONFIG_CASES])
def test_config_sizes_refused(base_copy, dotted, value):
    _edit(base_copy, "config.json", dotted, value)
    _refused_fast(_check(base_copy), "config.json", dotted.rsplit(".", 1)[-1], "model.name")


def test_config_patches_and_experts_refused(base_copy):
    _edit(base_copy, "config.json", "vision_config.image_size", 8192)
    _edit(base_copy, "config.json", "vision_config.patch_size", 1)
    _refused_fast(_check(base_copy), "config.json", "patches")
    _edit(base_copy, "config.json", "vision_config.patch_size", 16)
    _edit(base_copy, "config.json", "text_config.num_hidden_layers", 1000)
    _edit(base_copy, "config.json", "text_config.num_experts", 1000)
    _refused_fast(_check(base_copy), "config.json", "experts")


def test_config_beyond_its_weights_refused_before_allocation(base_copy, monkeypatch):
    """Within the bounds but beyond the weights: 40 layers over the weights of 4 would be made up at random;
    the model is counted on the meta device and refused before from_pretrained allocates anything."""
    import transformers

    from degusta_learn.vlm.load import load_vlm

    def never(*args, **kwargs):
        raise AssertionError("from_pretrained reached: the model would have been allocated")

    monkeypatch.setattr(transformers.AutoModelForImageTextToText, "from_pretrained", never)
    _edit(base_copy, "config.json", "text_config.num_hidden_layers", 40)
    _edit(base_copy, "config.json", "text_config.layer_types", ["full_attention"] * 40)
    with pytest.raises(DegustaError) as e:
        load_vlm(str(base_copy), device="cpu", dtype="float32")
    msg = str(e.value)
    assert "\n" not in msg and "config.json" in msg and "parameters" in msg and "weights" in msg, msg


def test_shipped_base_passes(base_copy):
    from degusta_learn.vlm import bounds
    from degusta_learn.vlm.hub import check_json_files

    check_json_files(base_copy, "model")
    bounds.check_weights(base_copy, "model")


# -- processor configs -------------------------------------------------------------------------------------------
PROCESSOR_CASES = [
    ("image_processor.size.height", 10**6), ("image_processor.size.width", 5000), ("image_processor.crop_size.height", 10**6),
    ("patch_size", 0), ("patch_size", 10**5), ("image_processor.size.height", -1),
    ("num_additional_image_tokens", 10**9),
]


@pytest.mark.parametrize("dotted,value", PROCESSOR_CASES, ids=[f"{k}={v}" for k, v in PROCESSOR_CASES])
def test_processor_sizes_refused(base_copy, dotted, value):
    _edit(base_copy, "processor_config.json", dotted, value)
    _refused_fast(_check(base_copy), "processor_config.json", dotted.rsplit(".", 1)[-1])


def test_processor_derived_tokens_refused(base_copy):
    _edit(base_copy, "processor_config.json", "patch_size", 1)
    _edit(base_copy, "processor_config.json", "image_processor.size", {"height": 300, "width": 300})  # 90,000 tokens
    _refused_fast(_check(base_copy), "processor_config.json", "image tokens")


@pytest.mark.parametrize("file,data,word", [
    ("preprocessor_config.json", {"image_processor_type": "Idefics3ImageProcessor", "size": {"longest_edge": 10**6}},
     "longest_edge"),
    ("preprocessor_config.json", {"image_processor_type": "Qwen2VLImageProcessor", "max_pixels": 10**13}, "max_pixels"),
    ("preprocessor_config.json", {"image_processor_type": "Qwen2VLImageProcessor", "patch_size": 1, "merge_size": 1,
                                  "size": {"longest_edge": 12845056}}, "image tokens"),
    ("preprocessor_config.json", {"image_seq_len": 10**9}, "image_seq_len"),
    ("preprocessor_config.json", {"max_image_tiles": 10**6}, "max_image_tiles"),
], ids=["edge", "qwen-pixels", "qwen-tokens", "seq-len", "tiles"])
def test_preprocessor_sizes_refused(base_copy, file, data, word):
    (base_copy / file).write_text(json.dumps(data))
    _refused_fast(_check(base_copy), file, word)


def test_real_processor_sizes_pass(tmp_path):
    """Real values stay accepted: Qwen2-VL-2B's area of 12,845,056 px (16,384 tokens, 32,768 positions), SmolVLM's
    2048 / 512 px edges with image splitting (17 tiles of 64 tokens, 8,192 positions)."""
    qwen, smol = tmp_path / "qwen", tmp_path / "smol"
    for folder, config, processor in [
        (qwen, {"model_type": "qwen2_vl", "vision_config": {"patch_size": 14, "spatial_merge_size": 2,
                                                            "temporal_patch_size": 2, "embed_dim": 1280, "depth": 32},
                "text_config": {"max_position_embeddings": 32768, "vocab_size": 151936, "hidden_size": 1536}},
         {"image_processor_type": "Qwen2VLImageProcessor", "patch_size": 14, "merge_size": 2, "temporal_patch_size": 2,
          "max_pixels": 12845056, "min_pixels": 3136, "size": {"longest_edge": 12845056, "shortest_edge": 3136}}),
        (smol, {"model_type": "idefics3", "scale_factor": 4, "vision_config": {"patch_size": 16, "image_size": 512},
                "text_config": {"max_position_embeddings": 8192, "vocab_size": 49280}},
         {"image_processor_type": "Idefics3ImageProcessor", "do_image_splitting": True, "size": {"longest_edge": 2048},
          "max_image_size": {"longest_edge": 512}, "image_seq_len": 64})]:
        folder.mkdir()
        (folder / "config.json").write_text(json.dumps(config))
        (folder / "preprocessor_config.json").write_text(json.dumps(processor))
        _check(folder)()


def test_processor_beyond_the_context_refused(base_copy):
    """patch_size 1 keeps the image tokens within 2^16 (256 x 256), but the model has 4,096 positions."""
    _edit(base_copy, "processor_config.json", "patch_size", 1)
    _refused_fast(_check(base_copy), "processor_config.json", "positions")


def test_qwen_processor_of_another_model_refused(tmp_path):
    """A Qwen2-VL processor whose patch size is not the vision tower's (14): silently wrong inputs before."""
    folder = tmp_path / "qwen"
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps({
        "model_type": "qwen2_vl", "vision_config": {"patch_size": 14, "spatial_merge_size": 2, "temporal_patch_size": 2},
        "text_config": {"max_position_embeddings": 32768}}))
    (folder / "processor_config.json").write_text(json.dumps({"processor_class": "Qwen2VLProcessor", "image_processor": {
        "image_processor_type": "Qwen2VLImageProcessor", "patch_size": 1, "merge_size": 2,
        "size": {"longest_edge": 50176, "shortest_edge": 3136}}}))
    _refused_fast(_check(folder), "processor_config.json", "patch_size", "vision_config.patch_size")


def test_image_budget_beyond_the_context_refused():
    from types import SimpleNamespace

    from degusta_learn.vlm.inputs import set_image_budget

    ip = SimpleNamespace(size={"height": 256, "width": 256}, crop_size={}, do_center_crop=False)
    processor = SimpleNamespace(image_processor=ip, patch_size=32)
    config = SimpleNamespace(model_type="fast_vlm", text_config=SimpleNamespace(max_position_embeddings=4096))
    set_image_budget(processor, config, 2048)  # 64 x 64 = 4,096 tokens: fits
    with pytest.raises(DegustaError, match="model.image_size: .* more than the model's 4,096 positions"):
        set_image_budget(processor, config, 4096)


def test_idefics3_budget_refused(tmp_path):
    from degusta_learn.vlm import bounds

    config = {"model_type": "idefics3", "scale_factor": 1, "vision_config": {"patch_size": 1, "image_size": 512}}
    processor = {"image_processor": {"max_image_size": {"longest_edge": 4096}, "size": {"longest_edge": 4096}}}
    with pytest.raises(DegustaError, match="image tokens a tile"):
        bounds.check_idefics3_budget(config, processor, tmp_path / "processor_config.json", "model")


# -- generation config, file sizes -------------------------------------------------------------------------------
@pytest.mark.parametrize("dotted,value", [("max_new_tokens", 10**12), ("num_beams", 10**6), ("max_length", 10**12),
                                          ("num_return_sequences", 10**6), ("min_new_tokens", 10**9),
                                          ("cache_config.max_cache_len", 10**9)])
def test_generation_config_refused(base_copy, dotted, value):
    _edit(base_copy, "generation_config.json", dotted, value)
    _refused_fast(_check(base_copy), "generation_config.json", dotted.rsplit(".", 1)[-1])


def test_oversized_json_refused_before_reading(base_copy):
    from degusta_learn.vlm import bounds

    with open(base_copy / "config.json", "a") as f:
        f.truncate(bounds.MAX_JSON_FILE_BYTES + 1)  # a sparse file: nothing is written
    _refused_fast(_check(base_copy), "config.json", "bytes")


# -- adapters ----------------------------------------------------------------------------------------------------
MODULES = [f"model.language_model.layers.{i}.self_attn.{p}" for i in range(4) for p in ("q_proj", "v_proj")]


@pytest.fixture
def adapter(tmp_path):
    """A rank-4 LoRA adapter folder (config and safetensors written by hand: no model needed)."""
    import torch
    from safetensors.torch import save_file

    out = tmp_path / "adapter"
    out.mkdir()
    tensors = {}
    for m in MODULES:
        tensors[f"base_model.model.{m}.lora_A.weight"] = torch.zeros(4, 256)
        tensors[f"base_model.model.{m}.lora_B.weight"] = torch.zeros(256, 4)
    save_file(tensors, str(out / "adapter_model.safetensors"))
    (out / "adapter_config.json").write_text(json.dumps(
        {"peft_type": "LORA", "r": 4, "lora_alpha": 8, "target_modules": MODULES, "task_type": "CAUSAL_LM"}))
    return out


ADAPTER_CASES = [
    ("r", 10**6), ("r", 10**9), ("r", 0), ("r", -3), ("r", 2.5), ("lora_alpha", 1e308), ("lora_alpha", "x"),
    ("target_modules", [f"m{i}" for i in range(20_000)]), ("rank_pattern", {"q_proj": 10**8}),
    ("alpha_pattern", {"q_proj": "x"}), ("layers_to_transform", list(range(5000))), ("target_modules", "(a"),
    ("modules_to_save", ["(a+)+$"]), ("layer_replication", [[0, 10**6]]), ("loftq_config", {"loftq_iter": 10**9}),
    ("trainable_token_indices", [10**9]),
]


@pytest.mark.parametrize("field,value", ADAPTER_CASES, ids=[f"{k}={str(v)[:12]}" for k, v in ADAPTER_CASES])
def test_adapter_config_refused(adapter, field, value):
    from degusta_learn.vlm.hub import check_json_files

    _edit(adapter, "adapter_config.json", field, value)
    _refused_fast(lambda: check_json_files(adapter, "model.adapter"), "adapter_config.json", field.split(".")[0],
                  "model.adapter")


def test_adapter_rank_beyond_its_weights_refused(adapter):
    """r = 4,096 is a valid rank, but these weights have rank 4: peft would allocate rank-4,096 matrices first."""
    from degusta_learn.vlm.bounds import check_adapter

    _edit(adapter, "adapter_config.json", "r", 4096)
    _refused_fast(lambda: check_adapter(adapter, MODULES, "model.adapter"), "adapter_config.json", "r", "rank 4")
    _edit(adapter, "adapter_config.json", "r", 4)
    _edit(adapter, "adapter_config.json", "rank_pattern", {"q_proj": 512})
    _refused_fast(lambda: check_adapter(adapter, MODULES, "model.adapter"), "rank_pattern", "512")


def test_adapter_backtracking_regex_refused_in_time(adapter):
    from degusta_learn.vlm.bounds import REGEX_SECONDS, check_adapter

    names = ["a" * 40 + str(i) for i in range(50)]
    _edit(adapter, "adapter_config.json", "target_modules", "(a|aa)+$")
    t = time.process_time()  # the regex module's timeout counts CPU time (the wall time depends on the load)
    with pytest.raises(DegustaError, match="target_modules.*takes more than") as e:
        check_adapter(adapter, names, "model.adapter")
    assert time.process_time() - t < REGEX_SECONDS + 1 and "\n" not in str(e.value)


def test_adapter_regexes_resolved_to_names(adapter):
    """A regex target and rank pattern reach peft as the exact names they match (peft's `re` has no time limit)."""
    import re

    from degusta_learn.vlm.bounds import check_adapter

    _edit(adapter, "adapter_config.json", "target_modules", r".*\.q_proj")
    _edit(adapter, "adapter_config.json", "rank_pattern", {r"layers\.0\..*": 4, "q_proj": 2})
    config = check_adapter(adapter, MODULES, "model.adapter")
    assert sorted(config.target_modules) == sorted(m for m in MODULES if m.endswith("q_proj"))
    assert config.rank_pattern[re.escape(MODULES[0])] == 4 and config.rank_pattern[re.escape(MODULES[2])] == 2


# -- records -----------------------------------------------------------------------------------------------------
RECORD_CASES = [("image_size", 10**9), ("image_size", -4), ("tokens_per_image", 10**12), ("render_size", 10**9),
                ("grid.rows", 10**6), ("parameters", 10**18), ("architecture.image_size", 10**12),
                ("architecture.vocab_size", 1e300)]


@pytest.mark.parametrize("dotted,value", RECORD_CASES, ids=[f"{k}={v}" for k, v in RECORD_CASES])
def test_base_record_sizes_refused(base_copy, dotted, value):
    from degusta_learn.vlm.record import read_record

    _edit(base_copy, "degusta_base.json", dotted, value)
    _refused_fast(lambda: read_record(base_copy / "degusta_base.json"), "degusta_base.json",
                  dotted.split(".")[-1] if "." not in dotted or dotted.startswith("architecture") else "rows",
                  reader_buffer=MAX_JSON_BYTES)


def test_finetune_record_sizes_refused(tmp_path):
    from degusta_learn.render.grid import Grid
    from degusta_learn.vlm.prompt_options import PromptOptions
    from degusta_learn.vlm.record import FinetuneRecord, TrainingData, read_record, write_record

    record = FinetuneRecord(base_model="x", method="mogma", mode="lora", grid=Grid(8, 8), prompt=PromptOptions(),
                            image_size=None, render_size=224, processor_size={"height": 224},
                            trained_on=TrainingData(dataset="d", fingerprint="f", seed=0, contexts=[2],
                                                    train_participants=["p"], val_participants=[]))
    path = write_record(tmp_path, record)
    assert read_record(path).image_size is None
    for dotted, value in [("image_size", 10**9), ("trained_on.contexts", [10**9]), ("processor_size.height", 10**15)]:
        data = json.loads(path.read_text())
        _set(data, dotted, value)
        path.write_text(json.dumps(data))
        _refused_fast(lambda: read_record(path), "degusta_finetune.json", dotted.split(".")[-1],
                      reader_buffer=MAX_JSON_BYTES)
        write_record(tmp_path, record)


# -- chat templates ----------------------------------------------------------------------------------------------
LOOP = "{% for i in range(100000) %}"
HOSTILE_TEMPLATES = {
    "range 10**12": "{% for i in range(10**12) %}x{% endfor %}",
    "nested loops": LOOP + LOOP + "{% endfor %}{% endfor %}",
    "doubling macro": "{% macro f(n) %}{% if n > 0 %}{{ f(n - 1) }}{{ f(n - 1) }}{% endif %}{% endmacro %}{{ f(60) }}",
    "endless macro": "{% macro f(n) %}{{ f(n + 1) }}{% endmacro %}{{ f(0) }}",
    "recursive loop": "{% for m in messages recursive %}{{ loop(messages) }}{{ loop(messages) }}{% endfor %}",
    "quiet recursive loop": "{% for m in range(1000) recursive %}{% if loop.depth < 3 %}{{ loop(range(1000)) }}"
                            "{% endif %}{% endfor %}",
    "string times 10**10": "{{ 'x' * 10**10 }}",
    "power tower": "{{ 10 ** 10 ** 10 }}",
    "power in a dead branch": "{% if false %}{{ 'x' * 10 ** 10 ** 10 }}{% endif %}{{ 9 ** 9 ** 9 }}",
    "center": "{{ 'x' | center(10**10) }}",
    "ljust in a loop": LOOP + "{{ 'x'.ljust(100000) }}{% endfor %}",
    "literal in a loop": LOOP + "y" * 5000 + "{% endfor %}",
    "literal in a macro": "{% macro f() %}" + LOOP + "y" * 5000 + "{% endfor %}{% endmacro %}{% set x = f() %}",
    "set block": "{% set x %}" + LOOP + "y" * 5000 + "{% endfor %}{% endset %}",
    "concat doubling": "{% set ns = namespace(s='xy') %}{% for i in range(64) %}{% set ns.s = ns.s ~ ns.s %}"
                       "{% endfor %}",
    "plus doubling": "{% set ns = namespace(s=['x']) %}{% for i in range(64) %}{% set ns.s = ns.s + ns.s %}"
                     "{% endfor %}",
    "percent width": "{{ '%1000000000d' % 1 }}",
    "format width": "{{ '{:>1000000000}'.format(1) }}",
    "lipsum": "{{ lipsum(100000, False, 100000, 100000) }}",
    "join of repeats": "{{ (['x' * 1000000] * 100000) | join }}",
    "replace blowup": "{{ ('a' * 100000) | replace('a', 'b' * 100000) }}",
    "map replace": "{{ range(100000) | map('string') | map('replace', '', 'x' * 1000) | list | length }}",
    "tojson indent": "{{ messages | tojson(indent=900000) }}",
    "list times": "{% set l = [1] * 10**7 %}",
    "squaring integer": "{% set ns = namespace(x=3) %}{% for i in range(100) %}{% set ns.x = ns.x * ns.x %}{% endfor %}",
    "literal integer": "{{ " + "9" * 4000 + " * 2 }}",
    "sum of lists": "{{ (range(3000) | map('string') | map('list') | list) | sum(start=[]) | length }}",
    "expandtabs": "{{ ('\t' * 100000).expandtabs(100000) }}",
    "indent": "{{ ('\n' * 100000) | indent('x' * 1000) }}",
    "wordwrap": "{{ ('a ' * 100000) | wordwrap(1, wrapstring='x' * 1000) }}",
    "fromkeys": "{{ dict.fromkeys(range(100000), 'x' * 100000) | tojson }}",
    "translate": "{{ ('a' * 100000).translate({97: 'b' * 100000}) }}",
    "batch fill": "{{ [1] | batch(10**6, 'x' * 1000) | list | tojson }}",
    "nested parens": "{{ " + "(" * 5000 + "1" + ")" * 5000 + " }}",
    "nested ifs": "{% if true %}" * 3000 + "x" + "{% endif %}" * 3000,
    "huge template": "x" * 1_000_001,
}
MESSAGES = [{"role": "user", "content": [{"type": "image"}, {"type": "text", "text": "where?"}]}]


@pytest.mark.parametrize("name", list(HOSTILE_TEMPLATES))
def test_hostile_chat_template_stopped(name):
    from degusta_learn.vlm.chat_template import render_chat

    t = time.perf_counter()
    tracemalloc.start()
    try:
        with pytest.raises(DegustaError) as e:
            render_chat(HOSTILE_TEMPLATES[name], MESSAGES, add_generation_prompt=True)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    msg = str(e.value)
    assert time.perf_counter() - t < TEMPLATE_S and "\n" not in msg and msg.startswith("model: its chat template"), msg
    assert "stopped" in msg, msg
    assert peak < 400 * 2**20, (peak, msg)  # MAX_CREATED_CELLS characters at most, never gigabytes


@pytest.mark.parametrize("file", ["chat_template.jinja", "chat_template.json", "tokenizer_config.json"])
def test_hostile_template_file_refused_at_load(base_copy, file):
    """The folder check renders a plain conversation with every template it holds and names the file."""
    template = LOOP + LOOP + "{% endfor %}{% endfor %}"
    if file == "chat_template.jinja":
        (base_copy / file).write_text(template)
    elif file == "chat_template.json":
        (base_copy / file).write_text(json.dumps({"chat_template": template}))
    else:
        _edit(base_copy, file, "chat_template", template)
    from degusta_learn.vlm.hub import resolve_model

    t = time.perf_counter()
    with pytest.raises(DegustaError) as e:
        resolve_model(str(base_copy), key="model.name")
    msg = str(e.value)
    assert time.perf_counter() - t < TEMPLATE_S and "\n" not in msg and file in msg and "chat template refused" in msg


def test_template_that_merely_fails_is_left_to_chat_format(base_copy):
    """A template that raises (roles must alternate) is no bound: the folder loads, ChatFormat reports it."""
    from degusta_learn.vlm.hub import resolve_model

    (base_copy / "chat_template.jinja").write_text("{{ raise_exception('roles must alternate') }}")
    resolve_model(str(base_copy), key="model.name")


KITCHEN_SINK = (
    "{%- set ns = namespace(images=0, last='') -%}"
    "{%- macro part(c) -%}{%- if c['type'] == 'image' -%}{%- set ns.images = ns.images + 1 -%}<img{{ ns.images }}>"
    "{%- elif c['type'] == 'text' -%}{{ c['text'] | trim }}{%- endif -%}{%- endmacro -%}"
    "{{ bos_token }}{% for message in messages %}{% if loop.first and message['role'] != 'system' %}"
    "<|system|>You are helpful.{{ '\\n' }}{% endif %}"
    "{% if message['role'] == 'skip' %}{% continue %}{% endif %}"
    "<|{{ message['role'] }}|>{% if message['content'] is string %}{{ message['content'] }}"
    "{% else %}{% for c in message['content'] %}{{ part(c) }}{% if not loop.last %} {% endif %}{% endfor %}{% endif %}"
    "{{ eos_token ~ '\\n' }}{% set ns.last = message['role'] %}{% endfor %}"
    "{% if add_generation_prompt %}<|assistant|>{% generation %}{% endgeneration %}{% endif %}"
    "{{ '#' * 3 }}{{ (messages | length) * 2 }}{{ messages | selectattr('role', 'equalto', 'user') | list | length }}"
    "{{ messages[0] | tojson }}{{ '%03d|%s' % (7, 'x') }}{{ '{}-{}'.format(1, 2) }}{{ ns.last | upper | center(9) }}"
    "{{ [1, 2, 3] | join(',') }}{{ range(3) | map('string') | join }}{{ dict(a=1) | tojson }}"
    "{% for k, v in {'a': 1, 'b': 2} | dictsort %}{{ k }}{{ v }}{% endfor %}{{ 'a\\tb'.expandtabs(2) }}"
    "{% for x in [[1, [2]], [3]] recursive %}{% if x is iterable %}({{ loop(x) }}){% else %}{{ x }}{% endif %}"
    "{% endfor %}{{ 'ab' | replace('a', 'c') }}{{ 2 ** 10 }}{{ 7 // 2 }}{{ 7 % 3 }}{{ 'x' ~ 1 ~ none }}"
)


@pytest.mark.parametrize("template", [
    "tiny_idefics3", "tiny_qwen2vl", "shipped_base", "kitchen_sink"])
def test_bounded_render_matches_transformers(template):
    """A well-behaved template renders exactly as transformers renders it (`apply_chat_template` calls
    render_jinja_template with the tokenizer's special tokens)."""
    from transformers.utils.chat_template_utils import render_jinja_template

    from degusta_learn.vlm.chat_template import render_chat
    from degusta_learn.vlm.random_models import tiny

    text = {"tiny_idefics3": tiny.IDEFICS3_CHAT_TEMPLATE, "tiny_qwen2vl": tiny.QWEN2VL_CHAT_TEMPLATE,
            "shipped_base": (BASE / "chat_template.jinja").read_text(), "kitchen_sink": KITCHEN_SINK}[template]
    special = {"bos_token": "<s>", "eos_token": "</s>", "pad_token": "<pad>", "additional_special_tokens": ["<image>"]}
    conversations = [
        MESSAGES,
        [{"role": "system", "content": [{"type": "text", "text": " sys "}]},
         {"role": "user", "content": [{"type": "image"}, {"type": "image"}, {"type": "text", "text": "a\nb"}]},
         {"role": "assistant", "content": [{"type": "text", "text": "[{'id': 3}]"}]},
         {"role": "user", "content": "plain string"}],
    ]
    for messages in conversations:
        for add in (True, False):
            theirs = render_jinja_template([messages], chat_template=text, add_generation_prompt=add, **special)[0][0]
            assert render_chat(text, messages, add, special) == theirs


def test_chat_format_uses_the_bounded_render(base_copy):
    """ChatFormat (every prompt degusta writes) renders through the bounds: a template that explodes only on a
    long conversation is stopped there, in one line, not hung."""
    from degusta_learn.vlm.inputs import ChatFormat
    from degusta_learn.vlm.load import load_processor

    # the conversations of the load-time probe (up to three messages) render quickly; four loop 10^10 times
    bomb = (BASE / "chat_template.jinja").read_text() + (
        "{% if messages | length > 3 %}" + LOOP + LOOP + "{% endfor %}{% endfor %}{% endif %}")
    (base_copy / "chat_template.jinja").write_text(bomb)
    processor = load_processor(str(base_copy))
    fmt = ChatFormat(processor)
    convo = [{"role": "user", "content": [{"type": "text", "text": str(i)}]} for i in range(4)]
    t = time.perf_counter()
    with pytest.raises(DegustaError, match="chat template was stopped") as e:
        fmt.prompt_text(convo)
    assert time.perf_counter() - t < TEMPLATE_S and "\n" not in str(e.value)


# -- rendering: bounded at every accepted size -------------------------------------------------------------------
def test_cli_render_size_bounds_are_the_renderers():
    from degusta_learn.cli import IMAGE_SIZE
    from degusta_learn.render.lifting import MAX_IMAGE_SIZE, MIN_IMAGE_SIZE

    assert IMAGE_SIZE(str(MIN_IMAGE_SIZE)) == MIN_IMAGE_SIZE and IMAGE_SIZE(str(MAX_IMAGE_SIZE)) == MAX_IMAGE_SIZE
    for bad in (str(MIN_IMAGE_SIZE - 1), str(MAX_IMAGE_SIZE + 1)):
        with pytest.raises(Exception, match="expected an integer from"):
            IMAGE_SIZE(bad)


def test_table_rim_filter_is_linear_and_exact():
    """The table's rim band was Pillow's MinFilter, whose cost is kernel^2 per pixel with a kernel that grows with
    the image (size^4 in all: minutes at 4096 px). The separable minimum gives the same bytes, at the largest
    accepted size within a second."""
    import numpy as np
    from PIL import ImageFilter

    from degusta_learn.render.lifting import MAX_IMAGE_SIZE
    from degusta_learn.render.tables import _min_filter, surface_mask
    from degusta_learn.scene import default_tables

    for table in default_tables():
        for w in (97, 200):
            mask = surface_mask(table, w, w)
            k = 2 * max(2, w // 110) + 1
            assert (np.asarray(mask.filter(ImageFilter.MinFilter(k))) == _min_filter(np.asarray(mask), k)).all()
    big = np.random.default_rng(0).integers(0, 256, size=(MAX_IMAGE_SIZE, MAX_IMAGE_SIZE), dtype=np.uint8)
    t = time.process_time()
    _min_filter(big, 2 * (MAX_IMAGE_SIZE // 110) + 1)
    assert time.process_time() - t < 2.0


def test_no_rank_filter_in_rendering(monkeypatch, small_dataset):
    """No Pillow rank filter (cost kernel^2 per pixel) is left on a render path: drawing a whole image set with
    them forbidden works."""
    from PIL import ImageFilter

    from degusta_learn.render import sprites, tables
    from degusta_learn.render.grid import Grid
    from degusta_learn.render.lifting import Renderer

    def forbidden(self, image):
        raise AssertionError(f"{type(self).__name__} used while rendering")

    monkeypatch.setattr(ImageFilter.RankFilter, "filter", forbidden)
    tables._table_image.cache_clear()
    sprites._sprite.cache_clear()
    sprites._rotated.cache_clear()
    r = Renderer.for_dataset(small_dataset, 96)
    arr = small_dataset.arrangements[0]
    r.gma(arr.table, arr.placements, Grid(8, 8))
    r.uma(arr.table, arr.placements)
    r.gomo(small_dataset.catalog.types[0])
    tables._table_image.cache_clear()


REFERENCE = Path(__file__).resolve().parent.parent.parent / "shared" / "reference-models" / "SmolVLM-256M-Instruct"


@pytest.mark.skipif(not (REFERENCE / "config.json").is_file(), reason="the reference SmolVLM-256M files are absent")
def test_real_smolvlm_files_pass_and_render_the_same():
    """SmolVLM-256M-Instruct's real config, processor, generation config and chat template pass every bound, and the
    bounded render writes exactly what transformers writes."""
    from degusta_learn.vlm.hub import check_json_files
    from degusta_learn.vlm.inputs import ChatFormat, assistant_message
    from degusta_learn.vlm.load import load_processor

    check_json_files(REFERENCE, "model")
    processor = load_processor(str(REFERENCE))
    fmt = ChatFormat(processor)
    convo = [{"role": "user", "content": [{"type": "text", "text": "a"}, {"type": "image"}]}, assistant_message("b"),
             {"role": "user", "content": [{"type": "text", "text": "c"}]}]
    for messages in (MESSAGES, convo):
        for add in (True, False):
            assert fmt.render(messages, add) == processor.apply_chat_template(messages, add_generation_prompt=add,
                                                                              tokenize=False)
