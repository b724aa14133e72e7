"""The real-model hf predict configs (SmolVLM-256M/500M, Qwen2-VL-2B; zero-shot and fine-tuned) are checked
offline: no weights here, so each config is loaded and its image budget is applied to the model's full-size
replica processor (vlm/random_models/replicas.py; SmolVLM-256M's real processor files too, where they are at hand), whose
per-image token count must resolve the grid (`vlm.inputs.check_grid_resolution`)."""

from __future__ import annotations

import functools
import json
import os
import tempfile
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import pytest  # noqa: E402

from degusta_learn.config import read_yaml  # noqa: E402
from degusta_learn.errors import DegustaError  # noqa: E402
from degusta_learn.methods import build_config, get_method  # noqa: E402
from degusta_learn.render.grid import Grid  # noqa: E402
from degusta_learn.vlm.inputs import ChatFormat, check_grid_resolution, set_image_budget, tokens_per_image  # noqa: E402
from degusta_learn.vlm.random_models.replicas import REPLICAS, build_replica  # noqa: E402

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
REFERENCE = Path(__file__).resolve().parent.parent.parent / "shared" / "reference-models" / "SmolVLM-256M-Instruct"
TOKENS = {"smolvlm_256m": 64, "smolvlm_500m": 64, "qwen2vl_2b": 324}  # per image at the trained budget
# The farthest a cell border falls from a token border, in tokens (hand-computed, tests/test_grid_alignment.py):
# SmolVLM 512 px, 26 px margins, 57.5 px cells, 64 px tokens: 26 / 64; Qwen2-VL 504 px, 25 px margins, 56.75 px
# cells, 28 px tokens: 3 / 28.
OFFSET = {"smolvlm_256m": 26 / 64, "smolvlm_500m": 26 / 64, "qwen2vl_2b": 3 / 28}


@functools.cache
def replica_dir(name: str, reference: bool = False) -> Path:
    """Config + processor (no weights) of replica `name`, built once per test process."""
    out = Path(tempfile.mkdtemp(prefix=f"degusta-{name}-"))
    return build_replica(name, out, reference_dir=REFERENCE if reference else None, weights=False)


def processor_and_config(name: str, reference: bool = False):
    from transformers import AutoConfig, AutoProcessor

    folder = replica_dir(name, reference)
    return AutoProcessor.from_pretrained(str(folder), local_files_only=True), AutoConfig.from_pretrained(str(folder))


def budget_of(name: str, kind: str, cfg) -> int:
    """The image budget the hf backend applies: model.image_size, else (fine-tuned) the trained one."""
    if kind == "zeroshot":
        assert cfg.model.image_size is not None
        return cfg.model.image_size
    assert cfg.model.image_size is None  # taken from the adapter's degusta_finetune.json
    return read_yaml(CONFIGS / f"finetune_{name}.yaml")["model"]["image_size"]


@pytest.mark.parametrize("kind", ["zeroshot", "finetuned"])
@pytest.mark.parametrize("name", sorted(REPLICAS))
def test_real_model_predict_config_resolves_the_grid(name, kind):
    path = CONFIGS / f"predict_hf_{name}_{kind}.yaml"
    _, cfg = build_config(path, [], "method", get_method)
    assert cfg.backend.name == "hf" and cfg.model.name == REPLICAS[name]["hub_id"]
    grid = Grid(cfg.grid.rows, cfg.grid.cols)
    processor, config = processor_and_config(name)
    set_image_budget(processor, config, budget_of(name, kind, cfg), key="model.image_size")
    check_grid_resolution(processor, config, grid, key="model.image_size")
    per_image = tokens_per_image(processor, ChatFormat(processor), config.image_token_id)
    assert per_image == TOKENS[name] >= grid.rows * grid.cols


@pytest.mark.parametrize("name", sorted(REPLICAS))
def test_finetuned_config_matches_its_training_run(name):
    _, cfg = build_config(CONFIGS / f"predict_hf_{name}_finetuned.yaml", [], "method", get_method)
    train = read_yaml(CONFIGS / f"finetune_{name}.yaml")
    run = Path(train["trainer"].get("run_dir", "runs")) / train["trainer"]["run_name"]
    assert Path(cfg.model.adapter) == run / "best_adapter"
    assert cfg.model.name == train["model"]["name"] and cfg.method == train["method"]
    assert cfg.seed == train["seed"] and cfg.render_size == train["data"]["render_size"]
    assert (cfg.grid.rows, cfg.grid.cols) == (train["data"]["grid"]["rows"], train["data"]["grid"]["cols"])


