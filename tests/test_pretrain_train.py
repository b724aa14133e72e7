"""`degusta train` with `kind: pretrain` on a tiny FastVLM: train, validate, export, resume, load, refuse bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.methods import run_train
from degusta_learn.pretrain.base import BaseArchitecture, build_base
from degusta_learn.pretrain.dense import DenseHead, DenseLabels, OracleTeacher, OracleTokens, projector_of
from degusta_learn.pretrain.tasks import PerceptionExamples, TaskMix
from degusta_learn.pretrain.train import PretrainConfig
from degusta_learn.render.grid import Grid
from degusta_learn.scene import default_catalog, default_tables
from degusta_learn.training import x86_with_avx2

CONFIG = Path(__file__).parent.parent / "configs" / "pretrain_tiny_vlm_cpu.yaml"
TINY = ["model.vision_channels=[8,8,16,16]", "model.vision_stem=8", "model.text_hidden=32", "model.text_layers=1",
        "model.text_heads=2", "model.text_kv_heads=1", "model.text_intermediate=64", "model.vocab_size=2048",
        "data.retrieval_layer=0", "data.retrieval_head=1", "data.tower_steps=0"]


def _overrides(tmp_path: Path, steps: int) -> list[str]:
    return TINY + [f"trainer.run_dir={tmp_path / 'runs'}", "trainer.run_name=p", f"trainer.max_steps={steps}",
                   "data.steps_per_epoch=2", "data.val_examples=3", "data.batch_size=2", "trainer.progress_bar=false",
                   "decoding.max_new_tokens=120", "trainer.log_every_n_steps=1", f"export={tmp_path / 'base'}"]


def test_shipped_pretrain_config_loads_and_is_checked():
    cfg = load_config(PretrainConfig, CONFIG)
    assert cfg.kind == "pretrain" and cfg.model.tokens_per_image == 64
    # the shipped recipe (experiments/tiny_base_log.md, point 19): the readout on, the last weights exported
    assert cfg.data.readout_weight > 0 and cfg.trainer.monitor is None
    with pytest.raises(DegustaError, match="model.image_size"):
        load_config(PretrainConfig, CONFIG, ["model.image_size=250"])
    with pytest.raises(DegustaError, match="model.vision_channels"):
        load_config(PretrainConfig, CONFIG, ["model.vision_channels=[8,8]"])
    with pytest.raises(DegustaError, match="data.mix"):
        load_config(PretrainConfig, CONFIG, ["data.mix.lists=0", "data.mix.describe=0", "data.mix.gomo=0",
                                             "data.mix.locate=0", "data.mix.transcribe=0"])


def test_images_too_coarse_for_the_grid_are_refused(tmp_path):
    with pytest.raises(DegustaError, match="model.image_size: 128 px gives 4 x 4 image tokens"):
        run_train(CONFIG, _overrides(tmp_path, 1) + ["model.image_size=128"])
    assert not (tmp_path / "runs").exists()  # refused before anything is written


def test_dense_head_trains_the_tokens_the_decoder_sees():
    model, _ = build_base(BaseArchitecture(vision_channels=[8, 8, 16, 16], vision_stem=8, text_hidden=32,
                                           text_layers=1, text_heads=2, text_kv_heads=1, text_intermediate=64,
                                           vocab_size=600))
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    ds = PerceptionExamples(catalog, tables, Grid(8, 8), 256, 0, 8, TaskMix(), block=1)
    labels = DenseLabels(catalog, 8)
    targets, keep = labels([ds[i] for i in range(8)])
    assert keep.numel() == sum(len(ds[i].prompt.images) for i in range(8)) and targets.shape[1:] == (64, labels.n_labels)
    assert targets.sum() > 0
    head = DenseHead(32, labels.n_labels, 8)
    assert projector_of(model) is model.model.multi_modal_projector
    tokens = torch.randn(keep.numel(), 64, 32, requires_grad=True)
    loss = head.loss(tokens, targets, keep)
    loss.backward()
    assert torch.isfinite(loss) and tokens.grad.abs().sum() > 0
    assert head.loss(None, targets, keep).item() == 0.0  # nothing captured: no signal, no crash


def _tiny_base():
    return build_base(BaseArchitecture(vision_channels=[8, 8, 16, 16], vision_stem=8, text_hidden=32, text_layers=1,
                                       text_heads=2, text_kv_heads=1, text_intermediate=64, vocab_size=2048))


def test_oracle_teacher_feeds_the_decoder_perfect_image_tokens_then_lets_go():
    model, processor = _tiny_base()
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    ds = PerceptionExamples(catalog, tables, Grid(8, 8), 256, 0, 8, TaskMix(objects_sheet=1.0), block=1)
    exs = [ds[i] for i in range(4)]
    ids = OracleTokens(catalog, processor.tokenizer, Grid(8, 8))(exs)
    _, keep = DenseLabels(catalog, 8)(exs)
    assert not keep.all() and ids.shape[:2] == (int(keep.sum()), 64)  # object sheets have no oracle
    tok = processor.tokenizer
    first = next(labels for ex in exs for labels in ex.meta["cell_labels"] if labels is not None)
    k, objects = next((k, objects) for k, objects in enumerate(first) if objects)
    oid, direction = objects[0]
    expect = [tok.convert_tokens_to_ids(t) for t in (Grid(8, 8).cells[k], catalog[oid].type, str(oid), direction)]
    assert ids[0, k, :4].tolist() == expect and ids[0, k, 3 * len(objects) + 1:].eq(-1).all()
    teacher = OracleTeacher(model.get_input_embeddings(), steps=10)
    teacher.ids, teacher.keep = ids, keep
    tokens = torch.randn(keep.numel(), 64, 32, requires_grad=True)
    swapped = teacher.replace(tokens, step=0)  # probability 1: every labelled image is its oracle sum
    assert torch.allclose(swapped[keep], teacher.oracle()) and torch.equal(swapped[~keep], tokens[~keep])
    assert teacher.probability(5) == 0.5 and torch.equal(teacher.replace(tokens, step=10), tokens)
    held = OracleTeacher(model.get_input_embeddings(), steps=10, hold=20)  # 1 through step 19, then 10 steps to 0
    assert [held.probability(s) for s in (0, 19, 20, 25, 30, 99)] == [1.0, 1.0, 1.0, 0.5, 0.0, 0.0]


def test_tied_readout_names_a_cells_content_through_the_decoders_output_layer():
    from degusta_learn.pretrain.dense import TiedReadout

    model, processor = build_base(BaseArchitecture(  # independent random embeddings: sums of four in 32 dimensions
        vision_channels=[8, 8, 16, 16], vision_stem=8, text_hidden=32, text_layers=1, text_heads=2, text_kv_heads=1,
        text_intermediate=64, vocab_size=2048, class_init=0.0))
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    ds = PerceptionExamples(catalog, tables, Grid(8, 8), 256, 0, 8, TaskMix(objects_sheet=1.0), block=1)
    exs = [ds[i] for i in range(6)]
    ids = OracleTokens(catalog, processor.tokenizer, Grid(8, 8), "readout_weight")(exs)
    _, keep = DenseLabels(catalog, 8)(exs)
    readout = TiedReadout(model.get_output_embeddings(), OracleTokens(catalog, processor.tokenizer, Grid(8, 8)), catalog)
    teacher = OracleTeacher(model.get_input_embeddings(), steps=1)
    teacher.ids, teacher.keep = ids, keep
    perfect = torch.zeros(keep.numel(), 64, 32)
    perfect[keep] = teacher.oracle().detach()  # the oracle sums: what the decoder learned to copy
    tokens = torch.randn(keep.numel(), 64, 32, requires_grad=True)
    read, chance = readout.readouts(perfect, exs, catalog), readout.readouts(tokens.detach(), exs, catalog)
    assert read["cells"] == chance["cells"] > 20
    assert read["id"] > 0.7 and read["type"] > 0.9 and chance["id"] < 0.2 and chance["type"] < 0.4  # ~25 ids a type
    loss = readout.loss(tokens, ids, keep)
    loss.backward()
    assert tokens.grad[keep].abs().sum() > 0 and tokens.grad[~keep].abs().sum() == 0  # object sheets: no target
    assert model.get_output_embeddings().weight.grad is None  # the decoder owns its output layer
    assert readout.loss(10 * perfect, ids, keep) < loss.item()
    assert readout.loss(None, ids, keep) is None and readout.loss(tokens, None, keep) is None


def test_class_init_gives_rare_answer_tokens_a_shared_direction():
    from degusta_learn.pretrain.base import init_token_classes, token_classes

    def mean_cosine(model, ids):
        rows = torch.nn.functional.normalize(model.get_input_embeddings().weight[ids], dim=1)
        sim = rows @ rows.T
        return float((sim.sum() - sim.diagonal().sum()) / (len(ids) * (len(ids) - 1)))

    model, processor = build_base(BaseArchitecture(vision_channels=[8, 8, 16, 16], vision_stem=8, text_hidden=32,
                                                   text_layers=1, text_heads=2, text_kv_heads=1, text_intermediate=64,
                                                   vocab_size=2048, class_init=0.0))
    types, numbers, cells, directions = token_classes(processor.tokenizer)
    assert len(types) == 5 and len(numbers) == 256 and len(cells) == 144 and len(directions) == 8
    assert abs(mean_cosine(model, numbers)) < 0.1  # plain random init: unrelated
    init_token_classes(model, processor.tokenizer, 1.0)  # what build_base does with model.class_init 1
    assert mean_cosine(model, numbers) > 0.3 and mean_cosine(model, cells) > 0.3
    with pytest.raises(DegustaError, match="model.class_init"):
        BaseArchitecture(class_init=-1)


def test_oracle_teacher_refuses_a_tokenizer_that_splits_cells():
    class Splitting:  # a byte-level tokenizer, as the tiny test models' are
        def encode(self, text, add_special_tokens=False):
            return list(text.encode())

    with pytest.raises(DegustaError, match="data.teacher_steps: the tokenizer splits 'A1' into 2 tokens"):
        OracleTokens(default_catalog(), Splitting(), Grid(8, 8))


def test_a_tokenizer_too_small_for_the_teacher_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(DegustaError, match="data.teacher_steps: the tokenizer splits"):
        run_train(CONFIG, _overrides(tmp_path, 1) + ["model.vocab_size=600", "data.teacher_steps=10"])
    assert not (tmp_path / "runs" / "p" / "init").exists()


def test_teacher_needs_one_token_per_cell():
    with pytest.raises(DegustaError, match="data.teacher_steps: the dense loss, the oracle teacher and the attention"):
        load_config(PretrainConfig, CONFIG, ["data.grid.rows=6", "data.grid.cols=6", "data.dense_weight=0",
                                             "data.tower_steps=0", "data.teacher_steps=10"])
    with pytest.raises(DegustaError, match="data.readout_weight: the dense loss"):
        load_config(PretrainConfig, CONFIG, ["data.grid.rows=6", "data.grid.cols=6", "data.dense_weight=0",
                                             "data.tower_steps=0", "data.teacher_steps=0"])
    with pytest.raises(DegustaError, match="data.retrieval_weight: the dense loss"):
        load_config(PretrainConfig, CONFIG, ["data.grid.rows=6", "data.grid.cols=6", "data.dense_weight=0",
                                             "data.tower_steps=0", "data.teacher_steps=0", "data.readout_weight=0"])


@pytest.mark.slow
def test_pretrain_exports_a_plain_hf_folder_and_resumes(tmp_path, monkeypatch):
    from transformers import AutoModelForImageTextToText, AutoProcessor

    from degusta_learn.training import effective_precision
    from degusta_learn.vlm.load import load_vlm

    seen: list[int] = []  # the training examples drawn, in order (validation uses another seed)
    draw = PerceptionExamples.__getitem__
    monkeypatch.setattr(PerceptionExamples, "__getitem__",
                        lambda self, i: (seen.append(i) if self.seed == 0 else None, draw(self, i))[1])
    best_of_validations = ["trainer.monitor=val/perception", "trainer.monitor_mode=max"]
    out = run_train(CONFIG, _overrides(tmp_path, 2) + best_of_validations)
    assert out == tmp_path / "base"
    for name in ("config.json", "model.safetensors", "tokenizer.json", "processor_config.json", "README.md",
                 "degusta_base.json", "pretrain_config.yaml"):
        assert (out / name).is_file(), name
    meta = json.loads((out / "degusta_base.json").read_text())
    assert meta["training"]["steps"] == 2 and meta["tokens_per_image"] == 64 and meta["validation_curve"]
    assert "val/perception" in meta["validation_curve"][-1]
    logged = next((tmp_path / "runs" / "p" / "csv").rglob("metrics.csv")).read_text().splitlines()[0].split(",")
    assert {"train/retrieval", "train/dense", "train/readout", "train/teacher_p"} <= set(logged)  # every aid ran
    card = (out / "README.md").read_text()
    assert "never shown anyone's table setting" in card and "AutoModelForImageTextToText" in card
    # the card's command rebuilds THIS model: the shipped recipe plus this run's overrides, not the plain command
    assert "--set trainer.monitor=val/perception" in meta["training"]["command"] in card
    assert "--set model.text_hidden=32" in meta["training"]["command"]
    # where it was written and under which run name is not what it builds: neither is in the command
    assert "export" not in meta["training"]["command"] and "run_name" not in meta["training"]["command"]
    # the arithmetic this machine ran the config's precision in (bf16-mixed: 32-true without native bfloat16), and
    # the kernels of this process (already chosen by earlier tests: the CLI test below shows the recipe's own)
    ran = effective_precision(load_config(PretrainConfig, CONFIG).trainer)
    kernels = torch.backends.cpu.get_cpu_capability()
    assert meta["training"]["precision"] == ran and meta["training"]["device"] == "cpu"
    assert meta["training"]["cpu_kernels"] == kernels and f"on a CPU in {ran} with {kernels} kernels." in card
    # loadable by the plain transformers Auto classes and by the toolkit's loader, without the dense head
    model = AutoModelForImageTextToText.from_pretrained(out)
    assert type(model).__name__ == "FastVlmForConditionalGeneration"
    assert type(AutoProcessor.from_pretrained(out)).__name__ == "LlavaProcessor"
    model2, _ = load_vlm(str(out), device="cpu", dtype="float32")
    assert not any("dense" in k for k in model2.state_dict())
    # resume: the same command with more steps continues the run (same initial weights and tokenizer)
    ckpt = tmp_path / "runs" / "p" / "last.ckpt"
    assert torch.load(ckpt, weights_only=True, map_location="cpu")["global_step"] == 2
    run_train(CONFIG, _overrides(tmp_path, 6) + best_of_validations)
    assert torch.load(ckpt, weights_only=True, map_location="cpu")["global_step"] == 6
    training = json.loads((out / "degusta_base.json").read_text())["training"]
    best = torch.load(tmp_path / "runs" / "p" / "best.ckpt", weights_only=True, map_location="cpu")["global_step"]
    assert training["run_steps"] == 6 and training["steps"] == best  # the exported weights are the best's
    # the resumed run drew exactly the examples an uninterrupted one would: steps 2-5, none skipped or repeated
    assert seen == list(range(6 * 2)), seen


def test_the_recipe_command_rebuilds_the_config_it_describes():
    """`recipe_command`: the shipped config gives the plain command; overrides come back as --set values that the
    shell hands the loader intact and that load to the same config (lists, spaces, quotes, brackets, a YAML word
    such as 'on' that must stay a string), the run's logistics (where it logs) left out."""
    import shlex

    from degusta_learn.config import to_dict
    from degusta_learn.pretrain.export import COMMAND, ran_as, recipe_command

    shipped = load_config(PretrainConfig, CONFIG)
    assert shipped.trainer.cpu_kernels == "avx2"  # the kernels its passing builds computed with (point 46)
    same = {"precision": shipped.trainer.precision, "cpu_kernels": "AVX2"}
    assert recipe_command(shipped) == COMMAND == recipe_command(shipped, ran=ran_as(same)) == recipe_command(
        shipped, ran=ran_as({}))  # a record without the facts says nothing about them
    other = "bf16-mixed" if shipped.trainer.precision == "32-true" else "32-true"
    # the arithmetic the run trained in, not the config's word for it (bf16-mixed ran as fp32 on an AVX2 CPU; the
    # kernels the process got, AVX-512 where avx2 came too late or off x86 where it means nothing)
    assert recipe_command(shipped, ran=ran_as({"precision": other})) == f"{COMMAND} --set trainer.precision={other}"
    for kernels in ("AVX512", "DEFAULT"):
        assert (recipe_command(shipped, ran=ran_as(same | {"cpu_kernels": kernels}))
                == f"{COMMAND} --set trainer.cpu_kernels=native")
    overrides = ["data.mix.transcribe=0.0", "model.vision_channels=[16,32,64,128]", "dataset=my data",
                 "trainer.max_steps=100", "trainer.run_name=elsewhere", "export=runs/it's (v2) & $HOME"]
    for last in ([], ["dataset='on'"]):  # a value YAML 1.1 would read as a boolean stays the text it is
        cfg = load_config(PretrainConfig, CONFIG, overrides + last)
        words = shlex.split(recipe_command(cfg))
        sets = [words[i + 1] for i, w in enumerate(words) if w == "--set"]
        assert len(sets) == 4 and not any(s.startswith(("trainer.run_name", "export")) for s in sets)
        rebuilt = to_dict(load_config(PretrainConfig, CONFIG, sets))
        logistics = {"trainer": rebuilt["trainer"], "export": rebuilt["export"]}
        assert rebuilt == to_dict(cfg) | logistics and rebuilt["dataset"] == cfg.dataset
        assert rebuilt["export"] != cfg.export and rebuilt["trainer"]["run_name"] != "elsewhere"
        assert rebuilt["trainer"]["max_steps"] == 100


