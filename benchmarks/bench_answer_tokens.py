"""How much of a fine-tuning answer is content, in tokens, and how much of the loss the content tokens carry.

An answer is `[{'type': 'plate', 'id': 17, 'position': ['D4', 'D5'], 'cardinal_direction': 'N'}, ...]`: the
values (type, id, cells, direction) are content, the rest is syntax that the answer grammar forces at
decoding time. (1) With a tokenizer (default: the real SmolVLM-256M one), count the supervised completion
tokens (template lead + answer + end-of-turn) of every ground-truth answer of a dataset that overlap a content
character. (2) Optionally, with a trained model (`--model`, `--adapter`), split its next-token loss on
validation episodes into content and syntax tokens (docs/finetune.md, "What the loss sees").

Usage:
    python benchmarks/bench_answer_tokens.py                               # share with the real tokenizer
    python benchmarks/bench_answer_tokens.py --model runs/tiny/idefics3_scratch \\
        --run runs/finetune_tiny_scratch_cpu --weights best_model --episodes 16
"""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"

CONTENT = re.compile(r"'type': '([^']+)'|'id': (\d+)|'([A-Z]+\d+)'|'cardinal_direction': '([A-Z]+)'")
FIELDS = ("type", "id", "cell", "direction")


def content_mask(tokenizer, text: str) -> tuple[list[int], list[str | None]]:
    """(token ids of `text`, per token the content field it overlaps or None for syntax)."""
    spans = []
    for m in CONTENT.finditer(text):
        g = next(i for i in range(1, 5) if m.group(i) is not None)
        spans.append((m.start(g), m.end(g), FIELDS[g - 1]))
    enc = tokenizer(text, add_special_tokens=False, return_offsets_mapping=True)
    fields = [next((k for s, e, k in spans if a < e and b > s), None) for a, b in enc["offset_mapping"]]
    return enc["input_ids"], fields


def token_share(tokenizer, answers: list[str], lead: str, end: str) -> dict:
    counts = dict.fromkeys(FIELDS, 0)
    total = 0
    chars = content_chars = 0
    for answer in answers:
        ids, fields = content_mask(tokenizer, lead + answer + end)
        total += len(ids)
        for f in fields:
            if f is not None:
                counts[f] += 1
        chars += len(answer)
        content_chars += sum(len(next(g for g in m.groups() if g is not None)) for m in CONTENT.finditer(answer))
    content = sum(counts.values())
    return {"answers": len(answers), "tokens": total, "content": content, "share": content / total,
            "char_share": content_chars / chars, **{f"share_{k}": v / total for k, v in counts.items()}}


def loss_split(args, ds, grid) -> dict:
    """Mean next-token loss of a trained model on content vs syntax answer tokens of val episodes."""
    import torch
    import torch.nn.functional as F

    from degusta_learn.finetune.collate import IGNORE, Collator
    from degusta_learn.finetune.data import LiftedExamples
    from degusta_learn.scene import make_episodes
    from degusta_learn.vlm.generate import chat_format
    from degusta_learn.vlm.inputs import set_image_budget
    from degusta_learn.vlm.load import load_vlm
    from degusta_learn.vlm.prompt_options import PromptOptions
    from degusta_learn.vlm.record import read_record

    weights = Path(args.run) / args.weights
    adapter = str(weights) if (weights / "adapter_config.json").is_file() else None
    model, processor = load_vlm(str(weights) if adapter is None else args.model, adapter=adapter, device="cpu",
                                dtype="float32")
    rec = read_record(weights / "degusta_finetune.json")
    set_image_budget(processor, model.config, rec.image_size)
    fmt = chat_format(model, processor)
    collate = Collator(processor, fmt, 100_000, getattr(model.config, "image_token_id", None))
    episodes = make_episodes(ds, args.context, "val", rec.trained_on.seed)[:args.episodes]
    examples = LiftedExamples(ds, episodes, rec.method, grid, rec.render_size, PromptOptions(
        include=list(rec.prompt.include), compose=list(rec.prompt.compose)))
    sums, counts = {"content": 0.0, "syntax": 0.0}, {"content": 0, "syntax": 0}
    model.eval()
    for i in range(len(examples)):
        ex = examples[i]
        batch = collate([ex])
        with torch.no_grad():
            logits = model(**{k: v for k, v in batch.items() if k != "labels"}).logits[0, :-1]
        target = batch["labels"][0, 1:]
        sel = target != IGNORE
        losses = F.cross_entropy(logits[sel].float(), target[sel], reduction="none").tolist()
        _, fields = content_mask(processor.tokenizer, fmt.completion_text(ex.answer))
        if len(fields) != len(losses):
            raise RuntimeError(f"episode {ex.episode}: {len(fields)} completion tokens but {len(losses)} supervised")
        for f, v in zip(fields, losses):
            key = "syntax" if f is None else "content"
            sums[key] += v
            counts[key] += 1
    n = counts["content"] + counts["syntax"]
    return {"episodes": len(examples), "tokens": n, "content_tokens": counts["content"] / n,
            "loss_all": (sums["content"] + sums["syntax"]) / n,
            "loss_content": sums["content"] / counts["content"], "loss_syntax": sums["syntax"] / counts["syntax"],
            "content_share_of_loss": sums["content"] / (sums["content"] + sums["syntax"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="data/naturalistic")
    ap.add_argument("--tokenizer", default=str(Path(__file__).resolve().parents[2] / "shared" / "reference-models"
                                               / "SmolVLM-256M-Instruct"))
    ap.add_argument("--model", help="base model folder (with --run and an adapter folder)")
    ap.add_argument("--run", help="a fine-tuning run folder: split the loss of its --weights")
    ap.add_argument("--weights", default="best_adapter", help="folder inside --run: best_adapter, adapter, best_model")
    ap.add_argument("--episodes", type=int, default=16)
    ap.add_argument("--context", type=int, default=4)
    args = ap.parse_args()

    from transformers import AutoTokenizer

    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.task.answer_format import answer_items, format_answer

    ds, grid = load_dataset(args.data), Grid(8, 8)
    tok = AutoTokenizer.from_pretrained(args.tokenizer)
    answers = [format_answer(answer_items(list(a.placements), ds.catalog, "grid", grid), "grid")
               for a in ds.arrangements]
    share = token_share(tok, answers, " ", "<end_of_utterance>")  # SmolVLM's completion: lead + answer + end
    print(f"{args.tokenizer}: {share['answers']} answers, {share['tokens']} tokens "
          f"({share['tokens'] / share['answers']:.1f} per answer), content {share['share']:.1%} of tokens "
          f"(characters: {share['char_share']:.1%}); " + ", ".join(f"{k} {share[f'share_{k}']:.1%}" for k in FIELDS))
    if args.run:
        split = loss_split(args, ds, grid)
        print(f"{args.run}/{args.weights} on {split['episodes']} val episodes ({split['tokens']} answer tokens, "
              f"{split['content_tokens']:.1%} content): "
              f"loss all {split['loss_all']:.3f}, content {split['loss_content']:.3f}, syntax "
              f"{split['loss_syntax']:.3f}; content tokens carry {split['content_share_of_loss']:.1%} of the loss")


if __name__ == "__main__":
    main()
