"""Fine-tuning examples rendered on the fly: the zero-shot prompt of an episode and its target answer.

An example is exactly what a zero-shot method sees — `prompting.build_prompt(method, ...)`: GoMO sheets
(or the catalog as text), the context arrangements as GMA (or UmA) images with their placement-order
lines, the empty target table (with grid), the task text — and the answer a perfect model gives, in
the zero-shot answer format (`format_answer(answer_items(...))`: cells from `Grid.encode`, directions
from `rotation_to_direction`, mark ids, in placement order). Nothing is pre-rendered: images are drawn
in `__getitem__` (in DataLoader workers), so grid size, image size or method change without a cache.

Each prompt is cut down by the config's `PromptOptions` (`vlm/prompt_options.py`: the context tables shown as
`data.modality` says, image groups sent, composed canvases), the same options the hf backend re-applies at
prediction time (the adapter's record).

Training examples can draw their context trials afresh every epoch (`resample_seed`, `data.resample_contexts`):
the context of item `i` in epoch `e` is drawn from the participant's other trials with a generator seeded by
(seed, e, i) — deterministic, so a resumed run sees the same contexts, and never from another participant.
`TrainSampler` hands the dataset `(epoch, i)` keys, so DataLoader workers (persistent ones included, which
keep their own copy of the dataset) know the epoch without any hook; it also orders the examples
(a seeded permutation per epoch, or length-grouped batches: `data.group_by_length`) and shards them by rank.

Example:
    examples = LiftedExamples(ds, episodes, "mogma", Grid(8, 8), render_size=448)
    ex = examples[0]; ex.prompt.images, ex.answer
    examples[(3, 0)]  # epoch 3's draw of item 0 (its own contexts when resample_seed is set)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch.utils.data import DistributedSampler

from degusta_learn.vlm.prompt_options import PromptOptions, adapt_prompt
import random
from degusta_learn.finetune.config import FinetuneConfig


@dataclass
class Example:
    """One training / validation example."""

    episode: str
    prompt: object  # prompting.Prompt
    answer: str
    participant: str = ""
    target: int = -1
    context: tuple = ()
    """The trials the prompt shows as context."""
    meta: dict = field(default_factory=dict)
    """What scoring needs beyond the answer text (perception examples: task and ground truth)."""
    followups: tuple = ()
    """(question, answer) text pairs that continue the conversation after `answer`, each a further user turn
    and its supervised answer (several questions about one rendered image). Training only: generation and
    scoring use `prompt` and `answer`."""


class LiftedExamples:
    """A map-style dataset of `Example`s rendered on the fly (torch DataLoader compatible)."""

    def __init__(self, ds, episodes, method: str, grid, render_size: int = 448,
                 options: PromptOptions | None = None, resample_seed: int | None = None):
        from degusta_learn.task.answers import answer_kind
        self.ds, self.episodes, self.method, self.grid = ds, list(episodes), method, grid
        self.kind = answer_kind(method)
        self.render_size = render_size
        self.options = options or PromptOptions()
        self.resample_seed = resample_seed
        """None: the episodes' own contexts every epoch; an int: contexts drawn afresh per (seed, epoch, index)."""
        self._trials = ds.by_participant() if resample_seed is not None else {}
        self._renderer = None  # built lazily: one per DataLoader worker (sprite cache)

    def __len__(self) -> int:
        return len(self.episodes)

    @property
    def renderer(self):
        if self._renderer is None:
            from degusta_learn.render.lifting import Renderer

            self._renderer = Renderer.for_dataset(self.ds, size=self.render_size)
        return self._renderer

    def episode(self, i: int, epoch: int = 0):
        """Episode `i` as epoch `epoch` sees it: with `resample_seed`, its context trials are drawn afresh from
        the same participant's other trials (as many, in trial order as `make_episodes` lists them)."""
        ep = self.episodes[i]
        if self.resample_seed is None or not ep.context:
            return ep
        trials = self._trials[ep.participant]
        others = [a for a in trials if a.trial != ep.target]
        rng = np.random.default_rng([self.resample_seed, epoch, i])
        ctx = [others[j] for j in sorted(rng.choice(len(others), size=len(ep.context), replace=False).tolist())]
        table = next(a.table for a in trials if a.trial == ep.target)
        return replace(ep, context=tuple(a.trial for a in ctx),
                       task="reconstruction" if any(a.table == table for a in ctx) else "generalization")

    def heaviest(self, i: int):
        """Episode `i` with the context the longest prompt could have: with `resample_seed`, its participant's
        other trials holding the most objects (what a token budget must fit whatever an epoch draws)."""
        ep = self.episodes[i]
        if self.resample_seed is None or not ep.context:
            return ep
        others = [a for a in self._trials[ep.participant] if a.trial != ep.target]
        ctx = sorted(sorted(others, key=lambda a: -len(a.placements))[:len(ep.context)], key=lambda a: a.trial)
        return replace(ep, context=tuple(a.trial for a in ctx))

    def example(self, i: int, ep) -> Example:
        """The example of item `i` (its target and answer) shown `ep`'s context."""
        return Example(episode=ep.id, prompt=self._prompt(ep), answer=self.answer(i), participant=ep.participant,
                       target=ep.target, context=tuple(ep.context))

    def prompt(self, i: int, epoch: int = 0):
        return self._prompt(self.episode(i, epoch))

    def _prompt(self, ep):
        from degusta_learn.task.prompt import build_prompt
        return adapt_prompt(build_prompt(self.method, self.ds, ep, self.renderer, self.grid), self.options)

    def answer(self, i: int) -> str:
        from degusta_learn.task.answer_format import answer_items, format_answer
        ep = self.episodes[i]
        target = self.ds.arrangement(ep.participant, ep.target)
        return format_answer(answer_items(list(target.placements), self.ds.catalog, self.kind, self.grid), self.kind)

    def __getitem__(self, key) -> Example:
        """`examples[i]` (epoch 0) or `examples[(epoch, i)]` (what `TrainSampler` yields)."""
        epoch, i = key if isinstance(key, tuple) else (0, key)
        return self.example(i, self.episode(i, epoch))

    def __getstate__(self):  # workers rebuild their own renderer
        state = dict(self.__dict__)
        state["_renderer"] = None
        return state