def test_mimetic_attention_and_tied_embeddings():
    arch = dict(vision_channels=[8, 8, 16, 16], vision_stem=8, text_hidden=32, text_layers=1, text_heads=2,
                text_kv_heads=1, text_intermediate=64, vocab_size=600, previous_token_head=False)
    model, _ = build_base(BaseArchitecture(**arch))
    assert model.lm_head.weight is model.get_input_embeddings().weight
    attn = model.model.language_model.layers[0].self_attn
    q, k = attn.q_proj.weight[:16], attn.k_proj.weight  # head 0 of the one key/value group
    assert torch.nn.functional.cosine_similarity(q.flatten(), k.flatten(), dim=0) > 0.9
    ov = attn.o_proj.weight[:, :16] @ attn.v_proj.weight  # (hidden, hidden): copies what head 0 attends to
    assert ov.diagonal().mean() > 5 * ov.fill_diagonal_(0).abs().mean()
    with pytest.raises(DegustaError, match="model.attention_init"):
        BaseArchitecture(attention_init="xavier")


@pytest.mark.parametrize("hidden, heads, kv", [(32, 2, 1), (256, 4, 2)])
def test_previous_token_head_attends_one_position_back_whatever_the_tokens(hidden, heads, kv):
    arch = BaseArchitecture(vision_channels=[8, 8, 16, 16], vision_stem=8, text_hidden=hidden, text_layers=1,
                            text_heads=heads, text_kv_heads=kv, text_intermediate=64, vocab_size=600)
    assert arch.previous_token_head  # on by default
    model, _ = build_base(arch)
    decoder = model.model.language_model
    decoder.config._attn_implementation = "eager"  # attention weights out
    ids = torch.randint(10, 500, (1, 1500), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        weights = decoder(input_ids=ids, output_attentions=True).attentions[0][0]  # (heads, T, T)
    assert torch.diagonal(weights[0], offset=-1).min() > 0.99  # head 0: every position reads its predecessor
    for other in range(1, heads):  # the others stay content heads (mimetic), not positional
        assert torch.diagonal(weights[other], offset=-1).mean() < 0.2
    plain, _ = build_base(BaseArchitecture(**{**arch.__dict__, "previous_token_head": False}))
    with torch.no_grad():
        plain.model.language_model.config._attn_implementation = "eager"
        before = plain.model.language_model(input_ids=ids, output_attentions=True).attentions[0][0]
    assert torch.diagonal(before[0], offset=-1).mean() < 0.2
    with pytest.raises(DegustaError, match="model.previous_token_head"):
        BaseArchitecture(previous_token_head="yes")


def test_vision_stage_trains_only_the_tower_then_the_decoder_starts_its_own_schedule(tmp_path):
    from safetensors.torch import load_file

    steps = ["data.tower_steps=2", "data.teacher_hold=1", "data.teacher_steps=2", "data.curriculum_steps=2",
             "data.steps_per_epoch=1", "data.readout_weight=1"]  # validations at steps 1 (in the vision stage), 2, ...
    run_train(CONFIG, _overrides(tmp_path, 2) + steps)
    run = tmp_path / "runs" / "p"
    init = load_file(run / "init" / "model.safetensors")
    state = torch.load(run / "last.ckpt", weights_only=True, map_location="cpu")
    after = {k[6:]: v for k, v in state["state_dict"].items() if k.startswith("model.")}
    changed = {k for k, v in init.items() if not torch.equal(v, after[k])}
    assert changed and all(("vision_tower" in k or "multi_modal_projector" in k) for k in changed), changed
    assert any("vision_tower" in k for k in changed)
    groups = state["optimizer_states"][0]["param_groups"]
    assert [g["name"] for g in groups] == ["vision", "decoder"]  # the decoder's schedule starts after the stage
    rows = (run / "csv").rglob("metrics.csv")
    import csv

    table = list(csv.DictReader(next(rows).open()))
    val = [r for r in table if r.get("val/tower_type")]
    assert val and val[0]["val/perception"] == "nan" and float(val[0]["val/tower_id"]) >= 0  # read, not answered
    assert not any(r.get("train/loss") or r.get("train/readout") for r in table)  # the decoder never ran
    assert float(val[0]["val/token_id"]) >= 0  # what the decoder's output layer reads from the tokens
    # the same command with more steps resumes into the decoder stage: every part trains, answers are scored
    run_train(CONFIG, _overrides(tmp_path, 4) + steps)
    state = torch.load(run / "last.ckpt", weights_only=True, map_location="cpu")
    after = {k[6:]: v for k, v in state["state_dict"].items() if k.startswith("model.")}
    assert not torch.equal(init["model.language_model.layers.0.mlp.up_proj.weight"],
                           after["model.language_model.layers.0.mlp.up_proj.weight"])
    table = [r for path in (run / "csv").rglob("metrics.csv") for r in csv.DictReader(path.open())]
    assert any(r.get("train/loss") for r in table) and any(r.get("train/teacher_p") == "1.0" for r in table)
    assert any(r.get("train/readout") for r in table)  # the tied readout trains the projector after the stage
    assert any(r.get("val/perception") not in (None, "", "nan") for r in table)
    # the shipped config monitors nothing: the last weights are exported, and the card says how they were trained
    training = json.loads((tmp_path / "base" / "degusta_base.json").read_text())["training"]
    assert training["steps"] == training["run_steps"] == 4 and not (run / "best.ckpt").exists()
    card = (tmp_path / "base" / "README.md").read_text()
    assert "vision stage of 2 steps" in card and "trained to name their cell's content (weight 1.0)" in card
    assert "first 2 decoder steps asked one-scene questions only (0.5 describe, 0.35 locate, 0.15 lists)" in card
    # and without a resume between them: the stages meet inside one epoch of one process
    run_train(CONFIG, _overrides(tmp_path, 2) + ["data.tower_steps=1", "trainer.run_name=q"])
    table = list(csv.DictReader(next((tmp_path / "runs" / "q" / "csv").rglob("metrics.csv")).open()))
    assert [r["step"] for r in table if r.get("train/dense")] == ["0", "1"] and table[-1]["val/perception"]


def test_while_the_teacher_holds_the_readout_trains_the_projectors_own_tokens(monkeypatch):
    from degusta_learn.pretrain.module import PerceptionModule

    model, processor = _tiny_base()
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    cfg = load_config(PretrainConfig, CONFIG, TINY + ["data.tower_steps=3", "data.readout_weight=1"])
    module = PerceptionModule(model, processor, cfg, catalog, Grid(8, 8), DenseLabels(catalog, 8).n_labels)
    monkeypatch.setattr(PerceptionModule, "vision_stage", property(lambda self: False))  # the decoder's first step
    assert module.teacher.probability(module.global_step) == 1.0  # the decoder sees only oracle sums
    exs = [PerceptionExamples(catalog, tables, Grid(8, 8), 256, 0, 2, TaskMix(), block=1)[i] for i in range(2)]
    ids, keep = OracleTokens(catalog, processor.tokenizer, Grid(8, 8))(exs), DenseLabels(catalog, 8)(exs)[1]
    module.teacher.ids, module.teacher.keep = ids, keep
    pixels = processor.image_processor(images=[getattr(im, "image", im) for ex in exs for im in ex.prompt.images],
                                       return_tensors="pt")["pixel_values"]
    model.model.get_image_features(pixel_values=pixels)  # the hook swaps the oracle sums in for the decoder
    tokens = module._readout_tokens()
    assert not torch.allclose(tokens[keep], module.teacher.oracle())  # the projector's tokens, not the swap
    module.readout.loss(tokens, ids, keep).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in projector_of(model).parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.model.vision_tower.parameters())


