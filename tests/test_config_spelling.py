"""One spelling per concept for a VLM (issue 51, item 3): `model:` and `decoding:` (vlm/settings.py) in fine-tuning,
pretraining's validation and every zero-shot predict config; `render_size` wherever the lifted images' pixel size is
meant; `data.val_contexts`. Every old spelling is one line naming the new key, in a YAML file and with `--set`."""

from __future__ import annotations

import pytest
import yaml

from degusta_learn.config import load_config, read_yaml
from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.compare import CompareConfig
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.methods import build_config, get_method
from degusta_learn.pretrain.config import PretrainConfig
from degusta_learn.shipped import shipped_config
from degusta_learn.vlm.settings import API_MAX_NEW_TOKENS, DecodingSettings, ModelSettings

ON_REPEAT = "decoding.on_repeat (skip, stop, next or substitute; true was stop)"

PREDICT = [  # (shipped config, old key, a value, the new key)
    ("predict_hf_base_zeroshot", "backend.model", "tiny_vlm_base", "model.name"),
    ("predict_hf_base_zeroshot", "backend.adapter", "runs/a", "model.adapter"),
    ("predict_hf_base_zeroshot", "backend.dtype", "float32", "model.dtype"),
    ("predict_hf_base_zeroshot", "backend.image_size", 256, "model.image_size"),
    ("predict_hf_base_zeroshot", "backend.max_tokens", 300, "decoding.max_new_tokens"),
    ("predict_hf_base_zeroshot", "backend.constrained", True, "decoding.constrained"),
    ("predict_hf_base_zeroshot", "backend.on_repeat", "stop", "decoding.on_repeat"),
    ("predict_hf_base_zeroshot", "backend.report_unconstrained", False, "decoding.report_unconstrained"),
    ("predict_hf_base_zeroshot", "backend.stop_on_repeat", True, ON_REPEAT),
    ("predict_hf_base_zeroshot", "image_size", 256, "render_size"),
    ("predict_hf_base_zeroshot", "n", 5, "decoding.n"),
    ("predict_hf_base_zeroshot", "temperature", 1.0, "decoding.temperature"),
    ("predict_hf_base_zeroshot", "aggregation", "steps", "decoding.aggregation"),
    ("zeroshot_mogma_gpt4o", "backend.model", "gpt-4o", "model.name"),
    ("zeroshot_mogma_gpt4o", "backend.max_tokens", 1024, "decoding.max_new_tokens"),
    ("zeroshot_mogma_gpt4o", "image_size", 768, "render_size"),
]
TRAIN = [  # (config class, shipped config, old key, a value, the new key)
    (FinetuneConfig, "finetune_tiny_cpu", "eval.constrained", True, "decoding.constrained"),
    (FinetuneConfig, "finetune_tiny_cpu", "eval.report_unconstrained", True, "decoding.report_unconstrained"),
    (FinetuneConfig, "finetune_tiny_cpu", "eval.max_new_tokens", 512, "decoding.max_new_tokens"),
    (FinetuneConfig, "finetune_tiny_cpu", "eval.on_repeat", "skip", "decoding.on_repeat"),
    (FinetuneConfig, "finetune_tiny_cpu", "eval.n", 1, "decoding.n"),
    (FinetuneConfig, "finetune_tiny_cpu", "eval.temperature", None, "decoding.temperature"),
    (FinetuneConfig, "finetune_tiny_cpu", "eval.aggregation", "steps", "decoding.aggregation"),
    (FinetuneConfig, "finetune_tiny_cpu", "eval.stop_on_repeat", True, ON_REPEAT),
    (FinetuneConfig, "finetune_tiny_cpu", "data.val_context", 4, "data.val_contexts (a list, e.g. [4])"),
    (PretrainConfig, "pretrain_tiny_vlm_cpu", "eval", {"constrained": True}, "decoding"),
    (CompareConfig, "compare_naturalistic", "image_size", 256, "render_size"),
]


def _with(data: dict, dotted: str, value) -> dict:
    """`data` with `dotted` set (sections created as needed)."""
    *sections, key = dotted.split(".")
    node = data
    for s in sections:
        node = node.setdefault(s, {})
    node[key] = value
    return data


def _renamed(old: str, new: str) -> str:
    return f"'{old}' is now '{new}' (one spelling per concept across config kinds: docs/configs.md)"


