"""Perception of the tiny base VLM on freshly rendered held-out scenes and marked-object sheets.

Scores the shipped base `tiny_vlm_base` (or --model) on perception questions drawn from a seed the model never
trained or validated on: object-set F1 (type and id), exact cell set per named object, direction
accuracy (plates left out: their direction cannot be seen), GoMO mark-id accuracy, cell IoU and the
parse rate, overall and by the number of scenes in the prompt. Constrained decoding, greedy, one answer
per question. Apart from the perception scores, `--transcribe` questions (another seed) ask for one scene's list
written in the prompt (`transcribe`: copying, not seeing): object F1 and how often the list has the written length.
Also plots the pretraining validation curve recorded in the model folder (the shipped base's: the docs' figure
docs/images/base_perception_curve.png; any other model's: OUT/perception_curve.png).

Usage:
    python benchmarks/bench_perception.py                               # 600 questions, ~10 CPU minutes
    python benchmarks/bench_perception.py --n 60 --out runs/bench_perception_quick
    python benchmarks/bench_perception.py --write-card                  # also perception.json + model card
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"

BENCH_SEED = 2_000_003  # training uses seed 0 and validation seed 1,000,003: never these examples
SHIPPED_BASE = "tiny_vlm_base"
SHIPPED_CURVE = "docs/images/base_perception_curve.png"  # its figure in the docs


def plot_curve(curve: list[dict], out: Path) -> Path | None:
    """Validation perception scores against training steps (PNG)."""
    if not curve:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=120)
    steps = [r["step"] for r in curve]
    for key, label in (("object_f1", "object-set F1"), ("cells_exact", "exact cell set"),
                       ("direction", "direction (no plates)"), ("mark_id", "GoMO mark id")):
        ax.plot(steps, [r.get(f"val/{key}", float("nan")) for r in curve], marker="o", ms=3, label=label)
    ax.axhline(0.9, color="grey", lw=0.8, ls="--", label="target 0.9")
    ax.set(xlabel="training step", ylabel="validation score", ylim=(0, 1.02),
           title="Tiny base VLM: perception during pretraining (held-out validation)")
    ax.legend(fontsize=8, loc="upper left", ncol=2)  # the curves end low on the right
    ax.grid(alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def curve_path(model: str, out: str) -> str:
    """Where the training curve goes by default: the docs' figure for the shipped base, else under `out` (a pilot
    model's curve never replaces the shipped base's figure)."""
    from degusta_learn.shipped import is_shipped_base

    if is_shipped_base(model):
        return SHIPPED_CURVE
    return str(Path(out) / "perception_curve.png")


def finite_or_null(value):
    """`value` with every NaN or infinite float (a score of a task no question asked) as None: JSON null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_or_null(v) for k, v in value.items()}
    if isinstance(value, list):
        return [finite_or_null(v) for v in value]
    return value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=SHIPPED_BASE)
    ap.add_argument("--n", type=int, default=600, help="questions (>= 500 held-out images by default)")
    ap.add_argument("--transcribe", type=int, default=100, help="transcribe questions, scored apart (0: none)")
    ap.add_argument("--seed", type=int, default=BENCH_SEED)
    ap.add_argument("--on-repeat", default="stop", choices=("stop", "skip", "next"),
                    help="a list item naming an object again (vlm/generate.py): stop, the decoding every recorded "
                         "perception score used (predict's default is skip)")
    ap.add_argument("--out", default="runs/bench_perception")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--write-card", action="store_true", help="write perception.json into the model folder "
                    "and re-render its model card")
    ap.add_argument("--plot", default=None, help="the training curve's PNG (default: the docs' figure for the "
                    "shipped base, OUT/perception_curve.png for any other model, so a pilot never replaces it)")
    args = ap.parse_args()
    args.plot = args.plot or curve_path(args.model, args.out)

    import torch

    torch.set_num_threads(args.threads)
    from degusta_learn.files.jsonio import atomic_write_json, read_json
    from degusta_learn.pretrain.export import BASE_META, PERCEPTION, write_card
    from degusta_learn.pretrain.score import score_answer, summarize
    from degusta_learn.pretrain.tasks import PerceptionExamples, TaskMix
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import default_catalog, default_tables
    from degusta_learn.task.grammar import AnswerGrammar
    from degusta_learn.vlm.generate import generate_answers
    from degusta_learn.vlm.inputs import set_image_budget
    from degusta_learn.vlm.load import load_vlm

    folder = Path(args.model)
    meta = read_json(folder / BASE_META)
    model, processor = load_vlm(str(folder), device="cpu", dtype="float32")
    set_image_budget(processor, model.config, meta["image_size"])
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    grid = Grid(meta["grid"]["rows"], meta["grid"]["cols"])
    examples = PerceptionExamples(catalog, tables, grid, meta["render_size"], args.seed, args.n,
                                  TaskMix(lists=0.7, describe=0.1, gomo=0.2), block=1)
    copies = PerceptionExamples(catalog, tables, grid, meta["render_size"], args.seed + 1, args.transcribe,
                                TaskMix(lists=0, describe=0, gomo=0, transcribe=1), block=1)
    grammar = AnswerGrammar("grid", catalog, grid)
    t0 = time.time()

    def answer(ex) -> dict:
        located = ex.meta["task"] != "gomo"
        text = generate_answers(model, processor, ex.prompt, n=1, temperature=0.0,
                                max_new_tokens=320 if located else 8, constrained=located,
                                grammar=grammar if located else None, on_repeat=args.on_repeat)[0].text
        return {**score_answer(ex, text, catalog, grid), "scenes": ex.meta.get("scenes", 1)}

    rows = []
    for i in range(len(examples)):
        rows.append(answer(examples[i]))
        if (i + 1) % 100 == 0:
            print(f"{i + 1}/{len(examples)} questions, {time.time() - t0:.0f} s", flush=True)
    copied = [answer(copies[i]) for i in range(len(copies))]
    scores = summarize(rows)
    by_scenes = {str(k): summarize([r for r in rows if r["task"] == "list" and r["scenes"] == k])
                 for k in (1, 2, 3, 4)}
    n_images = sum(r.get("scenes", 1) for r in rows)
    result = {"model": str(folder), "seed": args.seed, "n_questions": len(rows), "n_images": n_images,
              "seconds": round(time.time() - t0, 1), "scores": scores,
              "object_f1_by_scenes": {k: v["object_f1"] for k, v in by_scenes.items()},
              "cells_exact_by_scenes": {k: v["cells_exact"] for k, v in by_scenes.items()}}
    if copied:
        result["transcribe"] = {"n": len(copied), "object_f1": summarize(copied)["transcribe_f1"],
                                "length_exact": sum(r["tp"] + r["fp"] == r["n_truth"] for r in copied) / len(copied)}
    out = Path(args.out)
    result = finite_or_null(result)  # a task with no questions scores NaN, which strict JSON readers refuse
    atomic_write_json(out / "perception.json", result)
    print(f"\n{len(rows)} questions about {n_images} held-out images ({result['seconds']:.0f} s):\n")
    print("| object-set F1 | exact cell set | direction (no plates) | GoMO mark id | cell IoU | parse rate |")
    print("|---:|---:|---:|---:|---:|---:|")
    print("| " + " | ".join(f"{scores[k]:.3f}" for k in ("object_f1", "cells_exact", "direction", "mark_id",
                                                          "cell_iou", "parse_rate")) + " |")
    print("\nobject-set F1 by scenes in the prompt:", json.dumps(
        {k: None if v is None else round(v, 3) for k, v in result["object_f1_by_scenes"].items()}))
    if copied:
        print(f"transcribe ({len(copied)} lists written in the prompt, copied): object F1 "
              f"{result['transcribe']['object_f1']:.3f}, written length {result['transcribe']['length_exact']:.3f}")
    plot = plot_curve(meta.get("validation_curve") or [], Path(args.plot))
    if plot:
        print(f"training curve: {plot}")
    if args.write_card:
        atomic_write_json(folder / PERCEPTION, result)
        print(f"wrote {folder / PERCEPTION} and {write_card(folder)}")


if __name__ == "__main__":
    main()