def test_a_frozen_tower_keeps_what_the_vision_stage_taught_it(tmp_path):
    steps = ["data.tower_steps=1", "data.freeze_tower=true", "data.steps_per_epoch=1", "data.curriculum_steps=1",
             "data.teacher_steps=2"]  # the readout on, as shipped: it trains the projector, never the tower
    run = tmp_path / "runs" / "p"

    def weights():
        state = torch.load(run / "last.ckpt", weights_only=True, map_location="cpu")["state_dict"]
        return {k: v.clone() for k, v in state.items()}

    run_train(CONFIG, _overrides(tmp_path, 1) + steps)  # the vision stage alone: the tower trains
    staged = weights()
    run_train(CONFIG, _overrides(tmp_path, 3) + steps)  # resumed: two decoder steps with a validation between
    after = weights()
    tower = [k for k in staged if ".vision_tower." in k]
    assert any("running_mean" in k for k in tower)  # BatchNorm statistics are compared too
    assert all(torch.equal(staged[k], after[k]) for k in tower)
    changed = {k for k in staged if not torch.equal(staged[k], after[k])}
    assert any("multi_modal_projector" in k for k in changed) and any("language_model" in k for k in changed)
    import csv

    table = [r for path in (run / "csv").rglob("metrics.csv") for r in csv.DictReader(path.open())]
    assert any(r.get("train/teacher_p") for r in table)  # the teacher still shows the decoder its tokens


