"""`Planner`: any registered method, loaded once from its predict config, answering plan requests.

Usage:
    from degusta_learn import Planner
    planner = Planner.from_config("baseline_consensus")              # a shipped config name, a path, or None
    planner = Planner.from_config("learned_predict", ["checkpoint=runs/learned_cpu"])   # + --set style overrides
    plan = planner.plan({"participant": "p004", "table": 2, "objects": [3, 28, 57, 80, 104]})
    print(plan.to_json())

A plan runs the method's own `MethodSpec.run` on the request's one episode (planner/episode.py), so every method
plans with the config that evaluates it; the config's episode keys (`split`, `context`, `episodes`) are not used
(the request is the episode). What a method would otherwise load on every call is kept in memory between plans:

- `learned`: the checkpoint, loaded once (again only when the file changes), decoded as `learned`'s run does (the
  same catalog and participant checks, `torch.no_grad`, `num_threads`);
- the zero-shot methods (louma, logma, mouma, mogma): the backend the runner builds (for `hf`, the model and its
  processor; for an API, its client), kept per backend, model and decoding section. The response cache and the
  ledger go to the planner's `workdir` (default runs/plan/<config name>), not beside the config's `out`, so planning
  never touches an evaluation run's files; the plan's `diagnostics.cost_usd` is the ledger's spend for that plan;
- every other method runs as `degusta predict` runs it.

Plans are made one at a time (a lock): one model instance in memory, never used by two threads at once; a server
answers concurrent requests one after another (planner/server.py). `oracle` is refused: it reads the generator's
latent style of a synthetic participant, which a request's person does not have.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from degusta_learn.config import apply_overrides, from_dict, read_yaml
from degusta_learn.errors import DegustaError
from degusta_learn.methods import MethodSpec, get_method
from degusta_learn.methods.predict import run_choices
from degusta_learn.names import MODEL_PROMPTED_METHODS
from degusta_learn.planner.episode import Prepared, prepare
from degusta_learn.planner.plan import Plan, PlanTable
from degusta_learn.planner.request import PlanRequest, loads_request
from degusta_learn.planner.steps import finish
from degusta_learn.scene import Dataset, Prediction, load_dataset

class BackendUnavailable(DegustaError):
    """A zero-shot plan got no answer from its backend (a server kept failing, a budget was reached): not a fault of
    the request (`degusta serve` answers 503; the CLI exits 2 as for any DegustaError)."""


REFUSED = {"oracle": "the oracle reads the generator's latent style of a synthetic participant, which a plan "
                     "request's person does not have; plan with another method"}
"""Methods that cannot plan, and why."""

MAX_HISTORY_DATASETS = 4
"""Dataset folders named by requests (`dataset`) kept loaded at once."""


class Planner:
    """A method loaded once, planning for requests (module docstring). Build it with `from_config`."""

    def __init__(self, spec: MethodSpec, cfg: Any, raw: dict, *, name: str, workdir: Path, dataset: Dataset,
                 read_paths: bool = True):
        self.spec, self.cfg, self.name, self.workdir, self.dataset = spec, cfg, name, workdir, dataset
        self.read_paths = read_paths
        """Whether a request may name a dataset folder to take the person's arrangements from (a server: False)."""
        self._raw = raw
        self.config_sha256: str = run_choices(cfg)["config_sha256"]
        self._lock = threading.Lock()
        self._histories: dict[str, Dataset] = {}
        self._models: dict = {}  # learned: (checkpoint, mtime, size, device) -> (model, hyperparameters)
        self._backends: dict = {}  # zero-shot: repr of (backend, model, decoding, grid) -> backend

    @property
    def method(self) -> str:
        return self.cfg.method

    @classmethod
    def from_config(cls, config: str | Path | None = None, overrides: Sequence[str] | None = None, *,
                    workdir: str | Path | None = None, read_paths: bool = True) -> Planner:
        """A planner for the predict config `config` (a path, or a shipped config name; None: `overrides` alone,
        which must then give `method` and `dataset`) with `overrides` ("key=value" as `--set` takes them)."""
        from degusta_learn.shipped import resolve_config

        path = resolve_config(config) if config is not None else None
        where = str(path) if path else "config"
        raw = apply_overrides(read_yaml(path) if path else {}, list(overrides or []))
        if "method" not in raw:
            raise DegustaError(f"{where}: missing required key 'method'")
        try:
            spec = get_method(raw["method"])
        except DegustaError as e:
            raise DegustaError(f"{where}: {e}") from None
        if raw["method"] in REFUSED:
            raise DegustaError(f"{where}: method {raw['method']!r} cannot plan: {REFUSED[raw['method']]}")
        name = path.stem if path else str(raw["method"])
        workdir = Path(workdir) if workdir is not None else Path("runs") / "plan" / name
        raw = {**raw, "out": str(workdir / "plans.jsonl")}  # zero-shot: cache and ledger beside it; nothing else
        cfg = from_dict(spec.config_cls, raw, where=where)
        try:
            dataset = load_dataset(cfg.dataset)
        except DegustaError as e:
            raise DegustaError(f"{where}: dataset: {e} (the planner's catalog, tables and population)") from None
        return cls(spec, cfg, raw, name=name, workdir=workdir, dataset=dataset, read_paths=read_paths)

    # ----------------------------------------------------------------------------- planning

    def plan(self, request: PlanRequest | dict | bytes) -> Plan:
        """The plan for `request` (a PlanRequest, its JSON object, or its bytes); bad input: one DegustaError line."""
        req = self._checked(request)
        with self._lock:
            prep = prepare(req, self.dataset, str(self.cfg.dataset), self._history if self.read_paths else None)
            prediction, cost = self._predict(prep)
        steps, made = finish(prediction, prep)
        method_diagnostics = dict(prediction.diagnostics or {})
        failures = method_diagnostics.pop("failures", [])
        diagnostics = {"context": len(prep.episode.context), "failures": failures, "cost_usd": cost, **made,
                       "method": method_diagnostics}
        return Plan(tuple(steps), PlanTable.of(prep.table, prep.metres), self.method, self.config_sha256,
                    bool(prediction.failed), diagnostics)

    def dry_run(self, request: PlanRequest | dict | bytes, log=print) -> None:
        """What planning `request` would call and cost (the zero-shot API methods print their estimate); nothing is
        called or written."""
        req = self._checked(request)
        if not any(f.name == "dry_run" for f in dataclasses.fields(self.spec.config_cls)):
            prepare(req, self.dataset, str(self.cfg.dataset), self._history if self.read_paths else None)
            log(f"dry run: method {self.method!r} calls no paid API; the request is valid and would be planned")
            return
        cfg = from_dict(self.spec.config_cls, {**self._raw, "dry_run": True}, where=self.name)
        with self._lock:
            prep = prepare(req, self.dataset, str(self.cfg.dataset), self._history if self.read_paths else None)
            self.spec.run(cfg, prep.ds, [prep.episode])

    def image(self, plan: Plan, size: int = 512):
        """plan.png: the table with the plan drawn, each object labelled with its step (planner/draw.py)."""
        from degusta_learn.planner.draw import plan_image

        known = self.dataset.tables.get(plan.table.id)
        same = known is not None and tuple(known.surface) == tuple(plan.table.surface)
        return plan_image(plan, self.dataset.catalog, known if same else plan.table.table, self.dataset.root, size)

    # ----------------------------------------------------------------------------- internals

    @staticmethod
    def _checked(request: PlanRequest | dict | bytes) -> PlanRequest:
        if isinstance(request, (bytes, bytearray)):
            return loads_request(bytes(request))
        if isinstance(request, PlanRequest):  # built in Python: the same checks and bounds as its JSON
            return PlanRequest.from_json(request.to_json())
        return PlanRequest.from_json(request)

    def _history(self, path: str) -> Dataset:
        key = str(Path(path).expanduser().resolve())
        if key not in self._histories:
            if len(self._histories) >= MAX_HISTORY_DATASETS:
                self._histories.pop(next(iter(self._histories)))
            try:
                self._histories[key] = load_dataset(path)
            except DegustaError as e:
                raise DegustaError(f"request.dataset: {e}") from None
        return self._histories[key]

    def _predict(self, prep: Prepared) -> tuple[Prediction, float | None]:
        if self.method == "learned":
            return self._learned(prep), None
        if self.method in MODEL_PROMPTED_METHODS:  # a model asked: its backend kept between plans, its cost read
            return self._zeroshot(prep)
        predictions = self.spec.run(self.cfg, prep.ds, [prep.episode])
        return self._one(predictions), None

    def _one(self, predictions) -> Prediction:
        if predictions is None:
            raise DegustaError("dry_run: the config is a dry run, which plans nothing (Planner.dry_run, or "
                               "`degusta plan --dry-run`, prints its estimate)")
        return predictions[0]

    def _learned(self, prep: Prepared) -> Prediction:
        """`learned`'s run (baselines/learned/predict.py) with the model kept between plans."""
        import torch

        from degusta_learn.baselines.learned import load_model, predict_episodes
        from degusta_learn.baselines.learned.predict import resolve_checkpoint
        from degusta_learn.devices import resolve_device
        from degusta_learn.scene.dataset import dataset_identity
        from degusta_learn.training import torch_threads
        from degusta_learn.vlm.record import TrainingData

        cfg = self.cfg
        with torch_threads(cfg.num_threads):
            ckpt = resolve_checkpoint(cfg.checkpoint)
            stat = ckpt.stat()
            device = resolve_device(cfg.device, "device")
            key = (str(ckpt.resolve()), stat.st_mtime_ns, stat.st_size, str(device))
            if key not in self._models:
                self._models = {key: load_model(ckpt, device)}  # one checkpoint: a changed file replaces it
            model, hp = self._models[key]
            model.vocab.check_catalog(prep.ds.catalog, f"{cfg.dataset}/catalog.json")
            if isinstance(hp.get("trained_on"), dict):
                TrainingData(**hp["trained_on"]).check_unseen(dataset_identity(prep.ds), {prep.episode.participant},
                                                              str(ckpt))
            with torch.no_grad():
                return predict_episodes(model, prep.ds, [prep.episode], hp["population"], hp.get("min_objects", 1),
                                        cfg.batch_size, diagnostics={"checkpoint": str(ckpt)})[0]

    def _zeroshot(self, prep: Prepared) -> tuple[Prediction, float | None]:
        from degusta_learn.files.jsonio import read_json
        from degusta_learn.prompting import runner

        self.workdir.mkdir(parents=True, exist_ok=True)
        with _kept_backends(runner, self._backends):
            try:
                prediction = self._one(self.spec.run(self.cfg, prep.ds, [prep.episode]))
            except DegustaError as e:
                if str(e).startswith("zero-shot run "):  # runner.ZeroShotRun.incomplete_message: no answer came
                    raise BackendUnavailable(str(e)) from None
                raise
        ledger = Path(self.cfg.out).parent / "ledger.json"
        cost = None
        if prediction.diagnostics.get("backend") not in ("hf", "replay") and ledger.is_file():
            spent = read_json(ledger).get("cost_usd")
            cost = float(spent) if isinstance(spent, (int, float)) else None
        return prediction, cost


@contextlib.contextmanager
def _kept_backends(runner, kept: dict):
    """While one plan runs (under the planner's lock), the zero-shot runner's `make_backend` returns the backend
    built for the same (backend, model, decoding, grid) sections before, instead of building (loading) it again."""
    build = runner.make_backend

    def make(cfg, model, decoding=None, grid=None, catalog=None):
        key = repr((cfg, model, decoding, grid, id(catalog)))
        if key not in kept:
            kept[key] = build(cfg, model, decoding, grid, catalog)
        return kept[key]

    runner.make_backend = make
    try:
        yield
    finally:
        runner.make_backend = build


__all__ = ["REFUSED", "BackendUnavailable", "Planner"]
