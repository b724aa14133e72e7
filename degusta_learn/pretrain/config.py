"""The pretrain config (`kind: pretrain`): the FastVLM's sizes, the perception task mix and its stages, validation,
the export folder and the trainer section.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from degusta_learn.config import bounded, seed_field
from degusta_learn.errors import DegustaError
from degusta_learn.optim import OptimConfig
from degusta_learn.pretrain.tasks import TaskMix
from degusta_learn.render.grid import Grid
from degusta_learn.training import TrainerConfig
from degusta_learn.vlm.random_models.fastvlm import OUTPUT_STRIDE, BaseArchitecture
from degusta_learn.vlm.settings import DecodingSettings


@dataclass
class PretrainData:
    """The `data:` section: the perception examples and their batching."""

    REMOVED: ClassVar[dict[str, str]] = {
        "teacher_weight": "the oracle teacher's pull on the tower's tokens; no shipped recipe used it",
        "freeze_projector": "keeping the projector fixed after the vision stage; no shipped recipe used it",
        "retrieval_list_items": "attention supervision of list items' types and ids; no shipped recipe used it",
    }
    """Keys taken out, with why (a config that still sets one is refused with that line)."""

    grid: Grid = field(default_factory=Grid)
    """The labelled grid drawn over the scenes (the base learns this grid)."""
    mix: TaskMix = field(default_factory=TaskMix)
    """Which questions, how often."""
    steps_per_epoch: int = bounded(300, 1, 10_000_000)
    """Training steps between validations (an epoch of fresh examples; last.ckpt is written at its end)."""
    val_examples: int = bounded(48, 0, 1_000_000)
    """Held-out questions generated and scored at every validation."""
    batch_size: int = bounded(8, 1, 4096)
    """Examples per step; a batch holds one task and one number of images (little padding)."""
    max_length: int = bounded(2048, 1, 262_144)
    """Token budget of one example; longer is an error, never truncated."""
    num_workers: int = bounded(0, 0, 256)
    """DataLoader worker processes rendering the scenes (0: in the main process)."""
    dense_weight: float = 0.05
    """Weight of the dense auxiliary loss on the image tokens (what covers each token, where it is); 0: off."""
    tower_steps: int = bounded(0, 0, 10_000_000)
    """A vision stage first: for these steps only the vision tower, its projector and the dense head train, on the
    dense loss alone (the decoder is not run), on the curriculum's one-scene images. The curriculum, the teacher
    and the decoder's own warmup and cosine schedule start after it; `trainer.max_steps` counts both stages."""
    freeze_tower: bool = False
    """After the vision stage, keep the vision tower as the stage left it (weights and BatchNorm statistics); the
    projector, the dense head and the decoder go on training. Unfrozen, the decoder's answer loss reaches the tower
    through its tokens and erases the object ids the stage taught it. Without a
    vision stage (`tower_steps: 0`) there is nothing to keep and it has no effect."""
    teacher_steps: int = bounded(0, 0, 10_000_000)
    """Oracle teacher: the decoder sees perfect image tokens (sums of the embeddings of each cell's content)
    instead of the tower's with a probability falling from 1 to 0 over these steps; 0: off."""
    teacher_hold: int = bounded(0, 0, 10_000_000)
    """Steps at teacher probability 1 before it starts to fall over `teacher_steps` (e.g. a curriculum's)."""
    readout_weight: float = 0.0
    """Weight of the tied readout (`dense.TiedReadout`), after any vision stage: each labelled image token, read
    through the decoder's own output layer, should name its cell's content (cell, types, ids, directions), so the
    projector writes ids where the decoder's copy can name them; 0: off."""
    retrieval_weight: float = 1.0
    """Weight of the attention supervision (`retrieval.py`): one decoder head is told to look, at every answer
    cell and direction, at the image tokens of the object the answer names; 0: off."""
    retrieval_layer: int = bounded(1, 0, 1024)
    """The decoder layer of the supervised head (the previous-token head is in layer 0)."""
    retrieval_head: int = bounded(2, 0, 1024)
    """The supervised head of that layer (by default not in the previous-token head's key group)."""
    curriculum_steps: int = bounded(0, 0, 10_000_000)
    """The first steps draw their questions from `curriculum_mix` instead of `mix` (0: no curriculum)."""
    curriculum_mix: TaskMix = field(default_factory=lambda: TaskMix(
        lists=0.0, describe=1.0, gomo=0.0, locate=0.0, describe_questions=8, scenes=[1.0, 0.0, 0.0, 0.0],
        objects_sheet=0.0, empty_table=0.0))
    """The questions of the first `curriculum_steps` steps: one scene, up to eight *describe* questions about it,
    each answered before the next, the task shape on which a decoder from scratch learns to find an object's
    id among the image tokens. The shipped config adds *locate* and list questions to it, so that the decoder also
    learns to take the next named object."""

    def __post_init__(self):
        for key in ("steps_per_epoch", "batch_size", "max_length"):
            if getattr(self, key) < 1:
                raise DegustaError(f"data.{key}: expected >= 1, got {getattr(self, key)}")
        if self.val_examples < 0 or self.num_workers < 0 or self.dense_weight < 0 or self.retrieval_weight < 0:
            raise DegustaError("data.val_examples / data.num_workers / data.dense_weight / data.retrieval_weight: "
                               "expected >= 0")
        if self.teacher_steps < 0 or self.teacher_hold < 0:
            raise DegustaError("data.teacher_steps / data.teacher_hold: expected >= 0")
        if self.readout_weight < 0:
            raise DegustaError(f"data.readout_weight: expected >= 0, got {self.readout_weight}")
        if self.tower_steps > 0 and self.dense_weight <= 0:
            raise DegustaError("data.tower_steps: the vision stage trains the tower on the dense loss, which "
                               "data.dense_weight: 0 turns off; set data.dense_weight > 0 or data.tower_steps: 0")