@pytest.mark.parametrize("extra, key", [(["data.readout_weight=-1"], "data.readout_weight: expected >= 0"),
                                        (["data.freeze_projector=false"], "data.freeze_projector: removed"),
                                        (["data.teacher_weight=0"], "data.teacher_weight: removed"),
                                        (["data.retrieval_list_items=false"], "data.retrieval_list_items: removed")])
def test_settings_that_cannot_work_or_were_removed_are_refused(tmp_path, extra, key):
    with pytest.raises(DegustaError, match=key):
        run_train(CONFIG, _overrides(tmp_path, 2) + ["data.tower_steps=1"] + extra)
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("extra, key", [(["data.tower_steps=2", "data.dense_weight=0"], "data.tower_steps"),
                                        (["data.tower_steps=2", "trainer.early_stopping_patience=2"],
                                         "trainer.early_stopping_patience")])
def test_a_vision_stage_that_cannot_work_is_refused_before_anything_is_written(tmp_path, extra, key):
    with pytest.raises(DegustaError, match=key):
        run_train(CONFIG, _overrides(tmp_path, 4) + extra)
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("tower_steps", [0, 3])
def test_after_a_vision_stage_the_readout_trains_the_projector_not_the_tower(tower_steps):
    from degusta_learn.pretrain.module import PerceptionModule

    model, processor = _tiny_base()
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    cfg = load_config(PretrainConfig, CONFIG, TINY + [f"data.tower_steps={tower_steps}"])
    module = PerceptionModule(model, processor, cfg, catalog, Grid(8, 8), DenseLabels(catalog, 8).n_labels)
    exs = [PerceptionExamples(catalog, tables, Grid(8, 8), 256, 0, 2, TaskMix(), block=1)[i] for i in range(2)]
    ids, keep = OracleTokens(catalog, processor.tokenizer, Grid(8, 8))(exs), DenseLabels(catalog, 8)(exs)[1]
    module.teacher.ids, module.teacher.keep = ids, keep
    pixels = processor.image_processor(images=[getattr(im, "image", im) for ex in exs for im in ex.prompt.images],
                                       return_tensors="pt")["pixel_values"]
    model.model.get_image_features(pixel_values=pixels)
    module.readout.loss(module._readout_tokens(), ids, keep).backward()
    tower = [p.grad for p in model.model.vision_tower.parameters()]
    assert all(g is not None and g.abs().sum() > 0 for g in (p.grad for p in projector_of(model).parameters()))
    assert all(g is None or g.abs().sum() == 0 for g in tower) == (tower_steps > 0)


