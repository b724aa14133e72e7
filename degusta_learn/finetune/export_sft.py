"""`degusta data export-sft`: a fine-tuning config's lifted-image examples as a "messages + images" dataset.

Usage:
    degusta data export-sft --config configs/finetune_smolvlm_256m.yaml --out exports/smolvlm_sft
    degusta data export-sft --config configs/finetune_smolvlm_256m.yaml --out exports/smolvlm_sft_val --split val

Writes into `--out` (staged and swapped in whole by `files.folders.write_folder`; a folder this command did not write
is refused):

- `<split>.jsonl`: one line per example, the Hugging Face datasets "messages + images" layout that TRL's
  `SFTTrainer` reads: `{"messages": [{"role": "user", "content": [{"type": "image"}, ..., {"type": "text",
  "text": ...}]}, {"role": "assistant", "content": [{"type": "text", "text": answer}]}], "images":
  ["images/<episode>_0.png", ...]}`, the images in the order of the `{"type": "image"}` entries;
- `<split>_sharegpt.jsonl`: the same examples in LLaMA-Factory's sharegpt form, whose `content` is a string
  with one `<image>` placeholder where each image goes (LLaMA-Factory does not read typed content lists), and
  `dataset_info.json`, its dataset entry (`--dataset_dir <out>`);
- `images/*.png`: every image at `data.render_size`, as drawn for training;
- `README.md`: a dataset card saying how to load it; `degusta_export.json`: what was exported, from where.

The examples are the trainer's own: `finetune.train.build_examples` (the seeded participant split,
`data.contexts`, `data.max_train_episodes`, `data.val_episodes`), their epoch-0 contexts (with
`data.resample_contexts` later epochs draw others), the prompt options (`data.include` / `data.compose`),
and `vlm.inputs.prompt_messages`, which turns each prompt into the chat messages and images the collator
sends. No model, processor or `datasets` package is needed.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.files.folders import OutputKind, check_target, write_folder
from degusta_learn.files.guard import refuse_replacing_inputs

SPLITS = ("train", "val")
MARKER = "degusta_export.json"
IMAGE_TOKEN = "<image>"
"""LLaMA-Factory's image placeholder in a sharegpt message."""


def _ours(folder: Path) -> bool:
    """A non-empty folder is ours only when its marker names this export (never a user's folder)."""
    try:
        return json.loads((folder / MARKER).read_text(encoding="utf-8")).get("kind") == "degusta_sft_export"
    except (OSError, ValueError, AttributeError):
        return False


SFT_EXPORT = OutputKind("fine-tuning data export", (
    "train.jsonl", "val.jsonl", "train_sharegpt.jsonl", "val_sharegpt.jsonl", "dataset_info.json", "images",
    "README.md", MARKER), check=_ours, merge=False)


def sft_rows(examples) -> Iterator[tuple[dict, dict, list]]:
    """Per example (epoch 0), one at a time (images are drawn on the fly, never all held at once):
    (messages + images row, sharegpt row, [(relative path, PIL image)])."""
    from degusta_learn.vlm.inputs import assistant_message, prompt_messages

    stems = set()
    for i in range(len(examples)):
        ex = examples[i]
        stem = re.sub(r"[^A-Za-z0-9._-]+", "_", ex.episode).strip("._") or "example"
        if stem in stems:
            stem = f"{i:06d}_{stem}"
        stems.add(stem)
        messages, images = prompt_messages(ex.prompt)
        names = [f"images/{stem}_{j}.png" for j in range(len(images))]
        row = {"messages": [*messages, assistant_message(ex.answer)], "images": names}
        sharegpt = {"messages": [{"role": m["role"], "content": "".join(
            IMAGE_TOKEN if part["type"] == "image" else part["text"] for part in m["content"])}
            for m in row["messages"]], "images": names}
        yield row, sharegpt, list(zip(names, images))