@dataclass
class PretrainConfig:
    """`degusta train` with `kind: pretrain`: perception pretraining of a tiny base VLM from random weights."""

    kind: str = "pretrain"
    """Trainer name (TRAINERS)."""
    dataset: str | None = None
    """null: the embedded default catalog and tables; a dataset folder: its catalog.json and tables.json (its arrangements are never read)."""
    seed: int = seed_field()
    """Seed of the weights and of the example streams (validation uses seed + 1,000,003)."""
    model: BaseArchitecture = field(default_factory=BaseArchitecture)
    """Sizes of the FastVLM built from random weights."""
    data: PretrainData = field(default_factory=PretrainData)
    """Examples and batching."""
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=1.5e-3, weight_decay=0.01, warmup_steps=100))
    """Optimizer and schedule."""
    decoding: DecodingSettings = field(default_factory=lambda: DecodingSettings(max_new_tokens=240,
                                                                                report_unconstrained=False))
    """How validation generates: one greedy answer a question, read from constrained (null: true), on_repeat and
    max_new_tokens (a number: its questions are perception lists, not a dataset's answers to size auto from)."""
    RENAMED: ClassVar[dict[str, str]] = {"eval": "decoding"}
    channels_last: bool = False
    """Train the vision tower's convolutions in the channels-last memory layout: the same model up to rounding, its
    forward and backward faster on a CPU (the vision stage 0.51 s a step where 0.65 without it; benchmarks/RESULTS.md,
    "The recipe's time"). The export is written in the usual layout."""
    export: str = "runs/tiny_vlm_base"
    """Where the trained base is written as a plain Hugging Face model folder (with a model card). A folder inside
    the package's shipped models is refused; the shipped base's name (`tiny_vlm_base`) replaces it."""
    trainer: TrainerConfig = field(default_factory=lambda: TrainerConfig(
        run_name="pretrain_tiny_vlm_cpu", max_epochs=-1, max_steps=4000, monitor="val/perception",
        monitor_mode="max"))
    """Lightning settings and the run folder."""

    @property
    def export_target(self) -> tuple[Path, bool]:
        """(the folder `export` names, whether it is a shipped model asked for by name)."""
        from degusta_learn.shipped import shipped_model

        shipped = shipped_model(self.export)
        return (shipped, True) if shipped is not None else (Path(self.export), False)

    def __post_init__(self):
        from degusta_learn.files.paths import refuse_shipped

        self.decoding = self.decoding.resolved(local=True)
        if self.decoding.max_new_tokens == "auto" or self.decoding.n != 1 or self.decoding.sampling_temperature:
            raise DegustaError("decoding: pretraining's validation answers each question once, greedily, within a "
                               "number of tokens: set decoding.max_new_tokens to a number, n 1 and temperature null")

        if not self.export_target[1]:
            refuse_shipped(self.export, "export")
        need = max(self.data.grid.rows, self.data.grid.cols)
        if self.model.tokens_per_side < need:  # no image token would cover a single grid cell
            raise DegustaError(f"model.image_size: {self.model.image_size} px gives {self.model.tokens_per_side} x "
                               f"{self.model.tokens_per_side} image tokens, fewer than the grid's {need} cells per "
                               f"side; use at least {need * OUTPUT_STRIDE} px (or a coarser data.grid)")
        d, t = self.data, self.trainer
        if d.tower_steps > 0 and t.early_stopping_patience is not None:
            raise DegustaError("trainer.early_stopping_patience: the validations of the vision stage "
                               "(data.tower_steps) answer no questions, so val/perception is undefined there; set "
                               "trainer.early_stopping_patience: null")
        if d.retrieval_weight > 0 and not (d.retrieval_layer < self.model.text_layers and
                                           d.retrieval_head < self.model.text_heads):
            key = "retrieval_layer" if d.retrieval_layer >= self.model.text_layers else "retrieval_head"
            raise DegustaError(f"data.{key}: layer {d.retrieval_layer}, head {d.retrieval_head} is not in the decoder "
                               f"(model.text_layers {self.model.text_layers}, model.text_heads "
                               f"{self.model.text_heads}); pick one inside it or set data.retrieval_weight: 0")
        square = self.data.grid.rows == self.data.grid.cols == self.model.tokens_per_side
        for key in ("dense_weight", "teacher_steps", "readout_weight", "retrieval_weight"):  # one token per cell
            if getattr(self.data, key) > 0 and not square:
                raise DegustaError(f"data.{key}: the dense loss, the oracle teacher and the attention supervision "
                                   f"need one image token per grid cell, but model.image_size {self.model.image_size} "
                                   f"px gives {self.model.tokens_per_side} x {self.model.tokens_per_side} tokens for a "
                                   f"{self.data.grid.rows} x {self.data.grid.cols} grid; set data.{key}=0 or match them")
