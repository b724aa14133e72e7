"""Token budget per example of each prompting method and context length, with SmolVLM-256M's REAL processor.

Builds the SmolVLM-256M replica's config and processor (no weights) from the real tokenizer / processor files
in ../shared/reference-models/SmolVLM-256M-Instruct, then counts, for every training example of the
naturalistic train participants, the image, other prompt and answer tokens exactly as `degusta train` would
(the collator, with blank images of the rendered size: token counts depend only on image size). The settings
are configs/finetune_smolvlm_256m.yaml's (image size, prompt groups), with `method` and `data.contexts` varied.

Usage:
    python benchmarks/bench_token_budgets.py [--reference ../shared/reference-models/SmolVLM-256M-Instruct]
        [--dataset data/naturalistic] [--config finetune_smolvlm_256m]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path


def budgets(config: str, reference: Path, dataset: str) -> list[dict]:
    from degusta_learn.config import load_config
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.train import build_examples
    from degusta_learn.finetune.token_count import count_tokens, set_budget
    from degusta_learn.finetune.dry_run import meta_model
    from degusta_learn.names import CONTEXT_LENGTHS, PROMPT_METHODS
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.shipped import resolve_config
    from degusta_learn.vlm.inputs import ChatFormat
    from degusta_learn.vlm.load import load_processor
    from degusta_learn.vlm.replicas import build_replica

    rows = []
    ds = load_dataset(dataset)
    with tempfile.TemporaryDirectory(prefix="degusta-budgets-") as tmp:
        replica = build_replica("smolvlm_256m", Path(tmp) / "replica", reference_dir=reference, weights=False)
        base = load_config(FinetuneConfig, resolve_config(config), [f"model.name={replica}", f"dataset={dataset}"])
        processor = load_processor(str(replica))
        model, model_config = meta_model(str(replica))
        set_budget(base, processor, model_config)
        collator = Collator(processor, ChatFormat(processor, model.generation_config), base.data.max_length,
                            getattr(model_config, "image_token_id", None))
        for method in PROMPT_METHODS:
            for k in CONTEXT_LENGTHS:
                cfg = dataclasses.replace(base, method=method, data=dataclasses.replace(
                    base.data, contexts=[k], max_train_episodes=None, val_episodes=0))
                train, _ = build_examples(cfg, ds, Grid(cfg.data.grid.rows, cfg.data.grid.cols))
                counts = count_tokens(train, collator)
                row = {"method": method, "context": k, "examples": len(counts)}
                for key in ("image", "text", "answer", "total"):
                    values = [c[key] for c in counts]
                    row[key] = (max(values), sum(values) / len(values))
                rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", type=Path, default=Path("../shared/reference-models/SmolVLM-256M-Instruct"))
    ap.add_argument("--dataset", default="data/naturalistic")
    ap.add_argument("--config", default="finetune_smolvlm_256m")
    args = ap.parse_args()
    rows = budgets(args.config, args.reference, args.dataset)
    print("| method | context | examples | image tokens max / mean | other prompt max / mean | answer max / mean "
          "| total max / mean |\n|---|---:|---:|---|---|---|---|")
    for r in rows:
        cells = " | ".join(f"{r[k][0]} / {r[k][1]:.0f}" for k in ("image", "text", "answer", "total"))
        print(f"| {r['method']} | {r['context']} | {r['examples']} | {cells} |")


if __name__ == "__main__":
    main()
