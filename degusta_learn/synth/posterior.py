"""The achievable floor (method `posterior`): the posterior-predictive arrangement under the generator that made
the data. SYNTHETIC data from `degusta data generate naturalistic` (this module) or `degusta data generate
relational` (relational_posterior.py, the same decision over that generator's prior and trial model) only.

The oracle knows each participant's latent style (an information ceiling); `posterior` knows only what a method
could know: the context arrangements, and the generator (its prior over styles and its noise model). For each
episode it builds the posterior over the person's style given the context, draws target trials from the
posterior predictive on the target table, and answers with the candidate arrangement of least expected set
RMSD over those draws (minimum Bayes risk, the score that ranks methods):

- **context 0**: the prior predictive. Candidates are the expected arrangements (realize.expected_arrangement)
  of `candidates` styles drawn from the generator's prior, each with the prior's most probable objects; the
  draws are trials of `samples` other prior styles. One answer per table, the same for everyone.
- **context k >= 1**: tracks (the slots the context shows) and their geometry are fitted under the
  generator's trial model (posterior_model.py: the posterior mode and Laplace approximation of anchors and
  offsets, two hypotheses weighed by evidence x prior: one setting, or `multi`'s one setting per plate); the
  chance that each slot is set and the objects it gets come from the prior enumerated by
  posterior_prior.py. Candidates: each hypothesis's mode with the slots whose inclusion probability is at
  least 0.3, 0.5 or 0.7 and their most probable (distinct) objects, then `search` passes of local search
  from the best (set or drop one slot, switch hypothesis; with `search_objects`, give a slot another of its
  likely objects), each keeping the move of least expected set RMSD; draws: geometry from the Laplace
  posterior, p_include, taste particle and favourites from their posteriors, then the generator's own
  `sample_arrangement`. Slots the context never shows are left out (for k >= 2 their chance of being set
  next is below 0.4 under the prior).

Approximations (also docs/data.md, "The posterior floor"): one correspondence of context objects to slots;
Gaussian priors with the moments of the template draws on anchors and offsets (the templates' exact offsets
are not used, so a method that knew them could do slightly better); Laplace posteriors; the surface fit held
at its effect on the mode; independent slots. The method reads no latent style and no other participant.

It refuses a dataset that neither generator made (no meta.json `generator` and `seed`, or arrangements other than
the generator's for that seed and options), such as a researcher's own data, in one line.

Usage:
    degusta predict --config configs/posterior.yaml
    degusta predict --config configs/posterior.yaml --set split=val --set context=0 --set out=runs/posterior/val_k0.jsonl
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import softmax

from degusta_learn.errors import DegustaError
from degusta_learn.methods import MethodSpec, PredictConfig
from degusta_learn.scene import Dataset, Episode, Placement, Prediction, Table
from degusta_learn.synth.posterior_base import RELATIONAL, PosteriorPredictor, check_generator, check_relational, made_by
from degusta_learn.synth.posterior_model import Geometry, Track, Trial, fit_geometry, hypotheses, make_tracks, rematch
from degusta_learn.synth.posterior_prior import GeneratorPrior, distinct_modes, sample_distinct
from degusta_learn.synth.realize import expected_arrangement, sample_arrangement
from degusta_learn.synth.style import Noise, Setting, Slot, Style
from degusta_learn.synth.templates import TEMPLATES, sample_style

THRESHOLDS = (0.3, 0.5, 0.7)
"""Inclusion probabilities above which a context slot is set in a candidate (the draws pick among them)."""
LOG_PRIOR = {"single": math.log(1.0 - TEMPLATES["multi"]), "multi": math.log(TEMPLATES["multi"])}
MIN_WEIGHT = 0.01
"""A hypothesis with less posterior weight adds no candidates (it still takes part in the draws)."""
OBJECT_CHOICES = 3
"""The search tries each set slot with its `OBJECT_CHOICES` most probable objects."""


@dataclass
class PosteriorConfig(PredictConfig):
    """Predict config of `posterior`."""

    prior_styles: int = 2000
    """Styles drawn from the generator's prior: the enumeration of inclusion and object taste, and the context-0
    candidates (more: a finer prior, slower start; ~0.5 s per 1000)."""
    candidates: int = 100
    """Context 0: how many prior styles' expected arrangements compete for the least expected set RMSD."""
    samples: int = 100
    """Target trials drawn from the posterior predictive per episode, on which expected set RMSD is estimated
    (more: a steadier choice; cost grows linearly)."""
    search: int = 3
    """Context >= 1: passes of local search from the best threshold candidate (set or leave out one slot, give a
    slot another of its likely objects, switch hypothesis), each keeping the move of least expected set RMSD;
    0 = the threshold candidates only."""
    structures: int = 8
    """Relational data, context >= 1: how many of the prior's structures (those that explain the context best at
    their own draw's numbers) are fitted and weighed (more: a wider posterior, slower; relational_posterior.py)."""
    search_objects: bool = False
    """Let the search give a slot one of its other likely objects: a lower set RMSD (through the feature matching)
    at a large cost in object accuracy; off, every slot keeps its most probable object."""

    def __post_init__(self):
        super().__post_init__()
        for key, least in (("prior_styles", 1), ("candidates", 1), ("samples", 1), ("search", 0), ("structures", 1)):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise DegustaError(f"{key}: expected an integer >= {least}, got {value!r}")
        if self.candidates > self.prior_styles:
            raise DegustaError(f"candidates: {self.candidates} is more than prior_styles ({self.prior_styles}); "
                               "the candidates are prior styles")


