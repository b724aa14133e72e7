"""What both achievable floors share (posterior.py for naturalistic data, relational_posterior.py for relational
data): the refusal of a dataset that neither generator made, the predictor base (context 0 once per table from the
prior predictive, each episode's own random stream) and the minimum-Bayes-risk choice of least expected set RMSD.
"""

from __future__ import annotations

import math
import re

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.methods import PredictConfig
from degusta_learn.metrics import SET_PENALTY, feature_table
from degusta_learn.metrics.kabsch import kabsch_sq_residuals_batch
from degusta_learn.metrics.matching import as_complex, assign
from degusta_learn.scene import Catalog, Dataset, Episode, Placement, Table

GENERATOR = "degusta_learn.synth.naturalistic"
RELATIONAL = "degusta_learn.synth.relational"
REFUSE = ("posterior needs data made by `degusta data generate naturalistic` or `degusta data generate relational` "
          "(its generator is the prior)")
"""The first part of every refusal of data neither generator made."""


def check_generator(ds: Dataset) -> tuple[int, bool]:
    """(seed, plausible) of the naturalistic generator that made `ds`; DegustaError naming why if none did."""
    meta = made_by(ds)
    if meta["generator"] != GENERATOR:
        raise DegustaError(f"{REFUSE}: {_where(ds)} names generator {meta['generator']!r}, not {GENERATOR!r}")
    plausible = meta.get("plausible", False) is True
    from degusta_learn.synth.naturalistic import naturalistic_with_styles

    made, _ = naturalistic_with_styles(meta["seed"], _participants(ds), plausible=plausible)
    _same_arrangements(ds, made, f"with {_where(ds)}'s seed {meta['seed']}{' (plausible)' if plausible else ''}")
    return meta["seed"], plausible


def check_relational(ds: Dataset) -> dict:
    """The options of the relational generator that made `ds` (meta.json); DegustaError naming why if none did."""
    meta = made_by(ds)
    if meta["generator"] != RELATIONAL:
        raise DegustaError(f"{REFUSE}: {_where(ds)} names generator {meta['generator']!r}, not {RELATIONAL!r}")
    from degusta_learn.synth.relational import relational_options, relational_with_styles

    try:
        options = relational_options({**(meta.get("options") or {}), "participants": max(3, _participants(ds))})
    except DegustaError as e:
        raise DegustaError(f"{REFUSE}: {_where(ds)}'s options: {e}") from None
    made, _ = relational_with_styles(meta["seed"], options)
    _same_arrangements(ds, made, f"with {_where(ds)}'s seed {meta['seed']} and options")
    return {"multi": options.multi, "noise": options.noise}


def _where(ds: Dataset) -> str:
    return str(ds.root / "meta.json") if ds.root is not None else "the dataset's meta"


def made_by(ds: Dataset) -> dict:
    """meta.json of `ds` when it names a generator the floor knows and an integer seed."""
    meta = ds.meta or {}
    if meta.get("generator") not in (GENERATOR, RELATIONAL):
        raise DegustaError(f"{REFUSE}: {_where(ds)} names generator {meta.get('generator')!r}, not {GENERATOR!r} "
                           f"or {RELATIONAL!r}")
    seed = meta.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise DegustaError(f"{REFUSE}: {_where(ds)} has no integer 'seed' to regenerate it from")
    return meta


def _participants(ds: Dataset) -> int:
    """How many participants the generator must make to cover `ds` (its ids are p000, p001, ...)."""
    index = []
    for pid in ds.participants:
        m = re.fullmatch(r"p(\d{3,})", pid)
        if not m or f"p{int(m.group(1)):03d}" != pid:
            raise DegustaError(f"{REFUSE}: participant {pid!r} is not one the generator names (p000, p001, ...)")
        index.append(int(m.group(1)))
    return max(index, default=-1) + 1


def _same_arrangements(ds: Dataset, made: Dataset, how: str) -> None:
    made_by_key = {(a.participant, a.trial): a.to_json() for a in made.arrangements}
    for a in ds.arrangements:
        if made_by_key.get((a.participant, a.trial)) != a.to_json():
            raise DegustaError(f"{REFUSE}: participant {a.participant!r} trial {a.trial} is not what the generator "
                               f"makes {how}")


