"""Fine-tuned weights as plain folders: the last ones and the best ones, each written whole or not at all.

A fine-tuning run folder holds two exports of the weights, both loadable without degusta:

- `adapter/` (LoRA / QLoRA: `PeftModel.save_pretrained`) or `model/` (full: `save_pretrained` + the
  processor): the LAST weights, rewritten at every checkpoint and at the end (equal to `last.ckpt`);
- `best_adapter/` or `best_model/`: the weights `best.ckpt` holds, i.e. those of the validation with the
  best `trainer.monitor` so far (`val/set_rmsd` in every shipped config). Rewritten each time the monitor
  improves (`FinetuneModule.on_validation_end`, rank 0) and checked against `best.ckpt` at the end of the
  run (`sync_best`: an export a kill interrupted is redone from `best.ckpt`). This is what the predict
  configs load. Its `degusta_selection.json` says which validation it comes from (monitor, score, step, split,
  the number of validation episodes and participants) and the decoding that validation used (`decoding`, in
  predict's spelling): `degusta predict` warns when its own decoding differs; `decoding_from: adapter` uses it.

Every export also gets `degusta_finetune.json` (`finetune.train.write_meta`: how prompts were built), the resolved
config (`finetune_config.yaml`) and a model card (`README.md`: finetune/card.py) that the Hub and peft read.
A folder is staged beside it and swapped in whole (`files.folders.write_folder` with `MODEL_FOLDER`): a reader never
sees a half-written adapter; a kill leaves the previous complete folder (or, in the instant between the two
renames, an `.old.tmp` folder that the next write puts back), and a file of the user's inside it is kept.

Usage (what `finetune.train.run` and `FinetuneModule` do):
    save_last(module, run_dir)            # adapter/ or model/
    sync_best(module, run_dir)            # best_adapter/ or best_model/, from best.ckpt if it is stale
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.files.folders import OutputKind, write_folder
from degusta_learn.files.jsonio import atomic_write_json, read_json
from degusta_learn.training import BEST
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.vlm.record import SELECTION_FILE  # in a best folder: the validation that chose it (re-exported)

LAST_DIRS = {True: "adapter", False: "model"}
"""Folder of the last weights, by `module.lora`."""
BEST_DIRS = {True: "best_adapter", False: "best_model"}
"""Folder of the best weights (what `best.ckpt` holds), by `module.lora`."""
MODEL_FOLDER = OutputKind("model folder", ("*.safetensors", "*.bin", "*.json", "*.txt", "*.jinja", "*.model",
                                           "*.yaml", "README.md"))
"""What `save_pretrained` (model, processor, PEFT adapter) and degusta write into a model folder."""


def write_weights(module, out: Path, selection: dict | None = None) -> Path:
    """Write `module`'s current weights to `out` as a plain folder (adapter or model + processor), with the
    fine-tuning metadata, the model card (finetune/card.py) and, for a best export, `selection`; all or nothing
    (`write_folder`: a card that cannot be written leaves the previous folder as it was)."""
    from degusta_learn.finetune.card import write_finetune_files
    from degusta_learn.finetune.lora import save_adapter

    with write_folder(out, MODEL_FOLDER) as tmp:
        if module.lora:
            save_adapter(module.model, tmp)
        else:
            module.model.save_pretrained(str(tmp))
            module.processor.save_pretrained(str(tmp))
        write_meta(tmp, module.cfg, module.processor, chosen_on_val=selection is not None)
        if selection is not None:
            atomic_write_json(tmp / SELECTION_FILE, selection)
        write_finetune_files(tmp, module.cfg, adapter=module.lora, selection=selection,
                             metrics=validation_scores(module, selection))
    return Path(out)


def validation_scores(module, selection: dict | None) -> dict | None:
    """The validation scores of the weights being exported: the module's last validation when it is the selected
    one (or, for the last weights, the latest), else the run's logged row at the selected step; None if unknown."""
    from degusta_learn.training import validation_curve

    last = getattr(module, "last_val", None)
    step = int(getattr(module, "global_step", -1))
    if last and (selection is None or int(selection["step"]) == step):
        return {k: v for k, v in last.items() if k.startswith("val/")}
    run_dir = getattr(module, "run_dir", None)
    if selection is None or run_dir is None:
        return None
    rows = [r for r in validation_curve(Path(run_dir), selection["monitor"]) if r["step"] == int(selection["step"])]
    return rows[-1] if rows else None


def save_last(module, run_dir: Path) -> Path:
    """`adapter/` (LoRA) or `model/` (full) from the module's current weights."""
    return write_weights(module, Path(run_dir) / LAST_DIRS[module.lora])


def best_score(trainer) -> tuple[str, float] | None:
    """(best checkpoint path, its monitor value) as the trainer's ModelCheckpoint holds them, or None."""
    cb = getattr(trainer, "checkpoint_callback", None)
    if cb is None or getattr(cb, "monitor", None) is None or cb.best_model_score is None or not cb.best_model_path:
        return None
    return str(cb.best_model_path), float(cb.best_model_score)


