"""Zero-shot vs LoRA-fine-tuned vs fully fine-tuned tiny base VLM on the preference task, beside the baselines.

On the SYNTHETIC naturalistic default's test split (40 held-out participants, context 4, 200 episodes,
the same episodes for every method): the tiny base zero-shot (`configs/predict_hf_base_zeroshot.yaml`),
the base LoRA-fine-tuned by `configs/finetune_tiny_base_cpu.yaml` (timed), the base fully fine-tuned with the
same steps (`lora.mode=full`), and the heuristic baselines and the oracle. Prints one markdown table
(object accuracy, Kabsch RMSD, set RMSD, count error, objects per answer, few-matched share), the paired
bootstrap tests the issue asks for (fine-tuned vs population_mean on Kabsch RMSD, fine-tuned minus
zero-shot), the ratio to copy_nearest, and plots both runs' learning curves (validation RMSD, set
RMSD and parse rate against steps: docs/images/vlm_learning_curve.png for the documented run, OUT/learning_curve.png
for a run with another base, fewer episodes or overrides).

Usage:
    python benchmarks/bench_vlm.py                         # ~35 CPU minutes: 2 fine-tunings + 3 x 200 answers
    python benchmarks/bench_vlm.py --episodes 40 --modes lora --out runs/bench_vlm_quick
    python benchmarks/bench_vlm.py --reuse                 # re-score: keep finished runs and predictions
    python benchmarks/bench_vlm.py --modes lora --set trainer.max_steps=261 --out runs/bench_vlm_3ep
        # --set: fine-tuning overrides (here three epochs instead of one)
    python benchmarks/bench_vlm.py --modes lora --reuse --predict-set decoding.n=5 --predict-set decoding.temperature=1.0 --out OUT
        # --predict-set: the fine-tuned row's predict overrides (here 5 sampled answers aggregated)
    python benchmarks/bench_vlm.py --modes lora --seeds 0 1 --out OUT
        # one fine-tune per training seed (`trainer.seed`; the participant split stays): a row per seed, and a
        # row of each episode's mean over the seeds, which the paired tests use (a seed alone moved object
        # accuracy by 0.035: experiments/tiny_base_log.md point 32)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
import warnings
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"

BASELINES = ("random", "population_mean", "copy_nearest", "consensus", "oracle")


def plot_curve(runs: dict[str, Path], out: Path) -> Path | None:
    """Validation Kabsch RMSD, set RMSD, object accuracy and parse rate against steps, one panel per run (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from degusta_learn.training import validation_curve

    curves = {name: rows for name, run_dir in runs.items() if (rows := validation_curve(run_dir, "val/rmsd"))}
    if not curves:
        return None
    fig, axes = plt.subplots(1, len(curves), figsize=(5.2 * len(curves), 3.6), dpi=120, sharey=True, squeeze=False)
    for ax, (name, rows) in zip(axes[0], curves.items()):
        steps = [r["step"] + 1 for r in rows]
        for key, label in (("val/set_rmsd", "set RMSD"), ("val/rmsd", "Kabsch RMSD (paper)"),
                           ("val/object_accuracy", "object accuracy")):
            if key in rows[0]:
                ax.plot(steps, [r.get(key, math.nan) for r in rows], marker="o", ms=4, label=label)
        ax.set(xlabel="fine-tuning step", title=f"{name} (val participants, k=4)", xlim=(0, max(steps) * 1.05))
        ax2 = ax.twinx()
        ax2.plot(steps, [r.get("val/parse_rate", math.nan) for r in rows], color="grey", ls="--", marker="s", ms=3,
                 label="parse rate")
        ax2.set(ylim=(0, 1.05))
        ax2.set_ylabel("parse rate" if ax is axes[0][-1] else "")
        lines, labels = (a + b for a, b in zip(ax.get_legend_handles_labels(), ax2.get_legend_handles_labels()))
        ax.legend(lines, labels, fontsize=8, loc="center right")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("validation score")
    fig.suptitle("Tiny base VLM fine-tuned on MOGMA", fontsize=11)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def run_name(mode: str, seed: int) -> str:
    """A fine-tune's row and run folder: tiny_vlm_lora for training seed 0 (as before seeds), else ..._s<seed>."""
    return f"tiny_vlm_{mode}" if seed == 0 else f"tiny_vlm_{mode}_s{seed}"


def curve_path(args) -> str:
    """Where the learning curve goes by default: the docs' figure for the documented run (the shipped base, all test
    episodes, no config overrides), else under --out (a pilot's curve never replaces the docs' figure)."""
    from degusta_learn.shipped import is_shipped_base

    documented = (is_shipped_base(args.base) and args.episodes is None
                  and not args.overrides and not args.predict_overrides)
    return "docs/images/vlm_learning_curve.png" if documented else str(Path(args.out) / "learning_curve.png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default="data/naturalistic")
    ap.add_argument("--base", default="tiny_vlm_base")
    ap.add_argument("--out", default="runs/bench_vlm")
    ap.add_argument("--episodes", type=int, default=None, help="only the first N test episodes (default: all 200)")
    ap.add_argument("--modes", nargs="+", default=["lora", "full"], choices=["lora", "full"])
    ap.add_argument("--full-lr", type=float, default=5e-4, help="learning rate of full fine-tuning")
    ap.add_argument("--reuse", action="store_true", help="keep finished fine-tuning runs and prediction files")
    ap.add_argument("--plot", default=None, help="the learning curve's PNG (default: the docs' figure for a run of "
                    "the shipped base with no overrides, OUT/learning_curve.png for any other run)")
    ap.add_argument("--val-every", type=int, default=29,
                    help="fine-tuning steps between validations (the learning curve's points; 29: three an epoch)")
    ap.add_argument("--predict-set", dest="predict_overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="a predict config override for the fine-tuned rows, e.g. decoding.n=5 (repeatable)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="a fine-tuning config override for both runs, e.g. trainer.max_steps=261 (repeatable)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0],
                    help="training seeds (trainer.seed), one fine-tune each; more than one adds a mean-over-seeds row")
    args = ap.parse_args()
    if len(set(args.seeds)) != len(args.seeds) or any(s < 0 for s in args.seeds):
        ap.error("--seeds: distinct integers >= 0")
    if any(o.split("=")[0].strip() == "trainer.seed" for o in args.overrides):
        ap.error("--set trainer.seed: give training seeds with --seeds")
    args.plot = args.plot or curve_path(args)

    import numpy as np

    from degusta_learn.methods import get_method, run_predict, run_train
    from degusta_learn.metrics import SET_PENALTY, bootstrap_ci, paired_bootstrap, score_many
    from degusta_learn.scene import load_dataset, make_episodes, read_predictions, write_episodes
    from degusta_learn.synth import generate_dataset

    if not (Path(args.dataset) / "arrangements.jsonl").is_file():
        generate_dataset("naturalistic", args.dataset, seed=0)
    ds = load_dataset(args.dataset)
    out = Path(args.out)
    episodes = make_episodes(ds, 4, "test", 0)[: args.episodes]
    ep_file = out / "episodes.jsonl"
    write_episodes(ep_file, episodes)
    common = [f"dataset={args.dataset}", f"episodes={ep_file}"]
    preds, seconds = {}, {}

    def hf(name: str, config: str, extra: list[str]) -> None:
        path = out / "predictions" / f"{name}.jsonl"
        if not (args.reuse and path.is_file()):
            t0 = time.time()
            run_predict(config, common + [f"out={path}", f"model.name={args.base}"] + extra)
            seconds[f"predict {name}"] = time.time() - t0
        preds[name] = read_predictions(path, ds.catalog)

    hf("tiny_vlm_zeroshot", "configs/predict_hf_base_zeroshot.yaml", [])
    for mode, seed in [(mode, seed) for mode in args.modes for seed in args.seeds]:
        name = run_name(mode, seed)
        run_dir = out / "checkpoints" / name
        extra = [f"lora.mode={mode}", f"optim.lr={args.full_lr}"] if mode == "full" else []
        if not (args.reuse and (run_dir / ("adapter" if mode == "lora" else "model")).is_dir()):
            t0 = time.time()
            run_train("configs/finetune_tiny_base_cpu.yaml", [f"dataset={args.dataset}", f"model.name={args.base}",
                                                          f"trainer.run_dir={out / 'checkpoints'}",
                                                          f"trainer.run_name={name}", "trainer.progress_bar=false",
                                                          f"trainer.val_check_interval={args.val_every}",
                                                          f"trainer.seed={seed}"]
                      + extra + args.overrides)
            seconds[f"fine-tune {name}"] = time.time() - t0
        if mode == "lora":
            hf(name, "configs/predict_hf_base_finetuned.yaml",
               [f"model.adapter={run_dir / 'adapter'}"] + args.predict_overrides)
        else:
            hf(name, "configs/predict_hf_base_zeroshot.yaml",
               [f"model.name={run_dir / 'model'}"] + args.predict_overrides)
            preds[name] = read_predictions(out / "predictions" / f"{name}.jsonl", ds.catalog)
    for name in BASELINES:
        spec = get_method(name)
        cfg = spec.config_cls(method=name, dataset=args.dataset, out="", split="test")
        preds[name] = spec.run(cfg, ds, episodes)

    order = [e.id for e in episodes]
    gts = [ds.arrangement(e.participant, e.target) for e in episodes]
    keys = ("object_accuracy", "rmsd", "set_rmsd", "count_error", "n_pred", "n_matched")
    cols = {}  # name -> metric -> one value per episode
    for name, ps in preds.items():
        by = {p.episode: p for p in ps}
        scored = score_many(ds.catalog, gts, [by[i] for i in order])
        cols[name] = {k: np.array([getattr(s, k) for s in scored], dtype=float) for k in keys}
        cols[name]["few"] = (cols[name]["n_matched"] <= 2).astype(float)
        cols[name]["failed"] = np.array([by[i].failed for i in order], dtype=float)
    rows = {mode: run_name(mode, args.seeds[0]) for mode in args.modes}  # the row each mode's tests use
    if len(args.seeds) > 1:  # each episode's mean over the seeds (nan where no seed matched an object)
        for mode in args.modes:
            rows[mode] = f"tiny_vlm_{mode} (mean of seeds {','.join(map(str, args.seeds))})"
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-nan episodes stay nan
                cols[rows[mode]] = {k: np.nanmean([cols[run_name(mode, s)][k] for s in args.seeds], axis=0)
                                    for k in cols[run_name(mode, args.seeds[0])]}
    col = lambda name, key: cols[name][key]  # noqa: E731

    print(f"\n# {ds.label}: test split, context 4, {len(episodes)} episodes; set RMSD c = {SET_PENALTY}\n")
    print("| method | object accuracy | Kabsch RMSD (paper) | set RMSD | count error | objects / answer | "
          "<=2 matched | failed |")
    print("|---|---|---|---|---:|---:|---:|---:|")
    summary = {}
    table = []
    for name in preds:  # each mean-over-seeds row right after its mode's last seed
        table.append(name)
        table += [rows[m] for m in args.modes if len(args.seeds) > 1 and name == run_name(m, args.seeds[-1])]
    for name in table:
        acc, rmsd, srmsd = (bootstrap_ci(col(name, k)) for k in ("object_accuracy", "rmsd", "set_rmsd"))
        n_pred = col(name, "n_pred")
        few, failed = float(np.mean(col(name, "few"))), float(np.mean(col(name, "failed")))
        summary[name] = {"object_accuracy": acc, "rmsd": rmsd, "set_rmsd": srmsd,
                         "count_error": float(np.mean(col(name, "count_error"))), "objects": float(n_pred.mean()),
                         "few_matched": few, "failed": failed}
        f3 = lambda t: f"{t[0]:.3f} [{t[1]:.3f}, {t[2]:.3f}]"  # noqa: E731
        print(f"| {name} | {f3(acc)} | {f3(rmsd)} | {f3(srmsd)} | {summary[name]['count_error']:.2f} | "
              f"{n_pred.mean():.1f} | {few:.2f} | {failed:.2f} |")

    print("\nPaired bootstrap over the same episodes (difference a - b, 95% interval, two-sided p):\n")
    print("| a | b | metric | a - b | 95% interval | p |")
    print("|---|---|---|---:|---|---:|")
    tests = {}
    pairs = [(rows[m], b) for b in ("population_mean", "tiny_vlm_zeroshot", "copy_nearest") for m in args.modes]
    if {"lora", "full"} <= set(args.modes):
        pairs.append((rows["lora"], rows["full"]))
    for a, b in pairs:
        for key in ("rmsd", "set_rmsd", "object_accuracy"):
            t = paired_bootstrap(col(a, key), col(b, key), n_resamples=10000)
            tests[f"{a} - {b} {key}"] = t
            print(f"| {a} | {b} | {key} | {t['diff']:+.4f} | [{t['lo']:+.4f}, {t['hi']:+.4f}] | {t['p_value']:.4f} |")
    for m in args.modes:
        ratio = summary[rows[m]]["rmsd"][0] / summary["copy_nearest"]["rmsd"][0]
        print(f"\n{rows[m]}: Kabsch RMSD / copy_nearest = {ratio:.2f} (goal <= 1.15)")
        if len(args.seeds) > 1:  # how far apart the seeds' runs are: the spread a one-run difference sits in
            spread = {k: np.ptp([np.nanmean(col(run_name(m, s), k)) for s in args.seeds])
                      for k in ("object_accuracy", "rmsd", "set_rmsd", "count_error")}
            print(f"tiny_vlm_{m}: spread over seeds (max - min): "
                  + ", ".join(f"{k} {v:.3f}" for k, v in spread.items()))
    print("\nseconds:", json.dumps({k: round(v) for k, v in seconds.items()}))
    plot = plot_curve({("LoRA" if m == "lora" else "full fine-tuning"): out / "checkpoints" / run_name(m, args.seeds[0])
                       for m in args.modes}, Path(args.plot))
    if plot:
        print(f"learning curve: {plot}")
    (out / "results.json").write_text(json.dumps({"summary": summary, "tests": tests, "seconds": seconds},
                                                 indent=1, default=lambda x: None if isinstance(x, float) and
                                                 math.isnan(x) else x))


if __name__ == "__main__":
    from degusta_learn.errors import DegustaError

    try:
        main()
    except DegustaError as e:  # a config or data mistake: one line, as `degusta` gives it
        raise SystemExit(f"bench_vlm: {e}") from None
