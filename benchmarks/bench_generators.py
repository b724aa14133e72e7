"""The method ranking on both SYNTHETIC generator families: is it an artefact of the slot generator?

The naturalistic generator builds tables from slots, and so does the learned slot model; the relational
generator (docs/generators.md) builds them from placement rules relative to the table edge and to objects
already placed. This script generates both datasets into `--out` (or reuses them: a folder there that the same
generator made with the same seed), runs every non-trained method on each through `degusta predict` with its
shipped config and `--set dataset=...` (random, population_mean, copy_nearest, consensus, slot_heuristic,
collaborative, copy_context_text, oracle; with `--trained` also the learned slot model and the set transformer,
trained from `learned_cpu` / `set_transformer_cpu` on the train participants, their checkpoint chosen on the
validation participants), all at context 4 on the test split (split seed 0), and scores them with the evaluation
code of `degusta evaluate` (evaluate.scoring, evaluate.summary).

It takes no choice itself: every setting is the shipped config's (chosen on the naturalistic validation
participants; none is re-tuned for the relational data, which if anything favours the naturalistic side). It prints:

- per generator, the methods ranked by set RMSD (the headline; degenerate methods last) with 95% intervals that
  resample participants (`summarize(..., cluster="participant")`), object accuracy, Kabsch RMSD and count bias;
- Spearman's and Kendall's rank correlation (scipy.stats) between the two generators' mean set RMSD per method,
  with a 95% percentile interval from resampling each generator's test participants (independently, the two
  datasets' people are unrelated);
- every pair of methods whose order flips between the generators, with the paired, participant-clustered
  difference on each (metrics.paired_bootstrap, the test `degusta compare` reports) and whether the flip is
  significant: on both generators (a reversal), on one, or on neither (within noise);
- the same paired difference for each pair of neighbours in the first generator's ranking, on both generators
  (an order that holds but is not told apart on one of them).

Usage:
    python benchmarks/bench_generators.py --out runs/bench_generators              # ~30 s on a free core
    python benchmarks/bench_generators.py --out runs/bench_generators --trained    # + two trainings per generator
    python benchmarks/bench_generators.py --out runs/bench_generators --legacy     # naturalistic's legacy tables
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, set before numpy is imported

import argparse  # noqa: E402
import itertools  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import asdict  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from degusta_learn.errors import DegustaError  # noqa: E402
from degusta_learn.evaluate.scoring import score_file  # noqa: E402
from degusta_learn.evaluate.summary import rank_methods, summarize  # noqa: E402
from degusta_learn.methods import run_predict, run_train  # noqa: E402
from degusta_learn.metrics import paired_bootstrap  # noqa: E402
from degusta_learn.scene import load_dataset, make_episodes  # noqa: E402
from degusta_learn.shipped import shipped_config  # noqa: E402
from degusta_learn.synth import RelationalOptions, generate_dataset  # noqa: E402

GENERATORS = ("naturalistic", "relational")
METHODS = {"random": "baseline_random", "population_mean": "baseline_population_mean",
           "copy_nearest": "baseline_copy_nearest", "consensus": "baseline_consensus",
           "slot_heuristic": "baseline_slot_heuristic", "collaborative": "baseline_collaborative",
           "copy_context_text": "baseline_copy_context_text", "oracle": "oracle"}
TRAINED = {"learned": ("learned_cpu", "learned_predict"),
           "set_transformer": ("set_transformer_cpu", "set_transformer_predict")}
CONTEXT, SPLIT, SPLIT_SEED = 4, "test", 0
ALPHA = 0.05


LEGACY = "naturalistic_legacy"
"""`--legacy`: the naturalistic generator's legacy tables (before every table kept synth/plausible.py's rules)."""


def generator_names(legacy: bool) -> tuple[str, str]:
    """The two datasets compared: the naturalistic one (its legacy tables with `--legacy`) and relational."""
    return (LEGACY if legacy else GENERATORS[0]), GENERATORS[1]


def dataset(out: Path, name: str, seed: int) -> Path:
    """out/data/<name>: reused when the same generator made it with `seed` and its default options, else generated
    (replacing only a dataset degusta generated). `LEGACY` is the naturalistic generator with `legacy` on."""
    folder = out / "data" / name
    generator, plausible = ("naturalistic", False) if name == LEGACY else (name, True)
    options = asdict(RelationalOptions()) if name == "relational" else None
    try:
        meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
        if (meta.get("generator"), meta.get("seed"), meta.get("options"), meta.get("plausible", False)) \
                == (f"degusta_learn.synth.{generator}", seed, options, plausible):
            return folder
    except (OSError, ValueError):
        pass
    return generate_dataset(generator, folder, seed=seed, overwrite=folder.exists(),
                            legacy=name == LEGACY)


def _quiet(*_args, **_kwargs) -> None:
    pass


def predict(config: str, data: Path, out: Path, extra: tuple = ()) -> Path:
    """`degusta predict --config CONFIG --set dataset=DATA --set out=OUT ...` at the benchmark's episodes."""
    return run_predict(shipped_config(config), [f"dataset={data}", f"out={out}", f"context={CONTEXT}", f"split={SPLIT}",
                                f"seed={SPLIT_SEED}", *extra], log=_quiet)


