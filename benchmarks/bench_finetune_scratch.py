"""Does the fine-tuning pipeline learn? Train the tiny Idefics3 from scratch on CPU, score it on test participants.

Trains `configs/finetune_tiny_scratch_cpu.yaml` (full mode, random init, naturalistic train participants),
then predicts the test participants' episodes (context 2) with the trained model through `degusta predict`
(hf backend, constrained and unconstrained decoding) and with the `random` and `population_mean`
baselines, and prints one markdown table (parse rate, object accuracy, Kabsch RMSD, unregistered RMSD,
count error) for benchmarks/RESULTS.md. Also reports the untrained (zero-shot) tiny model.

Usage:
    degusta data generate naturalistic --out data/naturalistic     # once
    python benchmarks/bench_finetune_scratch.py                    # ~20-30 min on 2 busy CPU cores
    python benchmarks/bench_finetune_scratch.py --steps 20 --episodes 20 --out runs/bench_scratch_quick
    python benchmarks/bench_finetune_scratch.py --episodes 100 --reuse   # re-score a trained run only
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"


def summarize(name: str, preds, ds) -> dict:
    from degusta_learn.metrics import score_prediction

    scores = [score_prediction(ds.catalog, ds.arrangement(p.participant, p.target), p.placements, p.failed)
              for p in preds]
    parsed = [p.diagnostics.get("n_parsed", 0) / max(1, p.diagnostics.get("n_responses", 1)) for p in preds]
    rmsd = [s.rmsd for s in scores if not math.isnan(s.rmsd)]
    unreg = [s.rmsd_unregistered for s in scores if not math.isnan(s.rmsd_unregistered)]
    mean = lambda xs: sum(xs) / len(xs) if xs else float("nan")  # noqa: E731
    return {"method": name, "n": len(preds),
            "parse_rate": mean(parsed) if "n_parsed" in preds[0].diagnostics else float("nan"),
            "object_accuracy": mean([s.object_accuracy for s in scores]), "rmsd": mean(rmsd),
            "rmsd_unregistered": mean(unreg), "count_error": mean([s.count_error for s in scores]),
            "n_pred": mean([s.n_pred for s in scores])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default="data/naturalistic")
    ap.add_argument("--steps", type=int, default=None, help="override trainer.max_steps")
    ap.add_argument("--episodes", type=int, default=None, help="score only the first N test episodes")
    ap.add_argument("--out", default="runs/bench_finetune_scratch")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reuse", action="store_true", help="skip training when the run's model/ folder exists")
    args = ap.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    from degusta_learn.methods import run_predict, run_train
    from degusta_learn.scene import load_dataset, make_episodes, read_predictions, write_episodes

    out = Path(args.out)
    ds = load_dataset(args.dataset)
    overrides = [f"dataset={args.dataset}", f"trainer.run_dir={out / 'checkpoints'}", "trainer.progress_bar=false"]
    if args.steps is not None:
        overrides += [f"trainer.max_steps={args.steps}", f"trainer.val_check_interval={args.steps}"]
    t0 = time.time()
    run = out / "checkpoints" / "finetune_tiny_scratch_cpu"
    if not (args.reuse and (run / "model").is_dir()):
        run = run_train("configs/finetune_tiny_scratch_cpu.yaml", overrides)
    train_s = time.time() - t0
    episodes = make_episodes(ds, 2, "test", 0)[: args.episodes]
    ep_file = out / "episodes_test_k2.jsonl"
    write_episodes(ep_file, episodes)
    common = [f"dataset={args.dataset}", f"episodes={ep_file}"]
    hf = common + ["model.adapter=null", "model.image_size=64", "render_size=224", "decoding.max_new_tokens=512",
                   "cache='off'"]
    runs = {
        "tiny VLM, trained from scratch (constrained)": ("configs/predict_hf_tiny_zeroshot.yaml",
                                                         hf + [f"model.name={run / 'model'}"]),
        "tiny VLM, trained from scratch (unconstrained)": ("configs/predict_hf_tiny_zeroshot.yaml",
                                                           hf + [f"model.name={run / 'model'}",
                                                                 "decoding.constrained=false"]),
        "tiny VLM, untrained (constrained)": ("configs/predict_hf_tiny_zeroshot.yaml",
                                             hf + ["model.name=runs/tiny/idefics3_scratch"]),
        "population_mean": ("configs/baseline_population_mean.yaml", common),
        "random": ("configs/baseline_random.yaml", common),
    }
    rows, times = [], {}
    for i, (name, (cfg, ov)) in enumerate(runs.items()):
        t = time.time()
        path = run_predict(cfg, ov + [f"out={out / f'pred_{i}' / 'predictions.jsonl'}"])
        times[name] = time.time() - t
        rows.append(summarize(name, read_predictions(path, ds.catalog), ds))
    print(f"\ntraining: {train_s:.0f} s ({run}); {len(episodes)} test episodes (context 2), {ds.label}\n")
    print("| method | parse rate | object accuracy | Kabsch RMSD | unregistered RMSD | count error | objects/pred | predict s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['method']} | {r['parse_rate']:.3f} | {r['object_accuracy']:.3f} | {r['rmsd']:.3f} | "
              f"{r['rmsd_unregistered']:.3f} | {r['count_error']:.2f} | {r['n_pred']:.1f} | {times[r['method']]:.0f} |")


if __name__ == "__main__":
    main()