def _one_line(e: pytest.ExceptionInfo, old: str, new: str) -> None:
    message = str(e.value)
    assert "\n" not in message and message.endswith(_renamed(old, new)), message


@pytest.mark.parametrize("name, old, value, new", PREDICT)
def test_an_old_predict_spelling_in_a_file_is_one_line_naming_the_new_key(tmp_path, name, old, value, new):
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(_with(read_yaml(shipped_config(name)), old, value)))
    with pytest.raises(DegustaError) as e:
        build_config(path, [], "method", get_method)
    _one_line(e, old, new)
    assert str(e.value).startswith(f"{path}: ")


@pytest.mark.parametrize("name, old, value, new", PREDICT)
def test_an_old_predict_spelling_with_set_is_one_line_naming_the_new_key(name, old, value, new):
    with pytest.raises(DegustaError) as e:
        build_config(shipped_config(name), [f"{old}={yaml.safe_dump(value, default_flow_style=True).strip()}"
                                            .removesuffix("...").strip()], "method", get_method)
    _one_line(e, old, new)


@pytest.mark.parametrize("cls, name, old, value, new", TRAIN)
def test_an_old_training_or_compare_spelling_is_one_line_naming_the_new_key(tmp_path, cls, name, old, value, new):
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(_with(read_yaml(shipped_config(name)), old, value)))
    with pytest.raises(DegustaError) as e:
        load_config(cls, path)
    _one_line(e, old, new)
    flow = yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip()
    with pytest.raises(DegustaError) as e:
        load_config(cls, shipped_config(name), [f"{old}={flow}"])
    _one_line(e, old, new)


def test_a_whole_config_of_the_previous_version_names_its_first_old_key(tmp_path):
    """The tiny zero-shot predict config as the previous version shipped it."""
    path = tmp_path / "predict_hf_tiny_zeroshot.yaml"
    path.write_text("method: mogma\ndataset: data/naturalistic\nout: runs/p.jsonl\n"
                    "backend:\n  name: hf\n  model: runs/tiny/idefics3\n  constrained: true\n  device: cpu\n"
                    "  dtype: float32\n  image_size: 64\n  max_tokens: auto\n"
                    "n: 1\ntemperature: 0.0\nimage_size: 224\n")
    with pytest.raises(DegustaError, match=r"'image_size' is now 'render_size'"):  # the top level first
        build_config(path, [], "method", get_method)
    text = path.read_text().replace("n: 1\ntemperature: 0.0\nimage_size: 224\n", "")
    path.write_text(text)
    with pytest.raises(DegustaError, match=r"'backend.constrained' is now 'decoding.constrained'"):
        build_config(path, [], "method", get_method)  # then a section's keys, in order


def test_the_one_model_and_decoding_sections():
    """One class each, one default each; fine-tuning's model section adds its training keys."""
    from degusta_learn.finetune.config import ModelConfig
    from degusta_learn.prompting.runner import ZeroShotConfig

    assert issubclass(ModelConfig, ModelSettings)
    assert ZeroShotConfig.__dataclass_fields__["model"].type in ("ModelSettings", ModelSettings)
    for cls in (ZeroShotConfig, FinetuneConfig, PretrainConfig):
        assert cls.__dataclass_fields__["decoding"].type in ("DecodingSettings", DecodingSettings)
    d = DecodingSettings()
    assert (d.constrained, d.on_repeat, d.max_new_tokens, d.n, d.aggregation, d.temperature,
            d.report_unconstrained) == (None, "skip", "auto", 1, "steps", None, True)
    assert ModelSettings() == ModelSettings(name="", dtype="auto", image_size=None, adapter=None)
    assert d.resolved(local=True).constrained is True and d.resolved(local=False).constrained is False
    assert DecodingSettings(constrained=False).resolved(local=True).constrained is False


def test_constrained_null_is_true_for_a_local_model_and_false_for_an_api():
    _, hf = build_config(shipped_config("predict_hf_base_zeroshot"), ["decoding.constrained=null"], "method",
                         get_method)
    _, api = build_config(shipped_config("zeroshot_mogma_gpt4o"), [], "method", get_method)
    assert hf.decoding.constrained is True and api.decoding.constrained is False
    ft = load_config(FinetuneConfig, shipped_config("finetune_tiny_cpu"), ["decoding.constrained=null"])
    assert ft.decoding.constrained is True