class TrainSampler(DistributedSampler):
    """One rank's training order for an epoch, as `(epoch, index)` keys (see the module docstring).

    Each epoch (`set_epoch`, which Lightning calls) a permutation seeded by `seed + epoch` (as torch's
    DistributedSampler), or with `lengths` (token counts per example) transformers' length-grouped order
    (`get_length_grouped_indices`: random megabatches of up to 50 global batches, each sorted by length, the
    longest batch first so an out-of-memory error comes at once). A global batch of `batch_size x
    num_replicas` consecutive examples is shared out rank by rank (`rank::num_replicas`), so the ranks' batches
    have similar lengths too; the order is padded by repeating its start to a multiple of `num_replicas`.
    It subclasses DistributedSampler so that Lightning keeps it under DDP (it replaces any other sampler).
    """

    def __init__(self, dataset, seed: int, num_replicas: int = 1, rank: int = 0,
                 lengths: list[int] | None = None, batch_size: int = 1):
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=True, seed=seed, drop_last=False)
        if lengths is not None and len(lengths) != len(dataset):
            raise ValueError(f"lengths: {len(lengths)} values for {len(dataset)} examples")
        self.lengths, self.batch_size = lengths, batch_size

    def order(self) -> list[int]:
        """Every example's index once, in this epoch's order (before sharding)."""
        from transformers.trainer_pt_utils import get_length_grouped_indices

        g = torch.Generator()
        g.manual_seed(self.seed + self.epoch)
        if self.lengths is None:
            return torch.randperm(len(self.dataset), generator=g).tolist()
        return get_length_grouped_indices(self.lengths, self.batch_size * self.num_replicas, generator=g)

    def __iter__(self):
        order = self.order()
        order = (order * math.ceil(self.total_size / max(1, len(order))))[:self.total_size]
        return iter([(self.epoch, i) for i in order[self.rank:self.total_size:self.num_replicas]])


def build_examples(cfg: FinetuneConfig, ds, grid):
    """(train LiftedExamples, val LiftedExamples) from the dataset's seeded participant split."""
    from degusta_learn.finetune.data import LiftedExamples
    from degusta_learn.scene import make_episodes
    from degusta_learn.training.protocol import selection_episodes

    opts = cfg.data.prompt_options()
    train = [e for k in cfg.data.contexts for e in make_episodes(ds, k, "train", cfg.seed)]
    if cfg.data.max_train_episodes is not None and len(train) > cfg.data.max_train_episodes:
        train = random.Random(cfg.seed).sample(train, cfg.data.max_train_episodes)
    # validation picks best_adapter/ and drives early stopping: the validation participants only (training.protocol)
    val = selection_episodes(ds, cfg.data.val_contexts, cfg.seed) if cfg.data.val_episodes else []
    if len(val) > cfg.data.val_episodes:
        val = random.Random(cfg.seed + 1).sample(val, cfg.data.val_episodes)
    # training contexts drawn afresh each epoch, seeded by the training seed (the split stays the split seed's)
    resample = cfg.trainer.seed if cfg.data.resample_contexts else None
    return (LiftedExamples(ds, train, cfg.method, grid, cfg.data.render_size, opts, resample_seed=resample),
            LiftedExamples(ds, val, cfg.method, grid, cfg.data.render_size, opts))  # validation: fixed
