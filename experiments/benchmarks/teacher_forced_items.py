"""Teacher-forced, item by item: how well a fine-tune predicts each item of the TRUE answer, given the true items before it.

The companion of benchmarks/by_position.py (which scores free answers, where a wrong early item changes what follows).
Each test episode's ground-truth answer is fed whole (one forward pass, as in training); every supervised token is
assigned to its item (1 = the first object of the answer, the person's first placed) and to its field, and scored:
the type and id tokens (which object comes next), the cell tokens (where it goes, given the right object) and the
direction. Per item index: the top-1 accuracy of each field's tokens, and the mean loss of the id and cell tokens.

Usage:
    python benchmarks/teacher_forced_items.py --dataset data/naturalistic --adapter RUN/adapter [--episodes 200]
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

TYPE, ID, CELLS, DIRECTION = "'type'", "'id'", "'position'", "'cardinal_direction'"
FIELDS = {TYPE: r"[a-z]{3}", ID: r"\d", CELLS: r"[A-Z]\d", DIRECTION: r"[NSEW]"}
"""An answer item's keys (`prompting.format_answer`) and what a token of its value looks like (punctuation is
left out of the scores)."""


def token_fields(pieces: list[str]) -> list[tuple[int, str] | None]:
    """(item index, field) of each answer token given the decoded pieces in order; None for structure tokens."""
    out, text = [], ""
    for piece in pieces:
        prev, text = text, text + piece
        item = prev.count("{") - 1
        key = max(FIELDS, key=prev.rfind)
        if item < 0 or prev.rfind(key) < prev.rfind("{") or not re.search(FIELDS[key], piece):
            out.append(None)
        else:
            out.append((item, key))
    return out


def main(argv=None) -> int:
    import torch

    from degusta_learn.config import load_config
    from degusta_learn.finetune.collate import IGNORE, Collator
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.data import LiftedExamples
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset, make_episodes
    from degusta_learn.vlm.inputs import ChatFormat
    from degusta_learn.vlm.load import load_vlm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, required=True)
    ap.add_argument("--adapter", required=True, help="the fine-tune's adapter folder")
    ap.add_argument("--base", default="tiny_vlm_base")
    ap.add_argument("--config", default="configs/finetune_tiny_base_cpu.yaml", help="the fine-tune's config (prompts)")
    ap.add_argument("--episodes", type=int, default=200, help="the first N test episodes at context 4")
    ap.add_argument("--last", type=int, default=6, help="the last row pools this item index and beyond")
    args = ap.parse_args(argv)
    cfg = load_config(FinetuneConfig, args.config, [f"dataset={args.dataset}"])
    ds = load_dataset(cfg.dataset)
    episodes = make_episodes(ds, 4, "test", cfg.seed)[:args.episodes]
    grid = Grid(cfg.data.grid.rows, cfg.data.grid.cols)
    examples = LiftedExamples(ds, episodes, cfg.method, grid, cfg.data.render_size, cfg.data.prompt_options())
    model, processor = load_vlm(args.base, adapter=args.adapter, device="cpu", dtype="float32")
    tok = processor.tokenizer
    collate = Collator(processor, ChatFormat(processor, model.generation_config), cfg.data.max_length,
                       getattr(model.config, "image_token_id", None))
    scores: dict[tuple[int, str], list[tuple[float, bool]]] = {}
    with torch.no_grad():
        for start in range(0, len(episodes), 8):
            batch = collate([examples[i] for i in range(start, min(start + 8, len(episodes)))])
            labels = batch.pop("labels")[:, 1:]
            batch.pop("label_weights", None)
            logp = torch.log_softmax(model(**batch).logits[:, :-1].float(), -1)
            for b in range(len(labels)):
                where = (labels[b] != IGNORE).nonzero().flatten().tolist()
                ys = [int(labels[b, t]) for t in where]
                for t, y, tf in zip(where, ys, token_fields([tok.decode([y]) for y in ys])):
                    if tf is not None:
                        key = (min(tf[0], args.last - 1), tf[1])
                        scores.setdefault(key, []).append((-float(logp[b, t, y]), int(logp[b, t].argmax()) == y))
    print(f"{args.adapter}: teacher-forced on {len(episodes)} test episodes (context 4)")
    print("| item | type: top-1 | id: top-1, loss | cells: top-1, loss | direction: top-1 | type tokens |\n"
          "|---|---:|---|---|---:|---:|")
    for item in range(args.last):
        top1 = {f: np.mean([c for _, c in scores.get((item, f), [])] or [np.nan]) for f in FIELDS}
        loss = {f: np.mean([x for x, _ in scores.get((item, f), [])] or [np.nan]) for f in FIELDS}
        print(f"| {item + 1}{'+' if item == args.last - 1 else ''} | {top1[TYPE]:.3f} | {top1[ID]:.3f}, "
              f"{loss[ID]:.2f} | {top1[CELLS]:.3f}, {loss[CELLS]:.2f} | {top1[DIRECTION]:.3f} | "
              f"{len(scores.get((item, TYPE), []))} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