@pytest.mark.skipif(not REFERENCE.is_dir(), reason="the real SmolVLM-256M processor files are not here")
def test_smolvlm_256m_zeroshot_config_with_the_real_processor_files():
    _, cfg = build_config(CONFIGS / "predict_hf_smolvlm_256m_zeroshot.yaml", [], "method", get_method)
    processor, config = processor_and_config("smolvlm_256m", reference=True)
    set_image_budget(processor, config, cfg.model.image_size, key="model.image_size")
    check_grid_resolution(processor, config, Grid(8, 8), key="model.image_size")
    assert tokens_per_image(processor, ChatFormat(processor), config.image_token_id) == 64


@pytest.mark.parametrize("name, size, shown", [
    ("smolvlm_256m", 64, "1 x 1"),      # the tiny zero-shot config's budget with a real SmolVLM swapped in
    ("smolvlm_256m", 448, "7 x 7"),     # the render size as a budget: one token per 64 px is 7 per side
    ("qwen2vl_2b", 196, "7 x 7"),       # 14 px patches merged 2 x 2: 28 px a token
])
def test_a_budget_too_coarse_for_the_grid_is_one_line_naming_model_image_size(name, size, shown):
    processor, config = processor_and_config(name)
    set_image_budget(processor, config, size, key="model.image_size")
    with pytest.raises(DegustaError, match=rf"^model.image_size: images give the model {shown} image tokens, "
                                           r"fewer than the 8x8 grid's 8 cells per side") as e:
        check_grid_resolution(processor, config, Grid(8, 8), key="model.image_size")
    assert "\n" not in str(e.value)
    unit = 64 if name.startswith("smolvlm") else 28
    assert f"use at least {8 * unit} px per image" in str(e.value)


def test_the_tiny_zeroshot_config_no_longer_invites_a_real_model():
    text = (CONFIGS / "predict_hf_tiny_zeroshot.yaml").read_text()
    header = "".join(line for line in text.splitlines(keepends=True) if line.startswith("#"))
    assert "e.g. HuggingFaceTB/SmolVLM-256M-Instruct" not in header
    assert "predict_hf_{smolvlm_256m,smolvlm_500m,qwen2vl_2b}_zeroshot.yaml" in header
    assert read_yaml(CONFIGS / "predict_hf_tiny_zeroshot.yaml")["model"]["image_size"] == 64


def test_an_unknown_token_geometry_is_checked_by_counting_image_tokens():
    """A model type whose token geometry the toolkit does not know: the processor's own count is checked."""
    processor, config = processor_and_config("smolvlm_256m")
    other = SimpleNamespace(model_type="another_vlm", image_token_id=config.image_token_id,
                            vision_config=config.vision_config)
    set_image_budget(processor, config, 256)  # 4 x 4 = 16 image tokens
    with pytest.raises(DegustaError, match=r"^model.image_size: an image gives the model 16 image tokens, fewer "
                                           r"than the 8x8 grid's 64 cells") as e:
        check_grid_resolution(processor, other, Grid(8, 8), key="model.image_size")
    assert "\n" not in str(e.value)
    check_grid_resolution(processor, other, Grid(4, 4), key="model.image_size")  # 16 cells: resolved
    set_image_budget(processor, config, 512)
    check_grid_resolution(processor, other, Grid(8, 8), key="model.image_size")  # 64 tokens


@pytest.mark.parametrize("name", sorted(REPLICAS))
def test_gpu_configs_draw_at_the_model_input_size_with_separate_object_sheets(name):
    """Render size = the image budget (SmolVLM: the processor's 512 px tile), the five object sheets separate, and
    the grid's cell borders where the hand-computed geometry puts them among the image tokens."""
    train = read_yaml(CONFIGS / f"finetune_{name}.yaml")
    data = train["data"]
    assert data["render_size"] == train["model"]["image_size"]
    assert data.get("compose", []) == [] and "objects" in data["include"]
    if name.startswith("smolvlm"):
        tile = REPLICAS[name]["processor"]["max_image_size"]["longest_edge"]
        if REFERENCE.is_dir():
            real = json.loads((REFERENCE / "preprocessor_config.json").read_text())["max_image_size"]["longest_edge"]
            assert tile == real
        assert data["render_size"] == tile == 512
    for kind in ("zeroshot", "finetuned"):
        _, cfg = build_config(CONFIGS / f"predict_hf_{name}_{kind}.yaml", [], "method", get_method)
        assert cfg.render_size == data["render_size"], kind
    processor, config = processor_and_config(name)
    set_image_budget(processor, config, train["model"]["image_size"], key="model.image_size")
    a = check_grid_resolution(processor, config, Grid(8, 8), render_size=data["render_size"])
    assert a is not None and a.max_offset == pytest.approx(OFFSET[name])
