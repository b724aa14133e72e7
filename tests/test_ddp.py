"""DDP really run on the CPU: 2 processes, gloo, `trainer.strategy=ddp` — learned model and tiny fine-tune.

How it is launched: Lightning's "ddp" strategy starts the other ranks by re-running the command line of
rank 0 (`python -m degusta_learn.cli train ...` with LOCAL_RANK=1 in its environment). Under pytest that
command line would be pytest itself, so these tests run the CLI in a subprocess (through a small wrapper
script that audits file writes), exactly as a user would. ("ddp_spawn" would pickle the module instead.)

What is checked:
- a run trains, writes last.ckpt at a validation, is killed (SIGKILL of the whole process group) or stopped
  (max_steps), and resumes from last.ckpt under DDP to the later step;
- only rank 0 writes: every file-creating call of rank 1 under the run folder is recorded by the wrapper and
  must be none (checkpoints, config.yaml, logs, the adapter and degusta_finetune.json all come from rank 0);
- the validation metrics logged by the DDP run (each rank scores its share of the val episodes; the rows
  are gathered and each episode counted once, `training.gather_unique_rows`) equal a single-process
  validation of the same final weights within TOL (float noise of other batch paddings; in practice equal).

Not claimed: that DDP *training* reproduces single-process training bit for bit (DistributedSampler orders
the data differently and each rank's loss is a mean over its own batch).
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from degusta_learn.scene import save_dataset

pytestmark = pytest.mark.slow

ROOT = Path(__file__).parent.parent
CONFIGS = ROOT / "configs"
TOL = 1e-5
"""Largest allowed |DDP - single process| of a validation metric (accuracies, RMSDs in metres, rates)."""
METRICS_LEARNED = ("val/rmsd", "val/object_accuracy", "val/count_error", "val/rmsd_unregistered", "val/rmsd_k2")
METRICS_FINETUNE = ("val/rmsd", "val/object_accuracy", "val/parse_rate", "val/set_rmsd", "val/count_error")

AUDIT = '''
import builtins, io, os, shutil, sys
ROOT = os.path.realpath(os.environ["AUDIT_ROOT"])
LOG = os.environ["AUDIT_LOG"]
_open = builtins.open
def _note(what, path):
    try:
        p = os.path.realpath(os.fsdecode(path))
    except (TypeError, ValueError):
        return
    if p.startswith(ROOT + os.sep) and os.environ.get("LOCAL_RANK", "0") != "0":
        with _open(LOG, "a") as f:
            f.write(f"{os.environ.get('LOCAL_RANK')} {what} {p}\\n")
def _wrap(name, mod, check=lambda *a, **k: True):
    orig = getattr(mod, name)
    def inner(path, *a, **k):
        if check(path, *a, **k):
            _note(name, path)
        return orig(path, *a, **k)
    setattr(mod, name, inner)
_writes = lambda path, mode="r", *a, **k: isinstance(path, (str, bytes, os.PathLike)) and any(c in str(mode) for c in "wax+")
_wrap("open", builtins, _writes)
_wrap("open", io, _writes)
_wrap("open", os, lambda path, flags, *a, **k: bool(flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT)))
for name in ("mkdir", "makedirs", "remove", "unlink", "rmdir"):
    _wrap(name, os)
_wrap("rmtree", shutil)
for name in ("replace", "rename"):
    _wrap(name, os)
from degusta_learn.cli import main
sys.exit(main(sys.argv[1:]))
'''


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A small dataset on disk, the audit wrapper and the environment the CLI subprocesses run with."""
    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import make_small_dataset

    tmp = tmp_path_factory.mktemp("ddp")
    data = save_dataset(make_small_dataset(), tmp / "data")
    wrapper = tmp / "degusta_audited.py"
    wrapper.write_text(AUDIT)
    env = {**os.environ, "AUDIT_ROOT": str(tmp / "runs"), "AUDIT_LOG": str(tmp / "rank1_writes.log"),
           "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    for key in ("RANK", "LOCAL_RANK", "WORLD_SIZE", "NODE_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(key, None)
    return {"tmp": tmp, "data": data, "wrapper": wrapper, "env": env}


def _cli(world, args: list[str], background: bool = False):
    cmd = [sys.executable, str(world["wrapper"]), "train", *args]
    if background:
        return subprocess.Popen(cmd, env=world["env"], cwd=world["tmp"], start_new_session=True,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    done = subprocess.run(cmd, env=world["env"], cwd=world["tmp"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def _sets(overrides: list[str]) -> list[str]:
    return [x for o in overrides for x in ("--set", o)]


def _last_val(run: Path) -> dict[str, float]:
    """The last validation row of the newest CSV log version."""
    newest = max((run / "csv").glob("version_*"), key=lambda p: int(p.name.split("_")[1]))
    with open(newest / "metrics.csv") as f:
        rows = [r for r in csv.DictReader(f) if r.get("val/rmsd")]
    return {k: float(v) for k, v in rows[-1].items() if k.startswith("val/") and v}


def _rank1_writes(world) -> list[str]:
    log = Path(world["env"]["AUDIT_LOG"])
    return log.read_text().splitlines() if log.is_file() else []


def _validate_single(module, datamodule) -> dict[str, float]:
    import lightning as L

    trainer = L.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
    return {k: float(v) for k, v in trainer.validate(module, datamodule=datamodule, verbose=False)[0].items()}


def _assert_close(ddp: dict, single: dict, keys) -> None:
    for key in keys:
        print(f"{key}: DDP {ddp[key]!r} single process {single[key]!r}")  # shown with pytest -s
        assert abs(ddp[key] - single[key]) <= TOL, (key, ddp[key], single[key])


DDP = ["trainer.accelerator=cpu", "trainer.devices=2", "trainer.strategy=ddp", "trainer.progress_bar=false",
       "trainer.log_every_n_steps=1"]


def test_learned_ddp_killed_resumed_and_equal_to_one_process(world):
    from degusta_learn.baselines.learned import LearnedTrainConfig, build
    from degusta_learn.config import load_config

    runs = world["tmp"] / "runs"
    base = [f"dataset={world['data']}", "data.batch_size=8", "data.repeats=1", "model.d_model=16",
            "model.n_layers=1", "model.n_heads=2", "model.d_ff=32", "model.max_objects=8",
            f"trainer.run_dir={runs}", "trainer.run_name=learned", "trainer.max_epochs=-1",
            "trainer.val_check_interval=2", *DDP]
    cfg_path = CONFIGS / "learned_cpu.yaml"
    # 1. a long run, SIGKILLed (all ranks) as soon as its first validation wrote last.ckpt
    proc = _cli(world, ["--config", str(cfg_path), *_sets(base + ["trainer.max_steps=400"])], background=True)
    last = runs / "learned" / "last.ckpt"
    deadline = time.monotonic() + 120
    while not last.is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert last.is_file(), proc.stderr.read()[-3000:]
    step = torch.load(last, weights_only=True, map_location="cpu")["global_step"]
    assert step >= 2 and step % 2 == 0
    # 2. the same command, resumed under DDP, runs 2 more steps (one more validation)
    _cli(world, ["--config", str(cfg_path), *_sets(base + [f"trainer.max_steps={step + 2}"])])
    ckpt = torch.load(last, weights_only=True, map_location="cpu")
    assert ckpt["global_step"] == step + 2
    assert len(list((runs / "learned" / "csv").glob("version_*"))) == 2  # the resumed run logs a new version
    assert _rank1_writes(world) == []  # rank 1 wrote nothing under the run folder
    # 3. the DDP validation of the final weights == a single-process validation of the same weights
    cfg = load_config(LearnedTrainConfig, cfg_path, [o for o in base if not o.startswith("trainer.")])
    module, dm = build(cfg)
    module.load_state_dict(ckpt["state_dict"])
    _assert_close(_last_val(runs / "learned"), _validate_single(module, dm), METRICS_LEARNED)


def test_finetune_ddp_stopped_resumed_and_equal_to_one_process(world):
    from finetune_support import tiny_dir

    from degusta_learn.config import load_config
    from degusta_learn.finetune.collate import Collator
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.finetune.module import FinetuneData, FinetuneModule
    from degusta_learn.finetune.train import build_examples, prepare_model
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset
    from degusta_learn.task.answers import answer_kind
    from degusta_learn.vlm.generate import chat_format

    runs = world["tmp"] / "runs"
    # the overrides of tests/test_finetune_train.py; 3 val episodes: the ranks' shares are padded (2 + 2)
    base = [f"dataset={world['data']}", f"model.name={tiny_dir('idefics3')}", f"trainer.run_dir={runs}",
            "trainer.run_name=finetune", "trainer.val_check_interval=2", "data.val_episodes=3",
            "data.max_train_episodes=16", "data.batch_size=2", "data.render_size=128", "decoding.max_new_tokens=140",
            "decoding.report_unconstrained=false", *DDP]
    cfg_path = CONFIGS / "finetune_tiny_cpu.yaml"
    _cli(world, ["--config", str(cfg_path), *_sets(base + ["trainer.max_steps=2"])])  # stopped at step 2
    run = runs / "finetune"
    _cli(world, ["--config", str(cfg_path), *_sets(base + ["trainer.max_steps=4"])])  # resumed to step 4
    ckpt = torch.load(run / "last.ckpt", weights_only=True, map_location="cpu")
    assert ckpt["global_step"] == 4 and all("lora_" in k for k in ckpt["state_dict"])
    assert (run / "adapter" / "adapter_model.safetensors").is_file() and (run / "degusta_finetune.json").is_file()
    assert _rank1_writes(world) == []  # adapter, exports, logs, checkpoints: rank 0 only
    # single-process validation of the final adapter weights
    cfg = load_config(FinetuneConfig, cfg_path, [o for o in base if not o.startswith("trainer.")])
    ds, grid = load_dataset(cfg.dataset), Grid(cfg.data.grid.rows, cfg.data.grid.cols)
    model, processor = prepare_model(cfg)
    collator = Collator(processor, chat_format(model, processor), cfg.data.max_length,
                        getattr(model.config, "image_token_id", None))
    train, val = build_examples(cfg, ds, grid)
    module = FinetuneModule(model, processor, cfg, ds, grid, answer_kind(cfg.method))
    missing, unexpected = module.load_state_dict(ckpt["state_dict"], strict=False)
    assert not unexpected and not [k for k in missing if "lora_" in k]
    single = _validate_single(module, FinetuneData(train, val, collator, cfg.data.batch_size))
    _assert_close(_last_val(run), single, METRICS_FINETUNE)