@pytest.mark.parametrize("override, key", [
    ("model.adapter=runs/x/adapter", "model.adapter"), ("model.dtype=bfloat16", "model.dtype"),
    ("model.image_size=448", "model.image_size"), ("decoding.on_repeat=stop", "decoding.on_repeat"),
    ("decoding.report_unconstrained=false", "decoding.report_unconstrained"),
    ("decoding.constrained=true", "decoding.constrained"),
])
def test_a_local_model_key_given_to_an_api_backend_is_one_line(override, key):
    with pytest.raises(DegustaError) as e:
        build_config(shipped_config("zeroshot_mogma_gpt4o"), [override], "method", get_method)
    message = str(e.value)
    assert "\n" not in message and f"zeroshot_mogma_gpt4o.yaml: {key}: " in message and "openai backend" in message
    # the same keys at their defaults are what an API backend takes
    build_config(shipped_config("zeroshot_mogma_gpt4o"), ["decoding.constrained=false", "model.image_size=null"],
                 "method", get_method)


def test_model_name_defaults_to_the_backends_own():
    _, cfg = build_config(shipped_config("zeroshot_mogma_gpt4o"), ["model={}"], "method", get_method)
    assert cfg.model.name == "gpt-4o"
    _, cfg = build_config(shipped_config("zeroshot_mogma_gpt4o"), ["model={}", "backend={name: replay, path: x}"],
                          "method", get_method)
    assert cfg.model.name == "replay"


def test_auto_max_new_tokens_of_an_api_backend_is_the_fixed_budget(tmp_path):
    from conftest import make_small_dataset

    from degusta_learn.prompting.runner import ZeroShotRun

    ds = make_small_dataset(n_participants=3, n_trials=3)
    _, cfg = build_config(shipped_config("zeroshot_mogma_gpt4o"), [f"out={tmp_path / 'p.jsonl'}"], "method",
                          get_method)
    assert cfg.decoding.max_new_tokens == "auto" and ZeroShotRun(cfg, ds).max_tokens == API_MAX_NEW_TOKENS == 1024
    _, cfg = build_config(shipped_config("zeroshot_mogma_gpt4o"), [f"out={tmp_path / 'p.jsonl'}",
                                                                  "decoding.max_new_tokens=300"], "method", get_method)
    assert ZeroShotRun(cfg, ds).max_tokens == 300


def test_fine_tuning_refuses_an_adapter_and_an_empty_model_name():
    with pytest.raises(DegustaError, match=r"yaml: model.adapter: fine-tuning trains a new adapter"):
        load_config(FinetuneConfig, shipped_config("finetune_tiny_cpu"), ["model.adapter=runs/x/adapter"])
    with pytest.raises(DegustaError, match=r"yaml: model.name: required"):
        load_config(FinetuneConfig, shipped_config("finetune_tiny_cpu"), ["model.name=''"])


def test_pretraining_validation_takes_a_number_of_tokens_and_one_greedy_answer():
    cfg = load_config(PretrainConfig, shipped_config("pretrain_tiny_vlm_cpu"))
    assert (cfg.decoding.constrained, cfg.decoding.on_repeat, cfg.decoding.max_new_tokens) == (True, "stop", 240)
    for override in ("decoding.max_new_tokens=auto", "decoding.n=3"):
        with pytest.raises(DegustaError, match=r"yaml: decoding: pretraining's validation answers each question once"):
            load_config(PretrainConfig, shipped_config("pretrain_tiny_vlm_cpu"), [override])


def test_every_shipped_vlm_config_decodes_constrained():
    """One default, and every shipped config says it: a local model decodes inside the answer grammar."""
    from degusta_learn.shipped import shipped_names

    names = [n for n in shipped_names() if n.startswith(("predict_hf_", "finetune_", "pretrain_"))]
    assert len(names) >= 16
    for name in names:
        assert read_yaml(shipped_config(name))["decoding"]["constrained"] is True, name
    for name in (n for n in shipped_names() if n.startswith("predict_hf_")):
        assert read_yaml(shipped_config(name))["decoding"]["max_new_tokens"] == "auto", name