def test_channels_last_is_the_same_tower_in_a_faster_layout_and_exports_the_usual_one():
    from degusta_learn.pretrain.train import prepare_model

    # 16 channels at least: narrower strided 1x1 convolutions stay in the usual layout (next test)
    cfg = load_config(PretrainConfig, CONFIG, TINY + ["model.vision_channels=[16,16,32,32]"])
    assert cfg.channels_last  # the shipped recipe trains in it
    model, _ = build_base(cfg.model, seed=0)
    convs = [p for p in model.model.vision_tower.parameters() if p.dim() == 4]
    image = torch.rand(2, 3, cfg.model.image_size, cfg.model.image_size)
    with torch.no_grad():
        before = model.model.get_image_features(pixel_values=image)
        prepare_model(model, cfg)
        assert all(p.is_contiguous(memory_format=torch.channels_last) for p in convs)
        assert any(not p.is_contiguous() for p in convs)  # (1 x 1 kernels are both)
        after = model.model.get_image_features(pixel_values=image)
    torch.testing.assert_close(after, before, atol=1e-4, rtol=1e-3)  # the same up to rounding
    prepare_model(model, cfg, export=True)
    assert all(p.is_contiguous() for p in convs)
    plain = load_config(PretrainConfig, CONFIG, TINY + ["channels_last=false"])
    prepare_model(model, plain)  # off: the layout is left alone
    assert all(p.is_contiguous() for p in convs)


