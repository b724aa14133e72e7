"""Probe a perception-pretraining checkpoint: does the decoder read the image, and which answer tokens has it learned?

Teacher-forced accuracy of the next answer token, per task (list, locate, describe, gomo) and per kind of
answer token (type, id, first cell of an item, later cell, direction), on fresh examples of the run's own
task mix, computed twice: with the vision tower's image tokens, and with every image token replaced by its
oracle sum (`dense.OracleTokens`: the embeddings of the cell and of what covers it). Equal numbers mean the
decoder does not use the image yet; a gap means the tower is behind the decoder. Nothing is written.

Usage:
    python benchmarks/probe_pretrain.py checkpoints/pretrain_tiny_vlm_cpu                 # its last.ckpt
    python benchmarks/probe_pretrain.py RUN_DIR --checkpoint RUN_DIR/best.ckpt --batches 6
    python benchmarks/probe_pretrain.py RUN_DIR --curriculum     # the questions of data.curriculum_mix
"""

from __future__ import annotations

import argparse
import os
from collections import defaultdict
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"


def token_kinds(tokenizer, catalog, grid) -> dict[int, str]:
    """Token id -> its content kind (cell, type, id, dir); every other token is format."""
    from degusta_learn.render.grid import DIRECTIONS

    one = lambda text: tokenizer.encode(text, add_special_tokens=False)[0]  # noqa: E731
    kinds = {one(c): "cell" for c in grid.cells}
    for o in catalog:
        kinds[one(o.type)], kinds[one(str(o.id))] = "type", "id"
    kinds.update({one(d): "dir" for d in DIRECTIONS})
    return kinds


def tally(pred, target, tasks, kinds, counts) -> None:
    """Add right/total per "task:kind" of every supervised content token (a cell after a cell is "cell+")."""
    for row, task in enumerate(tasks):
        previous = None
        for t in range(target.shape[1]):
            y = int(target[row, t])
            kind = kinds.get(y)
            if y < 0 or kind is None:
                continue
            label = "cell+" if kind == "cell" and previous == "cell" else kind
            counts[f"{task}:{label}"][0] += int(pred[row, t] == y)
            counts[f"{task}:{label}"][1] += 1
            previous = kind


def task_label(meta: dict) -> str:
    """A question's row in the table: its task, list questions split by the order asked (reading / placement)."""
    return f"{meta['task']}/{meta['order']}" if meta.get("order") else meta["task"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a pretraining run folder (config.yaml, init/, last.ckpt)")
    ap.add_argument("--checkpoint", type=Path, default=None, help="default: RUN/last.ckpt")
    ap.add_argument("--batches", type=int, default=3, help="batches of data.batch_size fresh examples")
    ap.add_argument("--curriculum", action="store_true", help="ask the run's data.curriculum_mix questions")
    ap.add_argument("--seed", type=int, default=12345)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)

    import torch
    import yaml

    from degusta_learn.config import load_config
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.pretrain.dense import DenseLabels, OracleTeacher, OracleTokens, projector_of
    from degusta_learn.finetune.pretrain.tasks import PerceptionExamples
    from degusta_learn.finetune.pretrain.train import DenseCollate, PretrainConfig, catalog_and_tables
    from degusta_learn.render.grid import Grid
    from degusta_learn.vlm.generate import chat_format
    from degusta_learn.vlm.load import load_vlm

    torch.set_num_threads(args.threads)
    cfg = load_config(PretrainConfig, data=yaml.safe_load((args.run / "config.yaml").read_text()))
    catalog, tables, root = catalog_and_tables(cfg.dataset)
    grid = Grid(cfg.data.grid.rows, cfg.data.grid.cols)
    model, processor = load_vlm(str(args.run / "init"), device="cpu", dtype="float32", key="run")
    ckpt = args.checkpoint or args.run / "last.ckpt"
    state = torch.load(ckpt, map_location="cpu", weights_only=True)
    model.load_state_dict({k.removeprefix("model."): v for k, v in state["state_dict"].items()
                           if k.startswith("model.")})
    model.eval()
    tok = processor.tokenizer
    kinds = token_kinds(tok, catalog, grid)
    collate = DenseCollate(Collator(processor, chat_format(model, processor), cfg.data.max_length,
                                    model.config.image_token_id),
                           DenseLabels(catalog, cfg.model.tokens_per_side), OracleTokens(catalog, tok, grid))
    bs = cfg.data.batch_size
    examples = PerceptionExamples(catalog, tables, grid, cfg.model.image_size, args.seed, args.batches * bs,
                                  cfg.data.curriculum_mix if args.curriculum else cfg.data.mix, bs, root)
    teacher = OracleTeacher(model.get_input_embeddings(), 1)
    use_oracle = [False]
    projector_of(model).register_forward_hook(lambda m, i, out: teacher.replace(out, 0) if use_oracle[0] else None)
    counts = {False: defaultdict(lambda: [0, 0]), True: defaultdict(lambda: [0, 0])}
    with torch.no_grad():
        for b in range(args.batches):
            exs = [examples[b * bs + j] for j in range(bs)]
            batch = collate(exs)
            teacher.ids, teacher.keep = batch.pop("oracle_ids"), batch.pop("dense_keep")
            batch.pop("dense_targets")
            target = batch.pop("labels")[:, 1:]
            for oracle in (False, True):
                use_oracle[0] = oracle
                pred = model(**batch).logits[:, :-1].argmax(-1)
                tally(pred, target, [task_label(e.meta) for e in exs], kinds, counts[oracle])
    step = state.get("global_step", "?")
    print(f"{ckpt} (step {step}): teacher-forced accuracy of answer tokens, right/total")
    keys = sorted(set(counts[False]) | set(counts[True]))
    print(f"{'task:token':24s} {'tower':>14s} {'oracle':>14s}")
    for k in keys:
        cells = [f"{a / n:.2f} ({a}/{n})" if n else "-" for a, n in (counts[False][k], counts[True][k])]
        print(f"{k:24s} {cells[0]:>14s} {cells[1]:>14s}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
