"""A frozen vision tower's features computed once per distinct picture (`finetune.tower_cache`)."""

from __future__ import annotations

import pytest
import torch

from degusta_learn.finetune.module import freeze_batch_norms
from degusta_learn.finetune.tower_cache import cache_frozen_tower, find_tower, tower_is_frozen
from degusta_learn.pretrain.base import BaseArchitecture, build_base

ARCH = dict(vision_channels=[8, 8, 16, 16], vision_stem=8, text_hidden=32, text_layers=1, text_heads=2,
            text_kv_heads=1, text_intermediate=64, vocab_size=2048)


def _frozen_base():
    model, _ = build_base(BaseArchitecture(**ARCH), seed=3)
    model.train()
    tower = find_tower(model)
    tower.requires_grad_(False)
    freeze_batch_norms(tower)  # as fine-tuning keeps a frozen tower's BatchNorms
    return model, tower


def _pictures(n: int, seed: int = 0) -> torch.Tensor:
    return torch.randn(n, 3, 256, 256, generator=torch.Generator().manual_seed(seed))


def _counting(cache):
    """Count the pictures the tower's own forward really sees (under the cache)."""
    seen, forward = [], cache.forward

    def counted(pixel_values, **kwargs):
        seen.append(len(pixel_values))
        return forward(pixel_values, **kwargs)

    cache.forward = counted
    return seen


def test_a_frozen_tower_gives_the_same_features_and_runs_once_per_distinct_picture():
    model, tower = _frozen_base()
    pics = _pictures(3)
    batch = torch.cat([pics, pics[:2], pics[1:2]])  # 6 pictures, 3 distinct
    with torch.no_grad():
        plain = model.model.get_image_features(pixel_values=batch).pooler_output
    cache = cache_frozen_tower(model)
    first = model.model.get_image_features(pixel_values=batch).pooler_output
    again = model.model.get_image_features(pixel_values=pics.flip(0)).pooler_output
    assert torch.allclose(first, plain, atol=1e-6)
    assert torch.allclose(again, plain[:3].flip(0), atol=1e-6)
    assert (cache.misses, cache.hits) == (3, 6)
    first.sum().backward()  # the projector still trains on cached features
    assert model.model.multi_modal_projector.linear_1.weight.grad is not None


def test_the_cache_steps_aside_whenever_the_tower_could_change_or_has_other_inputs():
    model, tower = _frozen_base()
    cache = cache_frozen_tower(model)
    pics = _pictures(2)
    next(tower.parameters()).requires_grad_(True)  # a trainable tower weight (full fine-tuning, vision LoRA)
    assert not tower_is_frozen(tower)
    model.model.get_image_features(pixel_values=pics)
    next(tower.parameters()).requires_grad_(False)
    tower.train()  # BatchNorms in training mode use the batch's statistics
    assert not tower_is_frozen(tower)
    model.model.get_image_features(pixel_values=pics)
    tower.eval()
    assert tower_is_frozen(tower)
    model.model.get_image_features(pixel_values=pics.requires_grad_(True))  # gradients asked of the pixels
    assert (cache.hits, cache.misses) == (0, 0)
    model.model.get_image_features(pixel_values=pics.detach())
    assert (cache.hits, cache.misses) == (0, 2)


class MaskedTower(torch.nn.Module):
    """A tower with a tensor input beside the pixels (as Idefics3's patch mask) and a dropout."""

    def __init__(self, p: float):
        super().__init__()
        self.proj, self.drop = torch.nn.Linear(4, 3), torch.nn.Dropout(p)

    def forward(self, pixel_values, mask=None, return_dict=True):
        from transformers.modeling_outputs import BaseModelOutput

        x = self.drop(self.proj(pixel_values))
        return BaseModelOutput(last_hidden_state=x if mask is None else x * mask[..., None])


def test_other_tensor_inputs_and_active_dropout_bypass_the_cache():
    root = torch.nn.Module()
    root.vision_model = MaskedTower(0.0).requires_grad_(False)
    cache = cache_frozen_tower(root)
    x = torch.randn(2, 5, 4)
    out = root.vision_model(x, mask=torch.ones(2, 5))
    assert isinstance(out.last_hidden_state, torch.Tensor) and (cache.hits, cache.misses) == (0, 0)
    root.vision_model(x)
    root.vision_model(pixel_values=x, return_dict=True)
    assert (cache.hits, cache.misses) == (2, 2)  # dropout with p = 0 changes nothing, even in training mode
    root.vision_model.drop.p = 0.1
    assert not tower_is_frozen(root.vision_model)
    root.vision_model(x)
    assert (cache.hits, cache.misses) == (2, 2)
    root.vision_model.eval()
    assert tower_is_frozen(root.vision_model)