def test_a_tower_whose_strided_1x1_convolution_oneDNN_mishandles_keeps_the_usual_layout(capsys):
    """oneDNN (torch 2.14.1, AVX-512) aborts the backward pass of a strided 1x1 convolution over 8 channels in
    channels-last: such a tower trains in the usual layout, with a note; the recipe's tower is not one."""
    from degusta_learn.pretrain.base import BaseArchitecture
    from degusta_learn.pretrain.train import channels_last_is_safe, prepare_model

    cfg = load_config(PretrainConfig, CONFIG, TINY)  # vision_channels [8, 8, 16, 16]
    model, _ = build_base(cfg.model, seed=0)
    assert not channels_last_is_safe(model.model.vision_tower)
    prepare_model(model, cfg)
    assert all(p.is_contiguous() for p in model.model.vision_tower.parameters())
    assert "channels_last: the tower keeps the usual layout" in capsys.readouterr().err
    model.model.vision_tower(pixel_values=torch.rand(1, 3, 256, 256)).last_hidden_state.sum().backward()  # no abort
    recipe, _ = build_base(BaseArchitecture(), seed=0)
    assert channels_last_is_safe(recipe.model.vision_tower)


@pytest.mark.skipif(not x86_with_avx2(),
                    reason="the recipe's cpu_kernels: avx2 caps x86 kernels; this CPU has none to cap")