def export_sft(config: str | Path | None, out: str | Path, split: str = "train",
               overrides: list[str] | None = None) -> tuple[Path, int, int]:
    """Export the `split` examples of the finetune config at `config`; returns (folder, examples, images)."""
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.train import build_examples
    from degusta_learn.methods import build_config, get_trainer
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset

    if split not in SPLITS:
        raise DegustaError(f"--split: expected one of {', '.join(SPLITS)}, got {split!r}")
    _, cfg = build_config(config, overrides, "kind", get_trainer)
    if not isinstance(cfg, FinetuneConfig):
        raise DegustaError(f"{config}: kind: {cfg.kind!r}; export-sft takes a fine-tuning config (kind: finetune)")
    check_target(out, SFT_EXPORT)
    refuse_replacing_inputs(out, [("the config", config)], kind=SFT_EXPORT, datasets=[cfg.dataset],
                            key="--out")
    ds = load_dataset(cfg.dataset)
    train, val = build_examples(cfg, ds, Grid(cfg.data.grid.rows, cfg.data.grid.cols))
    examples = train if split == "train" else val
    if not len(examples):
        raise DegustaError(f"{config}: no {split} examples to export"
                           + (" (data.val_episodes is 0)" if split == "val" else ""))
    n = n_images = 0
    with write_folder(out, SFT_EXPORT) as tmp:
        (tmp / "images").mkdir()
        with open(tmp / f"{split}.jsonl", "w", encoding="utf-8") as rows, \
                open(tmp / f"{split}_sharegpt.jsonl", "w", encoding="utf-8") as sharegpt:
            for row, shared, images in sft_rows(examples):
                for name, image in images:
                    image.save(tmp / name, format="PNG")
                rows.write(json.dumps(row, ensure_ascii=False) + "\n")
                sharegpt.write(json.dumps(shared, ensure_ascii=False) + "\n")
                n, n_images = n + 1, n_images + len(images)
        info = {f"degusta_{split}": {"file_name": f"{split}_sharegpt.jsonl", "formatting": "sharegpt",
                                     "columns": {"messages": "messages", "images": "images"},
                                     "tags": {"role_tag": "role", "content_tag": "content", "user_tag": "user",
                                              "assistant_tag": "assistant"}}}
        (tmp / "dataset_info.json").write_text(json.dumps(info, indent=2) + "\n", encoding="utf-8")
        (tmp / "README.md").write_text(dataset_card(cfg, split, n, n_images), encoding="utf-8")
        (tmp / MARKER).write_text(json.dumps({
            "kind": "degusta_sft_export", "version": 1, "config": str(config), "split": split,
            "dataset": cfg.dataset, "seed": cfg.seed, "method": cfg.method, "render_size": cfg.data.render_size,
            "include": list(cfg.data.include), "compose": list(cfg.data.compose),
            "examples": n, "images": n_images,
            "participants": sorted({ep.participant for ep in examples.episodes}),
        }, indent=2) + "\n", encoding="utf-8")
    return Path(out), n, n_images


def dataset_card(cfg, split: str, n: int, n_images: int) -> str:
    """README.md of an export: what it is and how TRL, LLaMA-Factory and `datasets` load it."""
    from degusta_learn.textsafe import md_code

    return f"""# DegustaBot lifted-image SFT data ({split})

{n} examples, {n_images} images, exported by `degusta data export-sft` from the fine-tuning config of
method `{cfg.method}` on {md_code(cfg.dataset)} (participant split seed {cfg.seed}; `degusta_export.json` lists the
participants). Each example is exactly what `degusta train` trains on in its first epoch: the same prompt
text and lifted images (rendered at {cfg.data.render_size} px; prompt options include={list(cfg.data.include)},
compose={list(cfg.data.compose)}) and the same target answer. The data is SYNTHETIC if the dataset is.

## Files

- `{split}.jsonl`: Hugging Face "messages + images" rows (TRL): `messages` = one user turn whose `content`
  lists `{{"type": "image"}}` and `{{"type": "text", "text": ...}}` parts, and one assistant turn with the
  answer; `images` = paths relative to this folder, in the order of the image parts.
- `{split}_sharegpt.jsonl` + `dataset_info.json`: the same rows for LLaMA-Factory (`content` is a string with
  one `<image>` per image).
- `images/`: the PNGs.

## Load with `datasets`

```python
import os
from datasets import load_dataset, Sequence, Image

root = "path/to/this/folder"
ds = load_dataset("json", data_files=os.path.join(root, "{split}.jsonl"), split="train")
ds = ds.map(lambda r: {{"images": [os.path.join(root, p) for p in r["images"]]}})
ds = ds.cast_column("images", Sequence(Image()))   # PIL images on access
```

## TRL `SFTTrainer`

The rows have the layout of `HuggingFaceH4/llava-instruct-mix-vsft`, the dataset of TRL's VLM SFT example
scripts. Use them with a vision-language collator: TRL's `SFTTrainer` with a VLM processor
(`processing_class=processor`) handles "messages + images" rows itself in recent releases; with older ones
write a collator that calls `processor.apply_chat_template(row["messages"])` and
`processor(text=..., images=row["images"])` and masks the prompt tokens in the labels (as degusta does:
only the answer and the end-of-turn token are supervised). Keep `remove_unused_columns=False`
(`SFTConfig`) so the `images` column reaches the collator.

## LLaMA-Factory

Pass this folder as `dataset_dir` and the entry of `dataset_info.json` as the dataset:

```yaml
dataset_dir: path/to/this/folder
dataset: degusta_{split}
```

The entry is `{{"file_name": "{split}_sharegpt.jsonl", "formatting": "sharegpt", "columns": {{"messages":
"messages", "images": "images"}}, "tags": {{"role_tag": "role", "content_tag": "content", "user_tag": "user",
"assistant_tag": "assistant"}}}}`; image paths are relative to `media_dir` (by default the `dataset_dir`).
"""