def train(config: str, data: Path, run_dir: Path, name: str, seed: int) -> Path:
    """`degusta train --config CONFIG --set dataset=DATA --set trainer.seed=SEED` into run_dir/name; a finished run
    (best.ckpt) is reused."""
    if not (run_dir / name / "best.ckpt").is_file():
        run_train(shipped_config(config), [f"dataset={data}", f"seed={SPLIT_SEED}", f"trainer.run_dir={run_dir}",
                           f"trainer.run_name={name}", "trainer.progress_bar=false", f"trainer.seed={seed}"],
                  log=_quiet)
    return run_dir / name


def relabel(path: Path, method: str) -> Path:
    """Name every prediction of `path` `method` (one row per training seed in the tables)."""
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    path.write_text("".join(json.dumps({**r, "method": method}) + "\n" for r in rows))
    return path


def run_methods(name: str, data: Path, out: Path, trained: bool, seeds: tuple[int, ...] = (0,)) -> list[Path]:
    """Every method's predictions file on one generator's data (timed on stderr)."""
    pred_dir = out / "predictions" / name
    pred_dir.mkdir(parents=True, exist_ok=True)
    files = []
    for method, config in METHODS.items():
        start = time.perf_counter()
        files.append(predict(config, data, pred_dir / f"{method}.jsonl"))
        print(f"  {name} {method}: {time.perf_counter() - start:.1f} s", file=sys.stderr)
    if trained:
        for (method, (train_config, predict_config)), seed in itertools.product(TRAINED.items(), seeds):
            start = time.perf_counter()
            run = train(train_config, data, out / "runs", f"{train_config}_{name}_s{seed}", seed)
            label = f"{method}_s{seed}" if len(seeds) > 1 else method
            files.append(relabel(predict(predict_config, data, pred_dir / f"{label}.jsonl", (f"checkpoint={run}",)),
                                 label))
            print(f"  {name} {label} (trained): {time.perf_counter() - start:.1f} s", file=sys.stderr)
    return files


def score(data: Path, files: list[Path]) -> list:
    """The per-episode rows of `degusta evaluate` for these predictions files on the benchmark's episodes."""
    ds = load_dataset(data)
    episodes = {e.id: e for e in make_episodes(ds, CONTEXT, SPLIT, SPLIT_SEED)}
    rows = []
    for path in files:
        try:
            rows += score_file(ds, path, episodes, note=lambda text: print(f"note: {text}", file=sys.stderr))
        except DegustaError as e:
            raise SystemExit(str(e)) from None
    return rows


def _ci(stat: dict, digits: int = 3) -> str:
    if stat is None or stat.get("mean") is None:
        return "-"
    if stat.get("ci_low") is None:
        return f"{stat['mean']:.{digits}f}"
    return f"{stat['mean']:.{digits}f} [{stat['ci_low']:.{digits}f}, {stat['ci_high']:.{digits}f}]"


