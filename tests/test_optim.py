"""The shared `optim:` section and its schedule (degusta_learn/optim.py), used by every trainer."""

import pytest
import torch

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError
from degusta_learn.optim import OptimConfig, lr_schedule


def _lrs(cfg: OptimConfig, total: int) -> list[float]:
    opt = torch.optim.AdamW([torch.nn.Parameter(torch.zeros(1))], lr=cfg.lr)
    sched = lr_schedule(opt, cfg, total)["scheduler"]
    out = []
    for _ in range(total):
        out.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    return out


def test_cosine_warms_up_linearly_then_decays_to_the_floor():
    lrs = _lrs(OptimConfig(lr=1.0, warmup_steps=4, min_lr_ratio=0.1), 20)
    assert lrs[:5] == pytest.approx([0.0, 0.25, 0.5, 0.75, 1.0])
    assert all(a >= b for a, b in zip(lrs[4:], lrs[5:]))  # monotone decay after warmup
    assert lrs[-1] == pytest.approx(0.1, abs=0.01)  # reaches min_lr_ratio * lr at the last step


def test_constant_and_warmup_capped_at_half_the_run():
    assert _lrs(OptimConfig(lr=2.0, warmup_steps=2, schedule="constant"), 6)[2:] == [2.0] * 4
    lrs = _lrs(OptimConfig(lr=1.0, warmup_steps=100), 10)  # warmup longer than the run: capped at 5
    assert max(lrs) == pytest.approx(1.0) and lrs.index(max(lrs)) == 5


@pytest.mark.parametrize("override, message", [
    ("optim.schedule=linear", "optim.schedule: expected one of \\['cosine', 'constant'\\]"),
    ("optim.lr=0", "optim.lr: expected > 0"),
    ("optim.min_lr_ratio=1.5", "optim.min_lr_ratio: expected a value from 0.0 to 1.0"),
    ("optim.beta2=1.0", "optim.beta2: expected a value from 0.0 to"),
])
def test_bad_values_name_the_key(override, message):
    from degusta_learn.baselines.learned.train import LearnedTrainConfig

    with pytest.raises(DegustaError, match=message):
        load_config(LearnedTrainConfig, data={}, overrides=[override])


def test_beta2_reaches_every_trainers_adamw():
    """optim.beta2 (0.95-0.98 is usual from scratch; torch's 0.999 by default) is what AdamW gets, for the learned
    model and for fine-tuning / pretraining (FinetuneModule)."""
    from types import SimpleNamespace

    from degusta_learn.baselines.learned.module import LearnedModule
    from degusta_learn.finetune.module import FinetuneModule

    cfg = OptimConfig(lr=1e-3, beta2=0.98)
    trainer = SimpleNamespace(estimated_stepping_batches=10)
    learned = SimpleNamespace(optim_cfg=cfg, model=torch.nn.Linear(2, 2), trainer=trainer)
    assert LearnedModule.configure_optimizers(learned)["optimizer"].defaults["betas"] == (0.9, 0.98)
    holder = torch.nn.Module()
    holder.model = torch.nn.Linear(2, 2)
    tuned = SimpleNamespace(cfg=SimpleNamespace(optim=cfg), trainer=trainer, named_parameters=holder.named_parameters,
                            parameters=holder.parameters, model=holder.model)
    assert FinetuneModule.configure_optimizers(tuned)["optimizer"].defaults["betas"] == (0.9, 0.98)
    assert OptimConfig().beta2 == 0.999  # the default is torch's: no run changes unless asked


@pytest.mark.parametrize("schedule", ["cosine", "constant"])
@pytest.mark.parametrize("total", [1, 7, 100])
def test_warmup_factor_is_the_transformers_schedule_step_for_step(schedule, total):
    # the reference is transformers' own schedule (what lr_schedule hands Lightning), not a formula we wrote
    from degusta_learn.optim import warmup_factor

    o = OptimConfig(lr=1.0, warmup_steps=10, schedule=schedule, min_lr_ratio=0.05)
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    sched = lr_schedule(opt, o, total)["scheduler"]
    for step in range(total):
        assert opt.param_groups[0]["lr"] == pytest.approx(warmup_factor(o, step, total), abs=1e-12), step
        opt.step()
        sched.step()
