"""Tiny offline VLMs load through the Auto classes; image-token counts match; bad model ids fail fast."""

from __future__ import annotations

import re
import time

import pytest
import torch
from finetune_support import load, tiny_dir
from PIL import Image

from degusta_learn.errors import DegustaError
from degusta_learn.render.grid import Grid
from degusta_learn.vlm.inputs import ChatFormat, check_grid_resolution, set_image_budget, tokens_per_image
from degusta_learn.vlm.load import load_vlm, quiet_peft


@pytest.mark.parametrize("kind", ["idefics3", "qwen2vl"])
def test_tiny_model_loads_like_a_hub_model(kind):
    model, processor = load(kind)
    assert type(model).__name__ == {"idefics3": "Idefics3ForConditionalGeneration",
                                    "qwen2vl": "Qwen2VLForConditionalGeneration"}[kind]
    tok = processor.tokenizer
    assert model.config.get_text_config().vocab_size == len(tok)
    assert model.config.image_token_id == tok.convert_tokens_to_ids(processor.image_token)
    assert "token_type_ids" not in tok.model_input_names
    if kind == "qwen2vl":
        assert type(tok).__name__ in ("Qwen2TokenizerFast", "Qwen2Tokenizer")
    # Nothing of this model is big enough to matter in git or a test cache.
    assert sum(f.stat().st_size for f in tiny_dir(kind).iterdir()) < 2_000_000


@pytest.mark.parametrize("kind", ["idefics3", "qwen2vl"])
def test_image_token_count_matches_the_model(kind):
    model, processor = load(kind)
    fmt = ChatFormat(processor, model.generation_config)
    per_image = tokens_per_image(processor, fmt, model.config.image_token_id)
    if kind == "idefics3":  # one tile per image: (image_size / patch)^2 / scale^2, no splitting
        vc = model.config.vision_config
        assert per_image == (vc.image_size // vc.patch_size) ** 2 // model.config.scale_factor ** 2
    else:  # 224 px -> 16 x 16 patches merged 2 x 2
        assert per_image == 64
    messages = [{"role": "user", "content": [{"type": "image"}, {"type": "image"}, {"type": "image"},
                                             {"type": "text", "text": "where?"}]}]
    images = [Image.new("RGB", (300, 300), c) for c in ("red", "green", "blue")]  # rendered images are square
    enc = processor(text=[fmt.prompt_text(messages)], images=[images], add_special_tokens=False, return_tensors="pt")
    assert int((enc["input_ids"] == model.config.image_token_id).sum()) == 3 * per_image
    with torch.no_grad():
        out = model(**enc)  # raises if image features and image tokens disagree
    assert out.logits.shape[1] == enc["input_ids"].shape[1]


def test_image_budget_is_explicit_and_checked():
    model, processor = load("idefics3")
    set_image_budget(processor, model.config, 32)
    fmt = ChatFormat(processor, model.generation_config)
    assert tokens_per_image(processor, fmt, model.config.image_token_id) == (32 // 4) ** 2 // 4
    with pytest.raises(DegustaError, match="model.image_size"):
        set_image_budget(processor, model.config, 36)
    # 32 px gives 4 x 4 image tokens: a grid method on an 8 x 8 grid could not see single cells
    with pytest.raises(DegustaError, match=r"model.image_size: images give the model 4 x 4 image tokens.* 64 px"):
        check_grid_resolution(processor, model.config, Grid(8, 8))
    check_grid_resolution(processor, model.config, Grid(4, 4))  # a 4 x 4 grid is resolved


def test_unloadable_model_id_fails_fast_naming_the_key(tmp_path):
    start = time.time()
    with pytest.raises(DegustaError, match=r"model: .*not-a-real-org/no-such-vlm.*local Hugging Face cache"):
        load_vlm("not-a-real-org/no-such-vlm")
    assert time.time() - start < 5  # no hub timeout
    with pytest.raises(DegustaError, match="model.name: model folder .*missing.* not found"):
        load_vlm(str(tmp_path / "missing"), key="model.name")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DegustaError, match="without config.json"):
        load_vlm(str(tmp_path / "empty"))


def test_a_relative_model_path_not_found_says_where_it_was_looked_for(tmp_path, monkeypatch):
    # `runs/tiny_vlm_base` run from another folder: one slash reads as a hub id; say the folder too, and
    # that the shipped base is named by its name alone
    monkeypatch.chdir(tmp_path)
    with pytest.raises(DegustaError, match=r"model.name: 'runs/tiny_vlm_base' is not in the local Hugging "
                                           r"Face cache .*as a folder it would be .*runs/tiny_vlm_base: a "
                                           r"relative path is read from the current directory \(the shipped model "
                                           r"'tiny_vlm_base' is named by its name alone"):
        load_vlm("runs/tiny_vlm_base", key="model.name")
    with pytest.raises(DegustaError, match=r"model folder ./tiny_vlm_base not found \(the shipped model "):
        load_vlm("./tiny_vlm_base")


def test_adapter_folder_must_be_a_peft_adapter(tmp_path):
    with pytest.raises(DegustaError, match="adapter: .*adapter_config.json"):
        load_vlm(str(tiny_dir("idefics3")), adapter=str(tmp_path))


def test_device_and_dtype_errors_name_the_configs_own_keys():
    import torch

    if torch.cuda.is_available():
        pytest.skip("needs a machine without a CUDA device")
    with pytest.raises(DegustaError, match=r"^backend.device: 'cuda' requested but no CUDA device is visible"):
        load_vlm(str(tiny_dir("idefics3")), device="cuda", key="model.name", device_key="backend.device")
    with pytest.raises(DegustaError, match=r"^model.dtype: expected one of"):
        load_vlm(str(tiny_dir("idefics3")), dtype="fp8", key="model.name", device_key="backend.device")
    with pytest.raises(DegustaError, match=r"^device: 'cuda:1' requested"):
        load_vlm(str(tiny_dir("idefics3")), device="cuda:1")
    with pytest.raises(DegustaError, match=r"^backend.device: 'tpu' is not a device"):  # was torch's traceback
        load_vlm(str(tiny_dir("idefics3")), device="tpu", key="model.name", device_key="backend.device")


def test_a_corrupt_or_foreign_adapter_is_one_line_naming_the_key_and_folder(tmp_path):
    import json
    import warnings

    import peft

    model, _ = load("idefics3")
    with quiet_peft():
        lora = peft.get_peft_model(model, peft.LoraConfig(r=2, target_modules=["q_proj"], task_type="CAUSAL_LM"))
    good = tmp_path / "good"
    lora.save_pretrained(str(good))
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)  # peft's deprecated-attribute warning is silenced
        load_vlm(str(tiny_dir("idefics3")), adapter=str(good), key="model.name")

    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    (corrupt / "adapter_config.json").write_text("{")
    with pytest.raises(DegustaError, match=rf"^model.adapter: {corrupt / 'adapter_config.json'}: not readable as "
                                           r"JSON \(JSONDecodeError"):
        load_vlm(str(tiny_dir("idefics3")), adapter=str(corrupt), key="model.name")

    foreign = tmp_path / "foreign"  # an adapter of a model whose layers have other names
    foreign.mkdir()
    config = json.loads((good / "adapter_config.json").read_text())
    (foreign / "adapter_config.json").write_text(json.dumps({**config, "target_modules": ["no_such_proj"]}))
    with pytest.raises(DegustaError, match=rf"^adapter: cannot load the adapter in {foreign} onto this model"):
        load_vlm(str(tiny_dir("idefics3")), adapter=str(foreign))


