"""`degusta quickstart`: the main job on the embedded default, on a 2-core CPU in about 5 minutes.

Usage:
    degusta quickstart                      # everything under ./quickstart/
    degusta quickstart --out runs/qs --small  # a reduced size that finishes in a couple of minutes (CI)

Steps (each prints what it does; a re-run reuses what an interrupted run finished):
  1. generate the SYNTHETIC naturalistic dataset;
  2. pick the episodes: 20 test participants, one target trial each, at context 0, 2 and 4 (60);
  3. train the learned slot model (configs/learned_cpu.yaml, about 2 minutes);
  4. LoRA-fine-tune the shipped tiny base VLM (`tiny_vlm_base`, package data of every install, pretrained here on
     perception only; configs/finetune_tiny_base_cpu.yaml cut to QUICK_FINETUNE: half an epoch, ~3 minutes) on
     the train participants (with --small, four steps: the pipeline, not a result);
  5. compare heuristic baselines, the oracle, the learned model, and that VLM zero-shot and fine-tuned
     through the `hf` backend (plus zero-shot GPT-4o MOGMA with --with-api) in one report.

Every config it runs is written to `<out>/configs/` so that each step can be re-run or changed by hand.

Whose folder: quickstart writes only into a folder it created or one it wrote before. Before anything else it
checks `--out` (`files.paths.user_path`) and the marker file `MARKER` (.degusta_quickstart.json) it leaves there: a new
or empty folder is claimed (the marker is written first), a folder holding the marker is resumed, and any other
non-empty folder (or a file) is refused with one line naming --out and the folder, nothing written, so files of
the user's that happen to have the names quickstart writes (episodes.jsonl, configs/, report/ ...) are never replaced.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from degusta_learn.config import apply_overrides, dump_yaml, read_yaml
from degusta_learn.errors import DegustaError
from degusta_learn.files.atomic import atomic_write_text
from degusta_learn.files.jsonio import atomic_write_json, read_json
from degusta_learn.files.paths import shown_path, user_path
from degusta_learn.names import CONTEXT_LENGTHS
from degusta_learn.scene import Episode, load_dataset, make_episodes, participants_in, write_episodes
from degusta_learn.shipped import BASE_DIR, BASE_NAME, shipped_base, shipped_config

if TYPE_CHECKING:
    from degusta_learn.evaluate.compare import Comparison

BASELINES = ("random", "population_mean", "copy_nearest", "consensus", "oracle")

MARKER = ".degusta_quickstart.json"
"""The file quickstart writes first into its output folder: only a folder holding it (or a new or empty one) is
written into."""
MARKER_KIND = "degusta quickstart output folder"


def claim_folder(out: str | Path) -> Path:
    """The quickstart folder `out` (`~` expanded, checked), claimed: a new or empty folder gets the marker, a folder
    with our marker is taken as it is; a file, or a non-empty folder without the marker, is one DegustaError naming
    --out, and nothing is written."""
    out = user_path(out, "--out")
    if out.exists() and not out.is_dir():
        raise DegustaError(f"--out: {shown_path(out)}: exists and is not a folder; give a new or empty folder")
    entries: list[str] = []
    if out.is_dir():
        try:
            entries = sorted(p.name for p in out.iterdir())
        except OSError as e:
            raise DegustaError(f"--out: {shown_path(out)}: cannot read the folder ({e.strerror or e})") from None
    if MARKER in entries:
        try:
            marker = read_json(out / MARKER)
        except DegustaError as e:
            raise DegustaError(f"--out: {e}; give a new or empty folder") from None
        if not isinstance(marker, dict) or marker.get("kind") != MARKER_KIND:
            raise DegustaError(f"--out: {shown_path(out / MARKER)}: not the marker degusta quickstart writes (kind "
                               f"{MARKER_KIND!r}); give a new or empty folder")
        return out
    if entries:
        shown = ", ".join(repr(n) for n in entries[:3]) + (f" and {len(entries) - 3} more" if len(entries) > 3 else "")
        raise DegustaError(f"--out: {shown_path(out)}: refusing to write into a folder degusta quickstart did not "
                           f"create (it holds {shown}, and no {MARKER}): quickstart could replace files of those "
                           "names, so nothing was written; give a new or empty folder")
    atomic_write_json(out / MARKER, {"kind": MARKER_KIND, "version": 1,
                                     "note": "written by degusta quickstart, which writes only into a folder "
                                             "holding this file; delete the folder to start again"})
    return out


def _config(name: str, out_dir: Path, overrides: list[str], command: str) -> Path:
    """Take the shipped config `name` (package data), apply `overrides`, write it to `out_dir` and return that path."""
    data = apply_overrides(read_yaml(shipped_config(name)), overrides)
    path = out_dir / f"{name}.yaml"
    atomic_write_text(path, f"# {command} --config {path}\n# written by degusta quickstart from configs/{name}.yaml\n"
                      + dump_yaml(data))
    return path


def quickstart_episodes(ds, seed: int = 0, per_participant: int = 1, participants: int | None = None) -> list[Episode]:
    """One (seeded) target per test participant at each context length: the same set for every method.

    `participants` keeps only the first N test participants (sorted ids; None: all), to bound the VLM rows' time.
    """
    keep = set(participants_in(ds, "test", seed)[:participants])
    chosen = []
    for k in CONTEXT_LENGTHS:
        by_p: dict[str, list[Episode]] = {}
        for e in make_episodes(ds, k, "test", seed):
            if e.participant in keep:
                by_p.setdefault(e.participant, []).append(e)
        for p, eps in sorted(by_p.items()):
            rng = np.random.default_rng([seed, k, int.from_bytes(p.encode()[:8].ljust(8, b"\0"), "little") % 2**32])
            chosen += [eps[i] for i in sorted(rng.choice(len(eps), size=min(per_participant, len(eps)), replace=False))]
    return chosen


def run_quickstart(out: str | Path = "quickstart", small: bool = False, with_api: bool = False, log=print) -> Comparison:
    """Every step above; returns step 5's `Comparison` (the report folder and the methods that failed)."""
    from degusta_learn.evaluate.compare import CompareConfig, MethodEntry, compare
    from degusta_learn.methods import run_train
    from degusta_learn.synth import generate_dataset

    t0 = time.time()
    out = claim_folder(out)  # before anything is written: never into a folder of the user's
    cfg_dir, data_dir = out / "configs", out / "data" / "naturalistic"

    def step(msg: str) -> None:
        log(f"[quickstart {time.time() - t0:5.0f}s] {msg}")

    if not (data_dir / "arrangements.jsonl").exists():
        step("1/5 generating the SYNTHETIC naturalistic dataset")
        generate_dataset("naturalistic", data_dir, seed=0)
    else:
        step(f"1/5 reusing the dataset in {data_dir}")
    ds = load_dataset(data_dir)

    episodes = quickstart_episodes(ds, participants=4 if small else QUICK_PARTICIPANTS)
    ep_file = out / "episodes.jsonl"
    write_episodes(ep_file, episodes)
    step(f"2/5 {len(episodes)} episodes ({len(episodes) // 3} test participants, context 0/2/4) -> {ep_file}; "
         "the full test set: degusta compare --config configs/compare_naturalistic.yaml")

    runs = out / "runs"
    entries = []
    for name in BASELINES:
        cfg_name = name if name == "oracle" else f"baseline_{name}"
        path = _config(cfg_name, cfg_dir, [f"dataset={data_dir}", f"out={runs / name / 'predictions.jsonl'}"],
                       "degusta predict")
        entries.append(MethodEntry(name=name, config=str(path)))

    step("3/5 training the learned slot model (configs/learned_cpu.yaml)")
    ckpt = out / "checkpoints"
    learned = _config("learned_cpu", cfg_dir, [f"dataset={data_dir}", f"trainer.run_dir={ckpt}",
                                               "trainer.run_name=learned"] + (SMALL_LEARNED if small else QUICK_LEARNED),
                      "degusta train")
    run_dir = run_train(learned, [])
    path = _config("learned_predict", cfg_dir, [f"dataset={data_dir}", f"checkpoint={run_dir}",
                                                f"out={runs / 'learned' / 'predictions.jsonl'}"], "degusta predict")
    entries.append(MethodEntry(name="learned", config=str(path)))

    base = shipped_base()
    if base is None:  # package data of every install: only a damaged install lacks it
        raise DegustaError(f"the shipped tiny base VLM is missing from this install ({BASE_DIR}: config.json, "
                           "model.safetensors); reinstall degusta_learn")
    step(f"4/5 LoRA fine-tuning the shipped tiny base VLM ({BASE_NAME}: pretrained on perception only) on the "
         "train participants (configs/finetune_tiny_base_cpu.yaml"
         + (", a few steps: the pipeline, not a result)" if small else ")"))
    row = "tiny_base"
    finetune = _config("finetune_tiny_base_cpu", cfg_dir,
                       [f"dataset={data_dir}", f"model.name={BASE_NAME}", f"trainer.run_dir={ckpt}",
                        "trainer.run_name=finetune_tiny_base"] + (SMALL_FINETUNE if small else QUICK_FINETUNE),
                       "degusta train")
    ft_dir = run_train(finetune, [])
    for name, adapter in ((f"{row}_zeroshot", None), (f"{row}_finetuned", ft_dir / "best_adapter")):
        cfg_name = "predict_hf_base_" + ("zeroshot" if adapter is None else "finetuned")
        quick = (SMALL_PREDICT if small else QUICK_FINETUNED_PREDICT) if adapter is not None else []
        path = _config(cfg_name, cfg_dir, [f"dataset={data_dir}", f"model.name={BASE_NAME}",
                                           f"model.adapter={adapter if adapter else 'null'}",
                                           f"out={runs / name / 'predictions.jsonl'}"] + quick, "degusta predict")
        entries.append(MethodEntry(name=name, config=str(path)))

    if with_api or os.environ.get("OPENAI_API_KEY"):
        entries += api_entry(data_dir, out, cfg_dir, ep_file, with_api, step)
    else:
        step("no OPENAI_API_KEY: to add a zero-shot GPT-4o MOGMA row, export OPENAI_API_KEY=... and run "
             "`degusta quickstart --with-api` (see configs/zeroshot_mogma_gpt4o.yaml for a local server)")

    step("5/5 comparing every method on the same episodes")
    result = compare(CompareConfig(dataset=str(data_dir), out=str(out / "report"), methods=entries,
                                   episodes=str(ep_file), n_bootstrap=300 if small else 1000,
                                   title="degusta quickstart: every method on the SYNTHETIC naturalistic default"),
                     log=log)
    report = result.out
    step(f"done. Report: {report / 'report.md'} (open {report / 'report.html'} in a browser)")
    return result