class Posterior(PosteriorPredictor):
    """The posterior-predictive predictor of one naturalistic dataset (module docstring)."""

    def __init__(self, ds: Dataset, cfg: PosteriorConfig, plausible: bool):
        self.ds, self.cfg = ds, cfg
        self.prior = GeneratorPrior(ds.catalog, cfg.prior_styles, cfg.seed, plausible)
        rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 0x7472757468]))
        self._truth_styles = [sample_style(rng, f"draw{i}", ds.catalog, plausible=plausible)
                              for i in range(cfg.samples)]
        self._prior_answer: dict[int, tuple[list[Placement], dict]] = {}

    def _expected(self, style: Style, table: Table) -> list[Placement]:
        return expected_arrangement(style, table)

    def _sample(self, style: Style, table: Table, rng) -> list[Placement]:
        return sample_arrangement(style, table, self.ds.catalog, rng)

    def _prior_objects(self, types: list[str]) -> list[int]:
        return self.prior.prior_objects(types)

    def _posterior_predictive(self, ep: Episode, table: Table, rng) -> tuple[list[Placement], dict]:
        ds, prior = self.ds, self.prior
        trials = [Trial.of(a, ds.tables[a.table], ds.catalog) for a in (ds.arrangement(ep.participant, t)
                                                                       for t in ep.context)]
        tracks = make_tracks(trials)
        fits = [fit_geometry(trials, tracks, h) for h in hypotheses(tracks)]
        paired = rematch(trials, tracks, max(fits, key=_log_posterior))
        if [(t.type, t.members) for t in paired] != [(t.type, t.members) for t in tracks]:
            tracks = paired
            fits = [fit_geometry(trials, tracks, h) for h in hypotheses(tracks)]
        weights = softmax([_log_posterior(g) for g in fits])
        k = len(trials)
        seen = [len(tr.members) for tr in tracks]
        p_next = [prior.inclusion(tr.type, n, k) for tr, n in zip(tracks, seen)]
        objects = prior.object_posterior([tr.type for tr in tracks],
                                         [[trials[j].objects[n] for j, n in tr.members.items()] for tr in tracks])
        modes = distinct_modes(objects.ids, objects.predictive)
        order = sorted(range(len(tracks)), key=lambda a: (np.mean([trials[j].step[n] for j, n in
                                                                   tracks[a].members.items()]), a))
        rotations = [_rotations(trials, tracks, g) for g in fits]
        draws = []
        for _ in range(self.cfg.samples):
            h = int(rng.choice(len(fits), p=weights))
            g = fits[h]
            m = int(rng.choice(len(objects.weights), p=objects.weights))
            particle = prior.styles[m]
            favourites = sample_distinct(objects, m, rng)
            p = [prior.sample_inclusion(tr.type, n, k, rng) for tr, n in zip(tracks, seen)]
            anchors, offsets = g.sample(rng)
            noise = Noise(position=g.sigma, rotation=particle.noise.rotation, anchor=particle.noise.anchor,
                          turn=particle.noise.turn, scale=particle.noise.scale, order=particle.noise.order)
            style = _style(ep.participant, g, anchors, offsets, tracks, order, favourites, p, rotations[h], noise,
                           particle)
            draws.append(sample_arrangement(style, table, ds.catalog, rng))

        def answer(state: tuple) -> list[Placement]:
            """The expected arrangement of hypothesis `h` setting the tracks in `include` with `objs`."""
            h, include, objs = state
            g = fits[h]
            p = [0.5 + q / 2 if inc else q / 2 for q, inc in zip(p_next, include)]  # ranks kept for the top-up
            return expected_arrangement(_style(ep.participant, g, g.anchors, g.offsets, tracks, order, list(objs),
                                               p, rotations[h], Noise(position=g.sigma), prior.styles[0]), table)

        likely = [h for h, w in enumerate(weights) if w >= MIN_WEIGHT] or [int(np.argmax(weights))]
        states = [(h, tuple(q >= tau for q in p_next), tuple(modes)) for h in likely for tau in THRESHOLDS]
        state, risk = self._least_risk(states, answer, draws)
        choices = [[int(o) for o in ids[np.argsort(-pred, kind="stable")[:OBJECT_CHOICES]]]
                   for ids, pred in zip(objects.ids, objects.predictive)]
        moves = 0
        for _ in range(self.cfg.search):
            h, include, objs = state
            near = [(g2, include, objs) for g2 in likely if g2 != h]
            near += [(h, include[:a] + (not include[a],) + include[a + 1:], objs) for a in range(len(tracks))]
            if self.cfg.search_objects:
                near += [(h, include, objs[:a] + (o,) + objs[a + 1:]) for a in range(len(tracks)) if include[a]
                         for o in choices[a] if o not in objs]
            if not near:
                break
            found, found_risk = self._least_risk(near, answer, draws)
            if found_risk >= risk:
                break
            state, risk, moves = found, found_risk, moves + 1
        g = fits[state[0]]
        return answer(state), {
            "context": k, "expected_set_rmsd": round(risk, 5), "hypothesis": g.hypothesis, "search_moves": moves,
            "hypothesis_weights": {f.hypothesis: round(float(w), 4) for f, w in zip(fits, weights)},
            "tracks": len(tracks), "set_tracks": int(sum(state[1])), "position_noise": round(g.sigma, 5)}

