"""LoRA: language-model-only targets by default, training touches adapters only, grads flow with
gradient checkpointing, adapters round-trip through plain peft, checkpoints hold no frozen base."""

from __future__ import annotations

import pytest
import torch
from finetune_support import examples, load, tiny_dir

from degusta_learn.errors import DegustaError
from degusta_learn.finetune.collate import Collator
from degusta_learn.finetune.lora import LoraConfig, apply_lora, merge_and_save, resolve_targets, save_adapter
from degusta_learn.finetune.loss import lm_loss
from degusta_learn.finetune.module import enable_gradient_checkpointing
from degusta_learn.vlm.inputs import ChatFormat
from degusta_learn.vlm.load import load_vlm


def _batch(kind, model, processor, n=2):
    fmt = ChatFormat(processor, model.generation_config)
    exs = examples(context=0)
    return Collator(processor, fmt, 4096, model.config.image_token_id)([exs[i] for i in range(n)])


@pytest.mark.parametrize("kind,language", [("idefics3", "model.text_model."), ("qwen2vl", "model.language_model.")])
def test_default_targets_are_the_language_model_only(kind, language):
    model, _ = load(kind)
    names = resolve_targets(model, LoraConfig())
    assert names and all(n.startswith(language) for n in names)
    # A plain peft target list would also have hit the vision tower's projections:
    vision_qkv = [n for n, _ in model.named_modules() if n.endswith(("q_proj", "k_proj", "v_proj", "qkv"))
                  and not n.startswith(language)]
    assert vision_qkv and not set(vision_qkv) & set(names)
    both = resolve_targets(model, LoraConfig(vision_targets=["fc1"], connector=True))
    assert any("vision" in n or "visual" in n for n in both) and set(names) < set(both)


def test_targets_that_match_nothing_name_the_key():
    model, _ = load("idefics3")
    with pytest.raises(DegustaError, match=r"lora.targets: 'qkv' matches no Linear module in model.text_model"):
        apply_lora(model, LoraConfig(targets=["q_proj", "qkv"]))
    with pytest.raises(DegustaError, match=r"lora.vision_targets: 'gate_proj'"):
        apply_lora(model, LoraConfig(vision_targets=["gate_proj"]))
    with pytest.raises(DegustaError, match="lora.mode"):
        LoraConfig(mode="qlora4")


def test_lora_steps_change_every_adapter_tensor_and_no_base_tensor():
    model, processor = load("idefics3")
    batch = _batch("idefics3", model, processor)
    peft_model = apply_lora(model, LoraConfig(r=4, dropout=0.0))
    before = {n: p.detach().clone() for n, p in peft_model.named_parameters()}
    trainable = {n for n, p in peft_model.named_parameters() if p.requires_grad}
    assert trainable and all("lora_" in n for n in trainable)
    opt = torch.optim.AdamW([p for p in peft_model.parameters() if p.requires_grad], lr=1e-2)
    peft_model.train()
    for _ in range(3):
        loss, _ = lm_loss(peft_model, batch)
        loss.backward()
        opt.step()
        opt.zero_grad()
    for n, p in peft_model.named_parameters():
        changed = not torch.equal(before[n], p.detach())
        assert changed == (n in trainable), n


@pytest.mark.parametrize("kind", ["idefics3", "qwen2vl"])
def test_lora_with_gradient_checkpointing_gives_nonzero_grads(kind):
    model, processor = load(kind)
    batch = _batch(kind, model, processor, n=1)
    peft_model = apply_lora(model, LoraConfig(r=4, dropout=0.0))
    enable_gradient_checkpointing(peft_model)
    peft_model.train()
    # lora_B starts at zero, so lora_A gets no gradient on the first step: nudge B first.
    for n, p in peft_model.named_parameters():
        if "lora_B" in n:
            torch.nn.init.normal_(p, std=0.02)
    loss, _ = lm_loss(peft_model, batch)
    loss.backward()
    grads = {n: p.grad for n, p in peft_model.named_parameters() if p.requires_grad}
    assert grads and all(g is not None and g.abs().sum() > 0 for g in grads.values())