@pytest.mark.parametrize("name, content, message", [
    ("config.json", b"{bad", "config.json: not readable as JSON (JSONDecodeError"),
    ("tokenizer_config.json", b"[1, 2]", "tokenizer_config.json: expected a JSON object, got list"),
    ("tokenizer.json", bytes(range(128, 228)), "tokenizer.json: not readable as JSON (UnicodeDecodeError"),
    ("processor_config.json", b"", "processor_config.json: not readable as JSON"),
])
def test_a_corrupt_json_file_of_a_model_folder_is_named(tmp_path, name, content, message):
    """The libraries' errors named no file (JSONDecodeError), or were an AttributeError on a list."""
    from degusta_learn.vlm.hub import resolve_model

    (tmp_path / "config.json").write_text('{"model_type": "idefics3"}')
    (tmp_path / name).write_bytes(content)
    with pytest.raises(DegustaError, match=re.escape(f"model.name: {tmp_path / name}: {message.split(': ', 1)[1]}")):
        resolve_model(str(tmp_path), "model.name")


@pytest.mark.parametrize("kind", ["idefics3", "qwen2vl"])
def test_a_config_whose_image_token_is_not_the_processors_is_refused_at_load(tmp_path, kind):
    """An edited or foreign config.json used to fail at the first answer ("Image features and image tokens do
    not match, tokens: 0"), after a predict run had set up its cache and ledger."""
    import json
    import shutil

    folder = shutil.copytree(tiny_dir(kind), tmp_path / kind)
    load_vlm(str(folder), device="cpu")  # as built: the ids agree
    config = json.loads((folder / "config.json").read_text())
    config["image_token_id"] += 1
    (folder / "config.json").write_text(json.dumps(config))
    with pytest.raises(DegustaError, match=r"^model.name: .*config.json's image_token_id is \d+, but the "
                                           r"processor writes its image placeholder .* as token \d+"):
        load_vlm(str(folder), device="cpu", key="model.name")


@pytest.mark.parametrize("template, error", [("{% for m in messages %}{{ m.content }{% endfor %}", "TemplateSyntaxError"),
                                             ('{{ raise_exception("no chat here") }}', "TemplateError: no chat here")])
def test_a_chat_template_that_cannot_render_is_refused_when_the_backend_loads(tmp_path, template, error):
    """It failed at the first answer ("hf: TemplateSyntaxError: unexpected '}'"), naming no folder, after a
    predict run had set up its cache and ledger."""
    import shutil

    from degusta_learn.prompting.backends.hf import HFBackend

    folder = shutil.copytree(tiny_dir("idefics3"), tmp_path / "model")
    (folder / "chat_template.jinja").write_text(template)
    with pytest.raises(DegustaError, match=rf"^model.name: '{re.escape(str(folder))}': its chat template cannot "
                                           rf"render a message \({error}"):
        HFBackend(str(folder), device="cpu")
