"""Write a pretrained base as a plain Hugging Face model folder with its facts and a model card.

The folder holds what `save_pretrained` writes for the model (config.json, model.safetensors,
generation_config.json) and the processor (tokenizer, image processor, chat template), plus
`degusta_base.json` (architecture, image budget, training facts, the validation curve), the resolved
training config (`pretrain_config.yaml`) and `README.md`, the model card. `bench_perception.py`
adds `perception.json` (its held-out scores) and `bench_base_route.py --record` adds `selection.json` (how the
build was chosen, its fine-tuned route on the validation participants and the one test look); `write_card`
re-renders the card from them.

The folder is staged beside its destination and swapped in whole (`files.folders.write_folder`): a reader never sees
half of it, and a file of the user's in it is kept.

Example:
    export_base(model, processor, cfg, Path("runs/tiny_vlm_base"), run_dir, history)
    write_card(Path("runs/tiny_vlm_base"))          # after perception.json changed
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

from degusta_learn.files.atomic import atomic_write_text
from degusta_learn.files.jsonio import read_json
from degusta_learn.training import validation_curve
from degusta_learn.vlm.record import BASE_FILE as BASE_META  # the record's file name, defined once

PERCEPTION = "perception.json"
SELECTION = "selection.json"  # how the build was chosen and its route's rows (benchmarks/bench_base_route.py)
PRETRAIN_CONFIG = "pretrain_config.yaml"  # the run's resolved config, in the folder
RECIPE = "pretrain_tiny_vlm_cpu.yaml"  # the shipped pretraining config
COMMAND = f"degusta train --config configs/{RECIPE}"
_LOGISTICS = {"export", "trainer.run_name", "trainer.run_dir", "trainer.resume", "trainer.progress_bar",
              "trainer.loggers", "trainer.log_every_n_steps", "trainer.tracking_offline"}
"""Keys that say where a run writes and logs and how it shows progress, not what it builds: left out of the recipe
command."""


def ran_as(training: dict) -> dict:
    """The config values that a base's training record says its run computed with, for `recipe_command(ran=...)`:
    `trainer.precision` from the arithmetic it ran (bf16-mixed is 32-true on a CPU without native bfloat16), and on
    a CPU `trainer.cpu_kernels` from the kernels torch ran ("AVX2" is what `avx2` asks for, anything else `native`).
    Records that lack a key say nothing about it."""
    ran = {"trainer.precision": training["precision"]} if training.get("precision") else {}
    if training.get("cpu_kernels"):
        ran["trainer.cpu_kernels"] = "avx2" if training["cpu_kernels"] == "AVX2" else "native"
    return ran


def recipe_command(cfg, ran: dict | None = None) -> str:
    """The command that rebuilds the base `cfg` describes: COMMAND plus a `--set` for every key whose value differs
    from the shipped config's (a base built with overrides must not claim the plain command, which builds another
    model). Each `--set` is shell-quoted as a whole and its value written as YAML, so the shell hands the loader
    the value's YAML (a string such as 'on' stays a string). Where the shipped config cannot be read, the command
    runs the folder's own resolved config (`pretrain_config.yaml`), which rebuilds it too.

    `ran`: what the run actually computed with (`ran_as`), compared in place of the config's values: `bf16-mixed` is
    fp32 on a CPU without native bfloat16 and bf16 on one with it, `cpu_kernels: native` is AVX2 on one CPU and
    AVX-512 on another, and each pair builds different bases, so the command names
    the arithmetic that built this one."""
    import shlex

    from degusta_learn.config import dump_yaml, load_config, to_dict
    from degusta_learn.errors import DegustaError
    from degusta_learn.shipped import SHIPPED_DIR

    def flat(d: dict, prefix: str = ""):
        for k, v in d.items():
            yield from flat(v, f"{prefix}{k}.") if isinstance(v, dict) else [(f"{prefix}{k}", v)]

    try:
        shipped = dict(flat(to_dict(load_config(type(cfg), SHIPPED_DIR / RECIPE))))
    except (DegustaError, OSError):  # the folder's resolved config is the recipe then
        return f"degusta train --config {PRETRAIN_CONFIG} (the resolved config in this folder)"
    values = dict(flat(to_dict(cfg))) | (ran or {})
    sets = [f"{k}={dump_yaml(v, default_flow_style=True, width=10**6).strip().removesuffix('...').strip()}"
            for k, v in values.items() if k not in _LOGISTICS and shipped.get(k, object()) != v]
    return " ".join([COMMAND, *(f"--set {shlex.quote(s)}" for s in sets)])


def export_base(model, processor, cfg, out: Path, run_dir: Path, steps: int | None = None,
                run_steps: int | None = None, replace_shipped: bool = False) -> Path:
    """Save `model` + `processor` to `out` with degusta_base.json, pretrain_config.yaml and README.md.

    `steps`: the training step of these weights (the best validation's); `run_steps`: how long the run went;
    `replace_shipped`: `out` is the shipped base, asked for by name (`export: tiny_vlm_base`)."""
    from degusta_learn.config import dump_yaml, to_dict
    from degusta_learn.files.folders import write_folder
    from degusta_learn.finetune.export import MODEL_FOLDER
    from degusta_learn.render.grid import Grid
    from degusta_learn.training import effective_precision
    from degusta_learn.vlm.prompt_options import PromptOptions
    from degusta_learn.vlm.record import BaseRecord, write_record

    out = Path(out)
    device = _device(cfg.trainer)
    arithmetic = {"precision": effective_precision(cfg.trainer), "device": device}
    if device == "cpu":  # the kernels this process computed with (chosen once per process: the last stretch's)
        import torch

        arithmetic["cpu_kernels"] = torch.backends.cpu.get_cpu_capability()
    curve = validation_curve(run_dir, "val/perception")
    arch = cfg.model
    n_params = sum(p.numel() for p in model.parameters())
    with write_folder(out, MODEL_FOLDER, allow_shipped=replace_shipped) as tmp:  # no perception.json: a benchmark of earlier weights is stale
        model.save_pretrained(str(tmp))
        processor.save_pretrained(str(tmp))
        write_record(tmp, BaseRecord(
            architecture=dataclasses.asdict(arch), parameters=n_params, image_size=arch.image_size,
            render_size=arch.image_size, tokens_per_image=arch.tokens_per_image,
            grid=Grid(cfg.data.grid.rows, cfg.data.grid.cols),
            # the prompt layout it saw in pretraining (object sheets composed into one image); the hf backend
            # prompts the base this way zero-shot, as it prompts a fine-tuned model the way it was trained
            prompt=PromptOptions(include=["objects", "context", "target"], compose=["objects"]),
            catalog=cfg.dataset or "embedded default (125 objects, 5 tables)",
            training={"command": recipe_command(cfg, ran=ran_as(arithmetic)), "steps": steps,
                      # the arithmetic this machine ran the config in (bf16-mixed is 32-true on a CPU without native
                      # bfloat16; the kernels AVX2 or AVX-512): builds of one recipe in each differ
                      **arithmetic,
                      "run_steps": run_steps if run_steps is not None else steps,
                      "batch_size": cfg.data.batch_size, "examples": steps * cfg.data.batch_size if steps else None,
                      "lr": cfg.optim.lr, "seed": cfg.seed, "mix": dataclasses.asdict(cfg.data.mix),
                      "tower_steps": cfg.data.tower_steps, "freeze_tower": cfg.data.freeze_tower,
                      "dense_weight": cfg.data.dense_weight, "readout_weight": cfg.data.readout_weight,
                      "retrieval_weight": cfg.data.retrieval_weight, "teacher_steps": cfg.data.teacher_steps,
                      "teacher_hold": cfg.data.teacher_hold, "curriculum_steps": cfg.data.curriculum_steps,
                      "curriculum_mix": dataclasses.asdict(cfg.data.curriculum_mix)},
            validation_curve=curve))
        if (run_dir / "config.yaml").is_file():
            shutil.copyfile(run_dir / "config.yaml", tmp / PRETRAIN_CONFIG)
        else:
            atomic_write_text(tmp / PRETRAIN_CONFIG, dump_yaml(to_dict(cfg)))
        write_card(tmp, name=out.name, path=out)
    return out


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.3f}" if isinstance(v, float) else str(v)


def _device(trainer) -> str:
    """"gpu", "cpu", "mps" or "tpu": where a run of `trainer` (a TrainerConfig) trains on this machine."""
    from degusta_learn.training import trains_on_gpu

    if trains_on_gpu(trainer):
        return "gpu"
    return trainer.accelerator if trainer.accelerator in ("mps", "tpu") else "cpu"


def _where(t: dict) -> str:
    """Where and in which arithmetic it trained, in the card's words (older records lack these: a CPU then)."""
    device = t.get("device", "cpu")
    where = {"gpu": "on a GPU", "cpu": "on a CPU"}.get(device, f"on {device.upper()}")
    where = f"{where} in {t['precision']}" if t.get("precision") else where
    return f"{where} with {t['cpu_kernels']} kernels" if t.get("cpu_kernels") else where


def _stages(t: dict) -> str:
    """Which weights trained when (the model card's words for data.tower_steps / data.freeze_tower)."""
    if not t.get("tower_steps"):
        return "all weights trained together"
    after = "the tower frozen, the projector and the decoder trained" if t.get("freeze_tower") else "all weights"
    return (f"first a vision stage of {t['tower_steps']} steps (the vision tower and projector alone, on a dense "
            f"per-token loss: what covers each grid cell, its id and direction), then {after}{_aids(t)}")


def _aids(t: dict) -> str:
    """The decoder stage's auxiliary losses and teacher, in the card's words (older records lack the keys)."""
    aids = []
    if t.get("teacher_steps"):
        aids.append(f"for the first {t.get('teacher_hold', 0) + t['teacher_steps']} steps after it the decoder saw "
                    "perfect image tokens (sums of the embeddings of each cell's content) with a probability "
                    "falling from 1 to 0")
    if t.get("readout_weight"):
        aids.append("the projector's tokens, read through the decoder's output layer, trained to name their cell's "
                    f"content (weight {t['readout_weight']})")
    if t.get("retrieval_weight"):
        aids.append("one decoder head told which image token holds the object an answer names "
                    f"(weight {t['retrieval_weight']})")
    return "".join(f"; {a}" for a in aids)


def _curriculum(t: dict) -> str:
    """The decoder stage's first questions, in the card's words (older records lack the keys)."""
    if not t.get("curriculum_steps"):
        return ""
    mix = t["curriculum_mix"]
    asked = ", ".join(f"{mix[k]:g} {k}" for k in ("describe", "locate", "lists", "transcribe", "gomo") if mix.get(k))
    return f"; its first {t['curriculum_steps']} decoder steps asked one-scene questions only ({asked})"


def _route_table(section: dict) -> list[str]:
    """A selection.json section (bench_base_route.py) as a markdown table and its paired differences."""
    lines = [f"{section['episodes']} episodes of {section['participants']} participants, context "
             f"{section.get('context', '?')}, split seed {section.get('split_seed', '?')}, measured "
             f"{section.get('date', '?')}; a row's per-episode score is the mean over its training seeds, 95% "
             "intervals resample participants:", "",
             "| row | seeds | set RMSD | object accuracy (paper) | Kabsch RMSD (paper) | count error |",
             "|---|---:|---:|---:|---:|---:|"]
    for r in section["rows"]:
        lines.append(f"| {r['name']} | {r['files']} | " + " | ".join(
            f"{_fmt(r[k][0])} [{_fmt(r[k][1])}, {_fmt(r[k][2])}]" for k in ("set_rmsd", "object_accuracy"))
            + f" | {_fmt(r['rmsd'][0])} | {_fmt(r['count_error'][0])} |")
    lines.append("")
    for p in section.get("pairs", []):
        diffs = [f"{k.replace('_', ' ')} {d['diff']:+.4f} [{d['lo']:+.4f}, {d['hi']:+.4f}], "
                 + ("p < 0.001" if d["p_value"] < 0.001 else f"p {d['p_value']:.3f}")
                 for k, d in ((k, p[k]) for k in ("set_rmsd", "object_accuracy")) if d["p_value"] is not None]
        lines += [f"- {p['a']} minus {p['b']}: " + "; ".join(diffs)]
    return lines + ([""] if section.get("pairs") else [])


def _selection_lines(sel: dict | None) -> list[str]:
    """The card's "How this build was chosen" section from selection.json (nothing when the folder has none)."""
    if not sel:
        return []
    lines = ["## How this build was chosen", "", sel.get("protocol", "(no protocol recorded)"), ""]
    for key, title in (("validation", "Its route on the validation participants"),
                       ("test", "The test split, looked at once after every choice")):
        if key in sel:
            lines += [f"### {title}", "", *_route_table(sel[key])]
    for old in sel.get("withdrawn_test_looks", []):
        lines += [f"An earlier test look ({old.get('date', '?')}) was withdrawn: {old.get('withdrawn_because')}.", ""]
    return lines


def _load_lines(name: str, path: Path) -> list[str]:
    """The card's loading snippet: the shipped base by its name (degusta) and by its folder inside the installed
    package (transformers); another base by the folder it was exported to."""
    from degusta_learn.shipped import BASE_DIR, BASE_NAME

    shipped = path.resolve() == BASE_DIR
    where = "BASE_DIR" if shipped else f'"{path.as_posix()}"'
    return ["```python", *(["from degusta_learn.shipped import BASE_DIR  # this folder, inside the installed package"]
                           if shipped else []),
            "from transformers import AutoModelForImageTextToText, AutoProcessor",
            f"model = AutoModelForImageTextToText.from_pretrained({where})",
            f"processor = AutoProcessor.from_pretrained({where})", "```", "",
            f"In a degusta_learn config: `model: {{name: {BASE_NAME if shipped else path.as_posix()}}}` (fine-tuning, "
            f"and prompting with `backend: {{name: hf}}`); in Python, "
            f"`degusta_learn.vlm.load.load_vlm({BASE_NAME if shipped else path.as_posix()!r})`."
            + (" Publish it with `hf upload YOUR_NAME/" + name + f" {path.as_posix()}`." if not shipped else "")]


def write_card(folder: Path, name: str | None = None, path: Path | None = None) -> Path:
    """(Re)write `folder/README.md` from degusta_base.json and, if present, perception.json.

    `name` / `path`: the model's name and the folder users load (default: `folder`'s).
    """
    folder = Path(folder)
    name, path = name or folder.name, Path(path or folder)
    meta = read_json(folder / BASE_META)
    bench = read_json(folder / PERCEPTION) if (folder / PERCEPTION).is_file() else None
    selection = read_json(folder / SELECTION) if (folder / SELECTION).is_file() else None
    a, t = meta["architecture"], meta["training"]
    curve = meta.get("validation_curve") or []
    last = curve[-1] if curve else {}
    lines = [
        "---", "license: mit", "library_name: transformers", "pipeline_tag: image-text-to-text",
        "tags: [degusta_learn, fast_vlm, synthetic-data, tiny]", "---", "",
        f"# {name}: a {meta['parameters'] / 1e6:.1f} M-parameter FastVLM that can see lifted table images", "",
        "A miniature of a pretrained vision-language model, made by degusta_learn for CPU-sized experiments "
        "with its DegustaBot prompts and LoRA fine-tuning. It has the architecture of FastVLM (Apple, CVPR 2025; "
        "`FastVlmForConditionalGeneration` in transformers: a convolutional vision tower from timm, a 2-layer "
        "projector, a Qwen2 decoder), scaled down, and was trained **from random weights** on perception "
        "questions about randomly generated, style-free table scenes: which objects a grid-marked image shows "
        "(type and catalog id), which grid cells each covers, which way it points, and which id is marked on "
        "an object of a marked-object sheet. (Why not SmolVLM's ViT: from random weights on a CPU a ViT tower "
        "barely learns to see small objects; see docs/finetune.md.)", "",
        "It was **never shown anyone's table setting and never the DegustaBot preference question** "
        "(\"my preferences ... set the table\"), so prompting it with that question is zero-shot, and "
        "fine-tuning it on people's arrangements is the miniature of fine-tuning SmolVLM.", "",
        "## Load", "", *_load_lines(name, path), "",
        "## Architecture and image budget", "",
        f"- vision: timm `resnet18` layout with stage widths {a['vision_channels']}, blocks {a['vision_layers']}, "
        f"stem {a['vision_stem']}; {a['image_size']} px images, output stride 32: an "
        f"{a['image_size'] // 32} x {a['image_size'] // 32} feature map = {meta['tokens_per_image']} image tokens "
        f"(about one per cell of the {meta['grid']['rows']} x {meta['grid']['cols']} grid)",
        f"- projector: Linear + GELU + Linear to the decoder width {a['text_hidden']}",
        f"- language model: Qwen2, width {a['text_hidden']}, layers {a['text_layers']}, heads {a['text_heads']} "
        f"({a['text_kv_heads']} key/value heads), MLP {a['text_intermediate']}",
        "- tokenizer: byte-level BPE trained on the task texts, with object ids 0-255, grid cells and the "
        "literal pieces of the answer format as single tokens (an answer item costs ~13 tokens); Qwen-style chat "
        "template (`<|im_start|>user ... <|im_end|>`)",
        "- render images at the model's image size (no resizing, no crop); loading needs `timm`", "",
        "## How it was trained", "",
        f"`{t['command']}` (the resolved config is `{PRETRAIN_CONFIG}` in this folder): {t['steps']} steps "
        + (f"(the best validation of a {t['run_steps']}-step run) " if t.get("run_steps", t["steps"]) != t["steps"]
           else "") +
        f"of {t['batch_size']} examples ({t['examples']} examples, every one a freshly rendered random scene), "
        f"AdamW at {t['lr']}, warmup + cosine, seed {t['seed']}, {_stages(t)}, {_where(t)}. "
        f"Catalog and tables: {meta['catalog']}. Task mix: {t['mix']}{_curriculum(t)}.", "",
        "## Perception scores", "",
    ]
    if bench:
        lines += [f"On {bench['n_images']} freshly rendered held-out scenes and sheets "
                  f"(`python benchmarks/bench_perception.py`, constrained decoding; a list ends where the model names an object again):", "",
                  "| object-set F1 (type, id) | exact cell set | direction (no plates) | GoMO mark id | cell IoU | parse rate |",
                  "|---:|---:|---:|---:|---:|---:|",
                  "| " + " | ".join(_fmt(bench["scores"].get(k)) for k in
                                   ("object_f1", "cells_exact", "direction", "mark_id", "cell_iou", "parse_rate")) + " |",
                  ""]
        if bench.get("transcribe"):
            c = bench["transcribe"]
            lines += [f"Copying a list written in the prompt (not perception; {c['n']} *transcribe* questions): "
                      f"object F1 {c['object_f1']:.2f}, the written length {c['length_exact']:.2f} of the time.", ""]
    if curve:
        lines += [f"Validation during training ({len(curve)} validations; last at step {last['step']}):", "",
                  "| step | object F1 | exact cells | direction | mark id | mean | tower: type / id within type |",
                  "|---:|---:|---:|---:|---:|---:|---:|"]
        shown = curve[:: max(1, len(curve) // 8)]
        for row in shown + ([last] if shown[-1] is not last else []):
            lines.append("| " + " | ".join([str(row["step"])] + [_fmt(row.get(f"val/{k}")) for k in
                                             ("object_f1", "cells_exact", "direction", "mark_id", "perception")]
                                            + [f"{_fmt(row.get('val/tower_type'))} / {_fmt(row.get('val/tower_id'))}"])
                            + " |")
        lines.append("")
    lines += _selection_lines(selection)
    lines += [
        "## Limits", "",
        "- It knows the 125 objects and 5 tables it was trained on (the embedded default catalog); another "
        "catalog needs pretraining again (`dataset:` in the config points at your catalog and tables).",
        f"- Grid-marked images with the {meta['grid']['rows']} x {meta['grid']['cols']} grid at {a['image_size']} px "
        "only; no unmarked (x, y) answers, no free text.",
        *([f"- It does not yet name objects reliably: held-out object-set F1 {bench['scores']['object_f1']:.2f} and "
           f"GoMO mark id {bench['scores']['mark_id']:.2f} (target 0.9). It reads types, cells and directions better "
           "than ids (which object of a type is which); docs/tiny_base.md says why and what to try."]
          if bench and bench["scores"].get("object_f1", 1.0) < 0.5 else []),
        "- A plate's direction cannot be seen (round and square plates look the same turned around); "
        "directions are scored without plates.",
        "- Tiny and trained on synthetic images: a tool for CPU experiments and tests, not a result about "
        "real VLMs. Real runs fine-tune SmolVLM or Qwen2-VL on a GPU (configs/finetune_smolvlm_256m.yaml).", "",
    ]
    atomic_write_text(folder / "README.md", "\n".join(lines))
    return folder / "README.md"


def save_random_base(out: Path, arch=None, seed: int = 0) -> Path:
    """An UNTRAINED base (random weights) exported like a pretrained one: for tests and smoke runs only."""
    from degusta_learn.pretrain.base import BaseArchitecture, build_base
    from degusta_learn.pretrain.config import PretrainConfig

    arch = arch or BaseArchitecture()
    model, processor = build_base(arch, seed=seed)
    out = Path(out)
    return export_base(model, processor, PretrainConfig(model=arch, seed=seed), out, out.parent / f".{out.name}.norun",
                       steps=0)