# Sizes that keep the main job near 10 CPU minutes (the shipped configs train longer and score better).
QUICK_PARTICIPANTS = 20
QUICK_LEARNED: list[str] = []  # the shipped CPU config as it is (3 epochs, ~2 minutes)
SMALL_LEARNED = ["trainer.max_epochs=1", "data.repeats=1"]
QUICK_FINETUNE = ["trainer.max_steps=45", "trainer.val_check_interval=45", "data.contexts=[0,2,4]",
                  "data.group_by_length=true", "data.val_episodes=8"]
"""Half an epoch (the config's is 87 steps, ~10 minutes on a 2-core EPYC) on the contexts the quickstart scores (the
config trains on context 4 alone, what the test split is scored on; at context 0 it had never seen a prompt without
contexts), in batches of similar length (the three contexts mixed pad a random batch most: 195 s instead of 283 s),
validated once at its end on 8 episodes (the best_adapter the predict config loads). benchmarks/RESULTS.md, "Main
job", has what each choice measured."""
QUICK_FINETUNED_PREDICT = ["decoding.report_unconstrained=false"]
"""The fine-tuned row's answers as the shipped predict config decodes them (greedy + votes of five samples), without
the free answers behind the free parse rate (~30% of its decoding time; the report shows none for that row)."""
SMALL_FINETUNE = ["trainer.max_steps=4", "data.val_episodes=2", "trainer.val_check_interval=4", "data.contexts=[0,2,4]"]
SMALL_PREDICT = ["decoding.report_unconstrained=false", "decoding.n=1", "decoding.temperature=0.0",
                 "decoding.aggregation=steps"]
"""--small decodes the fine-tuned row greedily, once: the pipeline is tested, the score is not the point."""


def api_entry(data_dir: Path, out: Path, cfg_dir: Path, ep_file: Path, with_api: bool, step) -> list:
    """The zero-shot GPT-4o MOGMA row: a cost estimate first; added only with --with-api."""
    from degusta_learn.evaluate.compare import MethodEntry
    from degusta_learn.methods import run_predict

    path = _config("zeroshot_mogma_gpt4o", cfg_dir, [f"dataset={data_dir}", f"episodes={ep_file}",
                                                     f"out={out / 'runs' / 'mogma_gpt4o' / 'predictions.jsonl'}"],
                   "degusta predict")
    run_predict(path, [], dry_run=True, log=step)
    if not with_api:
        step("OPENAI_API_KEY found: the estimate above is what a zero-shot GPT-4o MOGMA row costs; "
             "add it with `degusta quickstart --with-api`")
        return []
    step("adding the zero-shot GPT-4o MOGMA row (cached: a re-run does not pay twice)")
    return [MethodEntry(name="mogma_gpt4o", config=str(path))]