@pytest.mark.parametrize("kind", ["idefics3", "qwen2vl"])
def test_a_frozen_vision_tower_builds_no_autograd_graph_under_checkpointing(kind):
    """transformers' enable_input_require_grads also hooks the vision tower's patch embedding: a frozen tower
    was back-propagated through (the Qwen2-VL-2B replica's first step ran out of 24 GiB). Only the text
    embeddings' output requires grad, unless the tower itself has trainable (LoRA) weights."""
    seen = {}
    for vision_targets, tower_grad in (([], False), (["fc1"], True)):
        model, processor = load(kind)
        batch = _batch(kind, model, processor, n=1)
        peft_model = apply_lora(model, LoraConfig(r=4, dropout=0.0, vision_targets=vision_targets))
        enable_gradient_checkpointing(peft_model)
        peft_model.train()
        tower = next(m for n, m in peft_model.named_modules() if n.endswith(("vision_model", "visual")))
        text = peft_model.get_input_embeddings()
        tower.get_input_embeddings().register_forward_hook(lambda m, i, o: seen.__setitem__("tower", o.requires_grad))
        text.register_forward_hook(lambda m, i, o: seen.__setitem__("text", o.requires_grad))
        for n, p in peft_model.named_parameters():
            if "lora_B" in n:
                torch.nn.init.normal_(p, std=0.02)
        loss, _ = lm_loss(peft_model, batch)
        loss.backward()
        assert seen == {"tower": tower_grad, "text": True}, (kind, vision_targets)
        grads = {n: p.grad for n, p in peft_model.named_parameters() if p.requires_grad}
        assert grads and all(g is not None and g.abs().sum() > 0 for g in grads.values())


def test_adapter_save_load_gives_identical_logits(tmp_path):
    from peft import PeftModel

    model, processor = load("idefics3")
    batch = _batch("idefics3", model, processor, n=1)
    inputs = {k: v for k, v in batch.items() if k != "labels"}
    peft_model = apply_lora(model, LoraConfig(r=4))
    for n, p in peft_model.named_parameters():
        if "lora_" in n:
            torch.nn.init.normal_(p, std=0.05)  # a non-trivial adapter
    peft_model.eval()
    with torch.no_grad():
        expected = peft_model(**inputs).logits
    out = save_adapter(peft_model, tmp_path / "adapter")
    files = sorted(f.name for f in out.iterdir())
    assert "adapter_config.json" in files and "adapter_model.safetensors" in files
    assert not any(f.startswith("model") for f in files)  # adapters only, never the base
    # Plain peft, onto a freshly loaded base:
    base, _ = load("idefics3")
    reloaded = PeftModel.from_pretrained(base, str(out)).eval()
    with torch.no_grad():
        got = reloaded(**inputs).logits
    assert torch.equal(got, expected)
    with torch.no_grad():  # and the adapter is not a no-op
        assert not torch.allclose(load("idefics3")[0](**inputs).logits, expected)
    # The degusta loader (adapter= argument) gives the same logits.
    model2, _ = load("idefics3", adapter=str(out))
    with torch.no_grad():
        assert torch.equal(model2(**inputs).logits, expected)
    # Merged: base + adapter as one plain model folder, same logits (up to float rounding).
    merged_dir = merge_and_save(peft_model, processor, tmp_path / "merged")
    merged, _ = load_vlm(str(merged_dir), device="cpu", dtype="float32")
    with torch.no_grad():
        assert torch.allclose(merged(**inputs).logits, expected, atol=1e-4)
    assert not any("lora" in n for n, _ in merged.named_parameters())
    assert tiny_dir("idefics3").exists()
    # Folded in at load (what the hf backend predicts with): a plain model, the same logits.
    folded, _ = load_vlm(str(tiny_dir("idefics3")), adapter=str(out), device="cpu", dtype="float32",
                         merge_adapter=True)
    assert not isinstance(folded, PeftModel) and not any("lora" in n for n, _ in folded.named_parameters())
    with torch.no_grad():
        assert torch.allclose(folded(**inputs).logits, expected, atol=1e-4)
    kept, _ = load_vlm(str(tiny_dir("idefics3")), adapter=str(out), device="cpu", dtype="float32",
                       trainable_adapter=True, merge_adapter=True)  # resuming training: never folded
    assert isinstance(kept, PeftModel)


def test_lightning_checkpoint_holds_only_trainable_tensors():
    from types import SimpleNamespace

    from degusta_learn.finetune.module import FinetuneModule

    model, processor = load("idefics3")
    peft_model = apply_lora(model, LoraConfig(r=4))
    cfg = SimpleNamespace(lora=LoraConfig(r=4))
    module = FinetuneModule(peft_model, processor, cfg, None, None, "grid", run_dir=None)
    ckpt = {"state_dict": module.state_dict()}
    n_all = len(ckpt["state_dict"])
    module.on_save_checkpoint(ckpt)
    kept = ckpt["state_dict"]
    assert 0 < len(kept) < n_all and all("lora_" in k for k in kept)
    assert module.strict_loading is False  # resuming loads the adapter tensors into the rebuilt model