def ranked_table(summary: dict) -> list[str]:
    lines = ["| rank | method | set RMSD [95% CI] | object accuracy | Kabsch RMSD | count bias |",
             "|---:|---|---:|---:|---:|---:|"]
    for k, method in enumerate(rank_methods(summary), start=1):
        s = summary[method]
        mark = " (degenerate)" if s.get("degenerate") else ""
        lines.append(f"| {k} | {method}{mark} | {_ci(s['set_rmsd'])} | {_ci(s['object_accuracy'])} | "
                     f"{_ci(s['rmsd'])} | {_ci(s.get('count_bias'), 2)} |")
    return lines


def participant_table(rows: list, methods: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(M, P) per-participant sums of set RMSD per method and (P,) episode counts, participants sorted."""
    people = sorted({r.participant for r in rows})
    col = {p: j for j, p in enumerate(people)}
    row = {m: i for i, m in enumerate(methods)}
    sums, counts = np.zeros((len(methods), len(people))), np.zeros((len(methods), len(people)))
    for r in rows:
        if r.method in row:
            sums[row[r.method], col[r.participant]] += r.set_rmsd
            counts[row[r.method], col[r.participant]] += 1
    if not (counts == counts[:1]).all():
        raise SystemExit("the methods were not scored on the same episodes")
    return sums, counts[0]


def rank_correlations(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(Spearman's rho, Kendall's tau-b) between two vectors of per-method scores."""
    return float(stats.spearmanr(a, b).statistic), float(stats.kendalltau(a, b).statistic)


def bootstrap_correlations(tables: list[tuple[np.ndarray, np.ndarray]], n_resamples: int, seed: int) -> np.ndarray:
    """(n_resamples, 2) Spearman and Kendall between the generators' per-method means, each generator's
    participants resampled with replacement (independently: the datasets' people are unrelated)."""
    rng = np.random.default_rng(seed)
    means = []
    for sums, counts in tables:
        w = rng.multinomial(len(counts), np.full(len(counts), 1 / len(counts)), size=n_resamples)  # (B, P)
        means.append((w @ sums.T) / (w @ counts)[:, None])  # (B, M)
    return np.array([rank_correlations(x, y) for x, y in zip(*means)])


def paired(rows: list, a: str, b: str, n_resamples: int, seed: int) -> dict:
    """Paired, participant-clustered set RMSD difference mean(b - a) on one generator's episodes."""
    by = {m: {r.episode: r for r in rows if r.method == m} for m in (a, b)}
    eps = sorted(by[a])
    return paired_bootstrap([by[b][e].set_rmsd for e in eps], [by[a][e].set_rmsd for e in eps],
                            n_resamples=n_resamples, seed=seed, clusters=[by[a][e].participant for e in eps])


def flips(summaries: dict, rows: dict, methods: list[str], n_resamples: int, seed: int,
          names: tuple[str, str] = GENERATORS) -> list[dict]:
    """Pairs of methods whose set RMSD order differs between the two datasets `names`, with each one's paired,
    participant-clustered difference mean(b - a) (a: better on the first)."""
    first, second = names
    mean = {g: {m: summaries[g][m]["set_rmsd"]["mean"] for m in methods} for g in names}
    out = []
    for a, b in itertools.combinations(methods, 2):
        if mean[first][a] > mean[first][b]:
            a, b = b, a
        if not mean[second][a] > mean[second][b]:
            continue
        entry = {"a": a, "b": b, **{g: paired(rows[g], a, b, n_resamples, seed) for g in names}}
        significant = [entry[g]["p_value"] < ALPHA for g in names]
        entry["verdict"] = ("significant on both (a reversal)" if all(significant) else
                            f"significant on {names[significant.index(True)]} only" if any(significant) else
                            "significant on neither (within noise)")
        out.append(entry)
    return out


def _diff(d: dict) -> str:
    p = "p < 0.001" if d["p_value"] < 0.001 else f"p {d['p_value']:.3f}"
    return f"{d['diff']:+.3f} [{d['lo']:+.3f}, {d['hi']:+.3f}], {p}"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for the datasets, predictions and trained runs")
    ap.add_argument("--seed", type=int, default=0, help="data seed of both generators")
    ap.add_argument("--trained", action="store_true", help="also train and score learned and set_transformer")
    ap.add_argument("--train-seeds", type=int, nargs="+", default=[0], help="training seeds (--trained): one row each")
    ap.add_argument("--n-bootstrap", type=int, default=2000)
    ap.add_argument("--legacy", action="store_true",
                    help=f"the naturalistic generator's legacy tables ({LEGACY}) in the default's place")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    names = generator_names(args.legacy)
    summaries, rows = {}, {}
    for name in names:
        data = dataset(args.out, name, args.seed)
        rows[name] = score(data, run_methods(name, data, args.out, args.trained, tuple(args.train_seeds)))
        summaries[name] = summarize(rows[name], n_bootstrap=args.n_bootstrap, seed=0, cluster="participant")
    n_people = len({r.participant for r in rows[names[0]]})
    n_eps = len({r.episode for r in rows[names[0]]})
    print(f"# Method ranking on both generators (SYNTHETIC data, seed {args.seed}; test split, split seed "
          f"{SPLIT_SEED}, context {CONTEXT}: {n_eps} episodes of {n_people} participants per generator)\n")
    print("Every setting is the shipped config's, chosen on the naturalistic validation participants (trained "
          "models: checkpoint chosen on each generator's validation participants); the benchmark chooses nothing. "
          f"Intervals: 95% percentile bootstrap over participants, {args.n_bootstrap} resamples.\n")
    for name in names:
        print(f"## {name}\n")
        print("\n".join(ranked_table(summaries[name])) + "\n")
    methods = rank_methods(summaries[names[0]])
    degenerate = [f"{m} ({g})" for g in names for m in methods if summaries[g][m].get("degenerate")]
    tables = [participant_table(rows[g], methods) for g in names]
    rho, tau = rank_correlations(*[sums.sum(1) / counts.sum() for sums, counts in tables])
    boot = bootstrap_correlations(tables, args.n_bootstrap, seed=0)
    lo, hi = np.percentile(boot, [100 * ALPHA / 2, 100 * (1 - ALPHA / 2)], axis=0)
    print(f"## Rank agreement ({len(methods)} methods, mean set RMSD)\n")
    print(f"- Spearman's rho {rho:.3f} [{lo[0]:.3f}, {hi[0]:.3f}]")
    print(f"- Kendall's tau {tau:.3f} [{lo[1]:.3f}, {hi[1]:.3f}]")
    print(f"- intervals: each generator's {n_people} test participants resampled ({args.n_bootstrap} times)")
    if degenerate:
        print(f"- degenerate (ranked last in the tables, by mean in the correlation): {', '.join(degenerate)}")
    found = flips(summaries, rows, methods, args.n_bootstrap, seed=0, names=names)
    print(f"\n## Pairs whose order flips between {names[0]} and {names[1]}\n")
    if not found:
        print("None: every pair of methods is in the same order on both generators.")
    else:
        print(f"a is ahead on {names[0]}, b on {names[1]}; difference = set RMSD of b - a (paired, "
              "participants resampled): > 0 means a ahead.\n")
        print(f"| a | b | {names[0]} | {names[1]} | flip |")
        print("|---|---|---:|---:|---|")
        for f in found:
            print(f"| {f['a']} | {f['b']} | {_diff(f[names[0]])} | {_diff(f[names[1]])} | {f['verdict']} |")
    print(f"\n## Neighbours in the {names[0]} ranking, on both generators\n")
    print("difference = set RMSD of the lower-ranked b - a (paired, participants resampled); > 0: a ahead.\n")
    print(f"| a | b | {names[0]} | {names[1]} |")
    print("|---|---|---:|---:|")
    for a, b in zip(methods, methods[1:]):
        print(f"| {a} | {b} | " + " | ".join(_diff(paired(rows[g], a, b, args.n_bootstrap, 0)) for g in names)
              + " |")
    print(f"\n({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