def test_the_cache_keeps_at_most_max_bytes_and_tells_pictures_apart_by_their_bytes():
    model, tower = _frozen_base()
    one = 64 * 16 * 4  # a picture's features: 8 x 8 tokens of the last 16 channels, float32
    cache = cache_frozen_tower(model, max_bytes=2 * one + 1)
    seen = _counting(cache)
    pics = _pictures(3)
    model.model.get_image_features(pixel_values=pics)
    assert len(cache.features) == 2 and cache.bytes == 2 * one and seen == [3]
    model.model.get_image_features(pixel_values=pics[2:])  # the newest stays
    assert seen == [3]
    model.model.get_image_features(pixel_values=pics[:1])  # the oldest went
    assert seen == [3, 1]
    nudged = pics[2:].clone()
    nudged[0, 0, 0, 0] += 1e-3
    model.model.get_image_features(pixel_values=nudged)
    assert seen == [3, 1, 1]


def test_lora_fine_tuning_leaves_the_tower_frozen_and_the_cache_in_use():
    from degusta_learn.finetune.lora import LoraConfig, apply_lora
    from degusta_learn.finetune.module import freeze_batch_norms

    model, _ = build_base(BaseArchitecture(**ARCH), seed=3)
    model = apply_lora(model, LoraConfig(mode="lora", r=4, alpha=8, targets=["q_proj", "v_proj"], connector=True))
    model.train()
    freeze_batch_norms(model)
    cache = cache_frozen_tower(model)
    assert cache is not None and tower_is_frozen(cache.tower)
    pics = _pictures(2)
    a = model.base_model.model.model.get_image_features(pixel_values=pics).pooler_output
    b = model.base_model.model.model.get_image_features(pixel_values=pics).pooler_output
    assert torch.equal(a, b) and (cache.misses, cache.hits) == (2, 2)


@pytest.mark.parametrize("name", ["vision_model", "vision_tower"])
def test_find_tower_knows_the_tower_names(name):
    root = torch.nn.Module()
    root.inner = torch.nn.Module()
    setattr(root.inner, name, torch.nn.Linear(2, 2))
    assert find_tower(root) is getattr(root.inner, name)
    assert find_tower(torch.nn.Linear(2, 2)) is None


def test_features_computed_under_autocast_are_kept_apart_from_full_precision_ones():
    model, _ = _frozen_base()
    cache = cache_frozen_tower(model)
    pics = _pictures(1)
    plain = model.model.vision_tower(pics).last_hidden_state
    with torch.autocast("cpu", dtype=torch.bfloat16):
        half = model.model.vision_tower(pics).last_hidden_state
    assert (cache.misses, cache.hits) == (2, 0)
    assert plain.dtype == torch.float32 and half.dtype == torch.bfloat16
    assert model.model.vision_tower(pics).last_hidden_state.dtype == torch.float32 and cache.hits == 1


def test_degusta_train_with_the_cache_learns_exactly_what_it_learns_without(tmp_path, monkeypatch):
    import csv

    from finetune_support import dataset

    from degusta_learn.finetune import tower_cache
    from degusta_learn.methods import run_train
    from degusta_learn.pretrain.export import save_random_base
    from degusta_learn.scene import save_dataset

    base = save_random_base(tmp_path / "base", BaseArchitecture(**{**ARCH, "text_layers": 2, "text_heads": 4}))
    data = save_dataset(dataset(), tmp_path / "data")
    losses, adapters, caches = {}, {}, []
    monkeypatch.setattr(tower_cache, "cache_frozen_tower",
                        lambda model, f=tower_cache.cache_frozen_tower: caches.append(f(model)) or caches[-1])
    for cached in (True, False):
        run = run_train("configs/finetune_tiny_base_cpu.yaml", [
            f"dataset={data}", f"model.name={base}", f"model.cache_tower={cached}", f"trainer.run_dir={tmp_path}",
            f"trainer.run_name=cache_{cached}", "trainer.max_steps=3", "trainer.progress_bar=false",
            "trainer.log_every_n_steps=1", "data.val_episodes=0", "data.max_train_episodes=6", "data.batch_size=2",
            "data.contexts=[2]", "trainer.precision=32-true", "trainer.monitor=null"])
        with open(next((run / "csv").glob("version_*/metrics.csv"))) as f:
            losses[cached] = [float(r["train/loss"]) for r in csv.DictReader(f) if r.get("train/loss")]
        from safetensors.torch import load_file

        adapters[cached] = load_file(run / "adapter" / "adapter_model.safetensors")
    assert len(caches) == 1 and caches[0].hits > 0 and caches[0].misses > 0  # the object sheet and tables recur
    assert len(losses[True]) == 3 and losses[True] == losses[False]
    assert all(torch.equal(adapters[True][k], adapters[False][k]) for k in adapters[False])