def test_degusta_train_runs_the_recipe_on_avx2_kernels_and_the_export_says_so(tmp_path):
    """The kernels are chosen at torch's first CPU operation: `degusta train` must ask for the recipe's before any,
    on every CPU (the AVX-512 builds of the recipe failed the route's bars, experiments/tiny_base_log.md point 46)."""
    import os
    import subprocess
    import sys

    from degusta_learn.training import AVX2_KERNELS

    env = {k: v for k, v in os.environ.items() if k not in AVX2_KERNELS}
    done = subprocess.run([sys.executable, "-m", "degusta_learn.cli", "train", "--config", str(CONFIG),
                           *(x for o in _overrides(tmp_path, 1) for x in ("--set", o))],
                          capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    training = json.loads((tmp_path / "base" / "degusta_base.json").read_text())["training"]
    assert training["cpu_kernels"] == "AVX2" and "cpu_kernels" not in training["command"]
    assert "trainer.cpu_kernels" not in done.stderr  # no note: nothing ran before it asked


@pytest.mark.parametrize("record, words", [
    ({}, "on a CPU"),  # a record from before the device and precision were written down
    ({"device": "cpu", "precision": "32-true"}, "on a CPU in 32-true"),
    ({"device": "cpu", "precision": "32-true", "cpu_kernels": "AVX2"}, "on a CPU in 32-true with AVX2 kernels"),
    ({"device": "gpu", "precision": "bf16-mixed"}, "on a GPU in bf16-mixed"),
])
def test_the_card_says_where_and_in_which_precision_the_base_trained(record, words):
    from degusta_learn.pretrain.export import _device, _where
    from degusta_learn.training import TrainerConfig

    assert _where(record) == words
    assert _device(TrainerConfig(accelerator="gpu")) == "gpu" and _device(TrainerConfig(accelerator="cpu")) == "cpu"