def _log_posterior(g: Geometry) -> float:
    return g.log_evidence + LOG_PRIOR[g.hypothesis]


def _rotations(trials: list[Trial], tracks: list[Track], g: Geometry) -> list[float]:
    """Per track, the circular mean of its observed rotations less each trial's fitted turn (degrees)."""
    out = []
    for tr in tracks:
        r = np.radians([trials[j].rot[n] for j, n in tr.members.items()]) - g.turn[list(tr.members)]
        out.append(float(np.degrees(np.arctan2(np.sin(r).mean(), np.cos(r).mean())) % 360.0))
    return out


def _style(participant: str, g: Geometry, anchors, offsets, tracks: list[Track], order: list[int],
           objects: list[int], p_include: list[float], rotation: list[float], noise: Noise, taste: Style) -> Style:
    """A latent style with the fitted settings and slots (facing 0: the offsets are in table axes), the taste
    and loyalty of `taste`: what realize.expected_arrangement / sample_arrangement turn into arrangements."""
    settings = [Setting(float(u), float(v), 0.0) for u, v in anchors]
    slots = [Slot(tracks[a].type, float(offsets[a, 0]), float(offsets[a, 1]), rotation[a], objects[a],
                  int(g.seat[a]), float(p_include[a])) for a in order]
    return Style(participant, "posterior", settings, slots, list(taste.colors), list(taste.materials),
                 taste.strictness, taste.loyalty, 1.0, noise)


def run(cfg: PosteriorConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    if made_by(ds)["generator"] == RELATIONAL:
        from degusta_learn.synth.relational_posterior import RelationalPosterior

        if cfg.search_objects:
            raise DegustaError("search_objects: true is for naturalistic data; the relational floor keeps each rule's "
                               "most probable object (leave it false)")

        model = RelationalPosterior(ds, cfg, check_relational(ds))
    else:
        model = Posterior(ds, cfg, check_generator(ds)[1])
    out = []
    for ep in episodes:
        placements, diagnostics = model.predict(ep)
        out.append(Prediction(ep.id, ep.participant, ep.target, cfg.method, list(placements), diagnostics=diagnostics))
    return out


POSTERIOR = MethodSpec(PosteriorConfig, run, "the posterior-predictive arrangement under the generator that made the "
                                             "data, given the context (synthetic naturalistic or relational data "
                                             "only): an achievable floor")