def selection_record(module, score: float, step: int, epoch: int) -> dict:
    """The `SELECTION_FILE` of a best folder: which validation chose the weights (monitor, its value, step), on
    what (split "val", the number of episodes and of participants) and decoded how (`decoding`: the fine-tune's
    `decoding:` section, in predict's spelling, so that `degusta predict` can compare it or use it exactly)."""
    import dataclasses

    t = module.cfg.trainer
    episodes, participants = validation_set(module)
    return {"monitor": t.monitor, "mode": t.monitor_mode, "score": score, "step": step, "epoch": epoch,
            "checkpoint": BEST, "split": "val", "val_episodes": episodes, "val_participants": participants,
            "decoding": dataclasses.asdict(module.cfg.decoding)}


def validation_set(module) -> tuple[int | None, int | None]:
    """(episodes, distinct participants) of the module's validation set (its datamodule's `val`); (None, None) when
    the module is not attached to a trainer with one."""
    try:
        val = module.trainer.datamodule.val
        episodes = list(getattr(val, "episodes", None) or [])
    except (AttributeError, RuntimeError):  # RuntimeError: a LightningModule not attached to a Trainer
        return None, None
    return len(episodes), len({e.participant for e in episodes})


def save_best(module, run_dir: Path, score: float) -> Path:
    """`best_adapter/` or `best_model/` from the module's current weights, which `best.ckpt` has just saved."""
    record = selection_record(module, score, int(module.global_step), int(module.current_epoch))
    return write_weights(module, Path(run_dir) / BEST_DIRS[module.lora], record)


def exported_step(folder: Path) -> int | None:
    """The training step a best folder was exported at (None: no readable selection record)."""
    with contextlib.suppress(Exception):
        return int(read_json(Path(folder) / SELECTION_FILE)["step"])
    return None


def sync_best(module, run_dir: Path) -> Path | None:
    """Make the best folder hold `best.ckpt`'s weights: re-export from `best.ckpt` when the folder is missing
    or from another step (an export a kill interrupted). Loads those weights into `module` (call it last).
    Returns the best folder, or None when the run has no `best.ckpt` (`trainer.monitor: null`)."""
    import torch

    run_dir = Path(run_dir)
    best, out = run_dir / BEST, run_dir / BEST_DIRS[module.lora]
    if not best.is_file():
        return None
    ckpt = torch.load(best, map_location="cpu", weights_only=True, mmap=True)
    step = int(ckpt["global_step"])
    if exported_step(out) == step and out.is_dir():
        return out
    state = ckpt["state_dict"]
    needed = {f"model.{n}" for n, p in module.model.named_parameters() if p.requires_grad or not module.lora}
    lacking, extra = needed - state.keys(), state.keys() - module.state_dict().keys()
    if lacking or extra:
        raise DegustaError(f"{best}: its weights do not fit this run's model (lacking {sorted(lacking)[:2]}, "
                           f"unknown {sorted(extra)[:2]}); delete it or use another trainer.run_name")
    module.load_state_dict(state, strict=False)
    record = selection_record(module, checkpoint_score(ckpt), step, int(ckpt.get("epoch", -1)))
    return write_weights(module, out, record)


def checkpoint_score(ckpt: dict) -> float:
    """The monitor value a Lightning checkpoint was saved with as best (nan if it records none)."""
    for key, state in (ckpt.get("callbacks") or {}).items():
        if str(key).startswith("ModelCheckpoint") and isinstance(state, dict):
            score = state.get("best_model_score")
            if score is not None:
                return float(score)
    return float("nan")


def write_meta(out: Path, cfg: FinetuneConfig, processor, chosen_on_val: bool = True) -> None:
    """Write the run's `FinetuneRecord` (`degusta_finetune.json`, vlm/record.py) into `out`: how the prompts
    were built (`prompt`: the image groups, composed canvases and `modality` of `data`), and what the model was trained on (dataset fingerprint, split seed, train and validation
    participants), which the hf backend checks before predicting. `chosen_on_val`: whether validation chose the
    weights in `out` (a best folder, the run folder) or not (the last weights); early stopping makes it true."""
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset, participants_in
    from degusta_learn.scene.dataset import dataset_identity
    from degusta_learn.vlm.record import FinetuneRecord, TrainingData, write_record

    ds = load_dataset(cfg.dataset)
    trained_on = TrainingData(
        dataset=cfg.dataset, fingerprint=dataset_identity(ds), seed=cfg.seed, contexts=list(cfg.data.contexts),
        train_participants=participants_in(ds, "train", cfg.seed),
        val_participants=participants_in(ds, "val", cfg.seed) if cfg.data.val_episodes else [],  # as build_examples
        chosen_on_val=chosen_on_val or cfg.trainer.early_stopping_patience is not None)
    write_record(out, FinetuneRecord(
        base_model=cfg.model.name, method=cfg.method, mode=cfg.lora.mode,
        grid=Grid(cfg.data.grid.rows, cfg.data.grid.cols),
        prompt=cfg.data.prompt_options(),
        image_size=cfg.model.image_size, render_size=cfg.data.render_size,
        processor_size=dict(getattr(processor.image_processor, "size", {}) or {}), trained_on=trained_on))