class PosteriorPredictor:
    """What both floors share: context 0 answered once per table from the prior predictive, each episode's own
    random stream, and the least-risk choice. A subclass sets `prior` (with `styles`), `_truth_styles` and
    `_posterior_predictive`, and says how a style becomes its expected and sampled arrangements."""

    kind = "hypothesis"
    """The diagnostics key that names what the answer came from ("prior" at context 0)."""
    ds: Dataset
    cfg: PredictConfig

    def predict(self, ep: Episode) -> tuple[list[Placement], dict]:
        table = self.ds.tables[self.ds.arrangement(ep.participant, ep.target).table]
        if not ep.context:
            if table.id not in self._prior_answer:
                self._prior_answer[table.id] = self._prior_predictive(table)
            return self._prior_answer[table.id]
        rng = np.random.default_rng(np.random.SeedSequence([self.cfg.seed, *map(ord, ep.id)]))
        return self._posterior_predictive(ep, table, rng)

    def _prior_predictive(self, table: Table) -> tuple[list[Placement], dict]:
        rng = np.random.default_rng(np.random.SeedSequence([self.cfg.seed, table.id]))
        candidates = []
        for style in self.prior.styles[:self.cfg.candidates]:
            placements = self._expected(style, table)
            ids = self._prior_objects([self.ds.catalog[p.object].type for p in placements])
            candidates.append([Placement(o, p.x, p.y, p.rotation) for o, p in zip(ids, placements)])
        draws = [self._sample(s, table, rng) for s in self._truth_styles]
        best, risk = self._least_risk(list(range(len(candidates))), candidates.__getitem__, draws)
        return candidates[best], {"context": 0, "expected_set_rmsd": round(risk, 5), self.kind: "prior"}

    def _least_risk(self, states: list, answer, draws: list[list[Placement]]) -> tuple:
        return least_risk(self.ds.catalog, states, answer, draws)


def least_risk(catalog: Catalog, states: list, answer, draws: list[list[Placement]]) -> tuple:
    """The state whose answer has the least mean set RMSD against the draws, and that mean (the expected set
    RMSD under the posterior predictive); states with the same answer are scored once."""
    answers: dict[tuple, tuple] = {}
    for st in states:
        placements = answer(st)
        answers.setdefault(_key(placements), (st, placements))
    found = list(answers.values())
    risk = [expected_set_rmsd(catalog, placements, draws) for _, placements in found]
    best = int(np.argmin(risk))
    return found[best][0], float(risk[best])


def expected_set_rmsd(catalog: Catalog, prediction: list[Placement], draws: list[list[Placement]]) -> float:
    """Mean `set_rmsd` of one prediction against many ground truths (metrics' matching, Kabsch registration and
    OSPA formula, batched over the draws of each length; equal to `metrics.score_many`'s set_rmsd)."""
    if not draws:
        return math.nan
    c2 = SET_PENALTY ** 2
    if not prediction:
        return SET_PENALTY
    ftable = feature_table(catalog)
    m = len(prediction)
    p_rows = np.array(ftable.rows_of([q.object for q in prediction], "prediction"))
    p_xy = np.array([[q.x, q.y] for q in prediction])
    by_len: dict[int, list[list[Placement]]] = {}
    for d in draws:
        by_len.setdefault(len(d), []).append(d)
    total = 0.0
    for n, group in by_len.items():
        if n == 0:  # an empty ground truth has no score (nan); the generator always sets >= 3
            continue
        g_rows = np.array([ftable.rows_of([q.object for q in d], "draw") for d in group])  # (B, n)
        g_xy = np.array([[[q.x, q.y] for q in d] for d in group])  # (B, n, 2)
        b = len(group)
        ham = ftable.hamming_between(g_rows, np.broadcast_to(p_rows, (b, m)))  # (B, n, m)
        pz = np.broadcast_to(as_complex(p_xy), (b, m))
        gi, pi = assign(ham, as_complex(g_xy), pz)
        rows = np.arange(b)[:, None]
        sq = np.minimum(kabsch_sq_residuals_batch(g_xy[rows, gi], p_xy[pi]), c2)  # (B, K)
        total += float(np.sqrt((sq.sum(1) + c2 * abs(n - m)) / max(n, m)).sum())
    return total / len(draws)


def _key(placements: list[Placement]) -> tuple:
    return tuple((p.object, round(p.x, 6), round(p.y, 6)) for p in placements)
