"""Full-size replicas (vlm/random_models/replicas.py): each one's published size, built on the meta device (no memory)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.vlm.random_models.replicas import REPLICAS, meta_replica, replica_config, replica_spec

REFERENCE = Path(__file__).resolve().parent.parent.parent / "shared" / "reference-models" / "SmolVLM-256M-Instruct"
CONFIGS = Path(__file__).resolve().parent.parent / "configs"


@pytest.mark.parametrize("name", sorted(REPLICAS))
def test_replica_has_the_published_parameter_count(name):
    spec = REPLICAS[name]
    n = sum(p.numel() for p in meta_replica(name).parameters())
    assert abs(n - spec["published_params"]) / spec["published_params"] < 0.002, (name, n)


def test_published_totals():
    assert 256.4e6 < REPLICAS["smolvlm_256m"]["published_params"] < 256.6e6
    assert REPLICAS["qwen2vl_2b"]["published_params"] == 4_417_971_200 // 2  # bf16 bytes in the index


@pytest.mark.parametrize("name", sorted(REPLICAS))
def test_every_gpu_config_names_its_replica(name):
    text = (CONFIGS.parent / REPLICAS[name]["configs"][0]).read_text()
    assert f"name: {REPLICAS[name]['hub_id']}" in text


def test_unknown_family_is_one_line_naming_the_key():
    with pytest.raises(DegustaError, match=r"^replica: unknown model family 'llava_7b'; expected one of") as e:
        replica_spec("llava_7b")
    assert "\n" not in str(e.value)
    with pytest.raises(DegustaError, match=r"^model.name: unknown model family"):
        replica_config("nope", key="model.name")


def test_image_token_counts_follow_the_published_geometry():
    s = REPLICAS["smolvlm_256m"]
    side = s["vision"]["image_size"] // s["vision"]["patch_size"]  # 32 patches per side of a 512 px tile
    assert side**2 // s["scale_factor"] ** 2 == s["processor"]["image_seq_len"] == 64
    q = REPLICAS["qwen2vl_2b"]["vision"]
    assert (448 // (q["patch_size"] * q["spatial_merge_size"])) ** 2 == 256  # the 2B config's 448 px image


@pytest.mark.skipif(not REFERENCE.is_dir(), reason="the real SmolVLM-256M config files are not here")
def test_smolvlm_256m_matches_the_real_config_files():
    real = json.loads((REFERENCE / "config.json").read_text())
    cfg = replica_config("smolvlm_256m")
    assert cfg.scale_factor == real["scale_factor"] and cfg.image_token_id == real["image_token_id"]
    for key in REPLICAS["smolvlm_256m"]["text"]:
        ours = cfg.text_config.rope_parameters["rope_theta"] if key == "rope_theta" else getattr(cfg.text_config, key)
        assert ours == real["text_config"][key], key
    for key in REPLICAS["smolvlm_256m"]["vision"]:
        assert getattr(cfg.vision_config, key) == real["vision_config"][key], key
    pre = json.loads((REFERENCE / "preprocessor_config.json").read_text())
    proc = json.loads((REFERENCE / "processor_config.json").read_text())
    p = REPLICAS["smolvlm_256m"]["processor"]
    assert (p["size"], p["max_image_size"], p["do_image_splitting"]) == (
        pre["size"], pre["max_image_size"], pre["do_image_splitting"])
    assert p["image_seq_len"] == proc["image_seq_len"]
