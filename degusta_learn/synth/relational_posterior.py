"""The achievable floor on relational data (method `posterior`): SYNTHETIC data from the relational generator.

Like the naturalistic floor (posterior.py), it knows what a method could know: the context arrangements and the
generator (its prior over people and its trial model), never a latent style. For each episode it approximates the
posterior over the person's placement rules given the context and answers with the candidate arrangement of least
expected set RMSD over draws from the posterior predictive on the target table (minimum Bayes risk):

- **context 0**: the prior predictive. Candidates are the expected arrangements (`expected_relational`) of
  `candidates` people drawn from the generator's prior, each with the prior's most probable objects; the draws are
  trials of `samples` other prior people on the target table.
- **context k >= 1**: `prior_styles` people drawn from the generator's prior (`relational_habits`, with the
  dataset's `multi` and `noise` options) are grouped by their *structure*: the layout, each seat's edge, and each
  rule's type, relation, reference, seat and whether it is always set. A structure that cannot have made a context
  table (more objects of a type than it has rules, or a different number of plates) is dropped; of the others, the
  `structures` that explain the context best at their own draw's numbers (`_screen`: distance at `SCREEN_STD`, the
  inclusion pattern, the prior share) are fitted:
  1. **which rule is which object** in each context table: per type, by the Hungarian algorithm on the distance to
     where the rule puts its object on that table; fitted once, then paired again against the fit;
  2. **the numbers**: each rule's rotation is the circular mean of its observed ones in its seat's frame; each
     seat's place along its edge and inset, each seen rule's direction, gap and shift, and each context table's
     own move of every seat (along, inset and turn: the generator's per-trial seat noise, prior std the root mean
     square of the prior people's) are the posterior mode under the generator's layout
     (`relational_realize.layout`: the rule chain, each object against its reference's laid-out place on that
     table), with Gaussian position noise whose size is fitted, priors around the structure's draw
     (`PRIOR_STD`), and the move onto each surface (`geometry.fit_into`) held at its effect on the mode (scipy
     least squares, then the Laplace approximation of evidence and covariance);
  3. **weights**: evidence x the structure's prior share x the chance of the rules' inclusion pattern (an
     always-set rule missing from a context table costs `MISSING_ALWAYS`).
  Candidates: each structure of weight >= `MIN_WEIGHT` with the rules whose chance of being set next is at least
  0.3, 0.5 or 0.7 and their most probable distinct objects, then `search` passes of local search (set or drop one
  rule, switch structure); draws: a structure by weight, its numbers from the Laplace posterior, each rule's
  inclusion and favourite object from their posteriors (posterior_prior.GeneratorPrior over the prior people's
  taste), a prior person's noise and loyalty, then the generator's own `sample_relational`. When no structure of
  the prior can have made the context, the answer is the prior predictive (diagnostics say "none fits").

Approximations (also docs/generators.md, "The floor"): one correspondence of context objects to rules per
structure; a finite set of structures (those of the prior draws); Gaussian priors around a structure's draw rather
than the habits' own distributions of directions and gaps; the per-object residuals independent (the generator's
direction and gap noise travels along the rule chain, so it is correlated); the person's noise and loyalty not
inferred (the draws take a prior person's); the placement order is not inferred (the answer lists the rules in
their mean placement step in the context). The method reads no latent style and no other participant.

Usage:
    degusta data generate relational --out data/relational
    degusta predict --config posterior --set dataset=data/relational --set out=runs/posterior_relational/predictions.jsonl
"""

from __future__ import annotations

import copy
import math
from collections import Counter
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, linear_sum_assignment
from scipy.special import softmax

from degusta_learn.scene import Catalog, Dataset, Episode, Placement, Table
from degusta_learn.synth.geometry import fit_into, sizes_of
from degusta_learn.synth.posterior_base import PosteriorPredictor
from degusta_learn.synth.posterior_model import Trial, log_evidence
from degusta_learn.synth.posterior_prior import GeneratorPrior, distinct_modes, sample_distinct
from degusta_learn.synth.relational_habits import sample_relational_style
from degusta_learn.synth.relational_realize import expected_relational, layout, place, sample_relational, with_least
from degusta_learn.synth.relational_style import SIDES, RelationalStyle

THRESHOLDS = (0.3, 0.5, 0.7)
"""Inclusion chances above which a seen rule is set in a candidate (the draws pick among them)."""
PROTOTYPES = 3
"""Of each structure, the prior draws whose own numbers are tried on the context (the best starts the fit)."""
SCREEN_STD = 0.03
"""How far (normalized units) a prior draw's own layout may sit from the context before its structure is unlikely:
the spread of the habits' gaps, directions and seats between people, for choosing which structures to fit."""
MIN_WEIGHT = 0.01
MISSING_ALWAYS = math.log(1e-3)
"""Log chance of an always-set rule missing from a context table (the generator's rare fallback layouts)."""
PRIOR_STD = {"along": 0.3, "inset": 0.04, "direction": 25.0, "gap": 0.02, "shift": 0.015}
"""Prior std of each fitted number around the structure's draw (direction in degrees, the rest normalized units)."""
SIGMA_RANGE = (0.003, 0.03)
"""The fitted position noise is kept in this range (the generator's own noise draws, chained)."""


def signature(style: RelationalStyle) -> tuple:
    """The structure of a relational person: what the fit keeps fixed (module docstring)."""
    return (style.layout, tuple(s.side for s in style.seats),
            tuple((r.type, r.relation, r.ref, r.seat, r.p_include >= 1.0) for r in style.rules))


class RelationalPrior:
    """`n` people drawn from the relational generator's prior, grouped by structure, and their taste."""

    def __init__(self, catalog: Catalog, styles: list[RelationalStyle]):
        self.catalog, self.styles = catalog, styles
        noise = np.array([[s.noise.seat, s.noise.seat * 0.5, s.noise.turn] for s in styles])
        self.seat_std = np.maximum(np.sqrt(np.mean(noise ** 2, axis=0)), 1e-4) if len(styles) else np.full(3, 1e-4)
        """Prior std of a seat's move in one trial (along, inset, turn): the root mean square of the prior's."""
        self.groups: dict[tuple, list[int]] = {}
        for i, s in enumerate(self.styles):
            self.groups.setdefault(signature(s), []).append(i)
        self.type_counts = {sig: Counter(r.type for r in self.styles[members[0]].rules)
                            for sig, members in self.groups.items()}
        self.taste = GeneratorPrior(catalog, styles=self.styles)
        self.p_partial = {t: np.array([r.p_include for s in self.styles for r in s.rules
                                       if r.type == t and r.p_include < 1.0]) for t in catalog.types}

    @classmethod
    def draw(cls, catalog: Catalog, tables: list[Table], n: int, seed: int, multi: float, noise: float
             ) -> RelationalPrior:
        """`n` people from the generator's prior with the dataset's `multi` and `noise` options."""
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0x72706F73]))
        return cls(catalog, [sample_relational_style(rng, f"prior{i}", catalog, tables, multi, noise)
                             for i in range(n)])

    def _weights(self, type_: str, seen: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        p = self.p_partial.get(type_)
        p = p if p is not None and len(p) else np.array([0.5])
        return p, p ** seen * (1.0 - p) ** (k - seen)

    def inclusion(self, type_: str, always: bool, seen: int, k: int) -> float:
        """P(a rule of `type_` set in `seen` of `k` context tables is set in the next one)."""
        if always:
            return 1.0
        p, w = self._weights(type_, seen, k)
        return float(np.sum(w * p) / np.sum(w)) if np.sum(w) > 0 else 0.0

    def sample_inclusion(self, type_: str, always: bool, seen: int, k: int, rng: np.random.Generator) -> float:
        if always:
            return 1.0
        p, w = self._weights(type_, seen, k)
        return float(rng.choice(p, p=w / w.sum())) if np.sum(w) > 0 else 0.0

    def log_pattern(self, type_: str, always: bool, seen: int, k: int) -> float:
        """Log chance of a rule being set in exactly `seen` given context tables of `k`."""
        if always:
            return 0.0 if seen == k else MISSING_ALWAYS * (k - seen)
        _, w = self._weights(type_, seen, k)
        return float(math.log(max(np.mean(w), 1e-300)))


@dataclass
class Fit:
    """One structure fitted to an episode's context."""

    style: RelationalStyle
    """The structure's rules with the fitted numbers (objects, inclusion: filled in by the predictor)."""
    members: list[dict[int, int]]
    """Per context table: rule -> index of its placement."""
    log_posterior: float
    sigma: float
    theta: np.ndarray
    cov: np.ndarray
    keys: list[tuple[str, int, str]]
    """What each entry of theta is: ("seat", index, "along" | "inset") or ("rule", index, field)."""


def _set_theta(style: RelationalStyle, keys: list, theta: np.ndarray) -> None:
    for (kind, i, name), v in zip(keys, theta):
        setattr(style.seats[i] if kind == "seat" else style.rules[i], name, float(v))


def _pair(style: RelationalStyle, trial: Trial) -> dict[int, int] | None:
    """Rule -> placement of one context table, by type and distance to where the rules put their objects; None
    when the structure cannot have made the table."""
    rules = list(range(len(style.rules)))
    xy, _ = layout(style, trial.table, rules)
    out: dict[int, int] = {}
    for t in set(trial.types):
        obs = [n for n, u in enumerate(trial.types) if u == t]
        mine = [i for i in rules if style.rules[i].type == t]
        if len(obs) > len(mine) or (t == "plate" and len(obs) != len(mine)):
            return None
        cost = np.linalg.norm(xy[mine][:, None] - trial.xy[obs][None], axis=-1)
        for a, b in zip(*linear_sum_assignment(cost)):
            out[mine[a]] = obs[b]
    if any(r.type == "plate" and i not in out for i, r in enumerate(style.rules)):
        return None
    return out


def _screen(style: RelationalStyle, trials: list[Trial], prior: RelationalPrior) -> float:
    """How well a prior draw explains the context at its own numbers, as a log score (-inf: it cannot have made a
    context table): Gaussian in the distance of each paired object from where the draw lays it out (`SCREEN_STD`),
    plus the chance of the rules' inclusion pattern (so a rule the context never shows costs what it should)."""
    total, counts = 0.0, Counter()
    for trial in trials:
        members = _pair(style, trial)
        if members is None:
            return -math.inf
        present = sorted(members)
        xy, _ = layout(style, trial.table, present)
        total += float(np.sum((xy - trial.xy[[members[i] for i in present]]) ** 2))
        counts.update(present)
    k = len(trials)
    return -0.5 * total / SCREEN_STD ** 2 + sum(prior.log_pattern(r.type, r.p_include >= 1.0, counts[i], k)
                                                for i, r in enumerate(style.rules))


def _rotations(style: RelationalStyle, trials: list[Trial], members: list[dict[int, int]]) -> None:
    """Each seen rule's rotation: the circular mean of its observed rotations in its seat's frame."""
    for i, rule in enumerate(style.rules):
        facing = SIDES[style.seats[rule.seat].side]
        seen = [trials[j].rot[m[i]] - facing for j, m in enumerate(members) if i in m]
        if seen:
            r = np.radians(seen)
            rule.rotation = float(np.degrees(np.arctan2(np.sin(r).mean(), np.cos(r).mean())) % 360.0)


def fit_structure(proto: RelationalStyle, trials: list[Trial], prior: RelationalPrior, log_share: float) -> Fit | None:
    """The posterior mode, evidence and covariance of one structure given the context (module docstring)."""
    style = copy.deepcopy(proto)
    k = len(trials)
    members = [_pair(style, t) for t in trials]
    if any(m is None for m in members):
        return None
    for _ in range(2):  # fit, then pair again against the fit and fit once more
        fit, keys, n_data, s_prior, sigma = _fit_numbers(style, trials, members, prior.seat_std)
        paired = [_pair(style, t) for t in trials]
        if any(m is None for m in paired) or paired == members:
            break
        members = paired
    n_glob = len(keys)
    log_ev = log_evidence(fit.fun, fit.jac, n_data, sigma, s_prior)
    counts = [sum(i in m for m in members) for i in range(len(style.rules))]
    log_pattern = sum(prior.log_pattern(r.type, r.p_include >= 1.0, n, k) for r, n in zip(style.rules, counts))
    cov = np.linalg.pinv(fit.jac.T @ fit.jac)[:n_glob, :n_glob]
    return Fit(style, members, log_ev + log_pattern + log_share, sigma, fit.x[:n_glob].copy(), (cov + cov.T) / 2, keys)


def _fit_numbers(style: RelationalStyle, trials: list[Trial], members: list[dict[int, int]], seat_std: np.ndarray):
    """Step 2 of the module docstring for one correspondence: `style` gets the fitted rotations and numbers;
    returns (scipy's fit, what each global entry is, data entries, prior stds, position noise)."""
    k, n_seats = len(trials), len(style.seats)
    _rotations(style, trials, members)
    seen = {i for m in members for i in m}
    keys = [("seat", s, name) for s in range(n_seats) for name in ("along", "inset")]
    keys += [("rule", i, name) for i in sorted(seen) if style.rules[i].relation != "edge"
             for name in ("direction", "gap", "shift")]
    n_glob = len(keys)
    mean = np.array([getattr(style.seats[i] if kind == "seat" else style.rules[i], name) for kind, i, name in keys])
    mean = np.concatenate([mean, np.zeros(3 * n_seats * k)])  # each context table's seat moves, mean 0
    s_prior = np.concatenate([[PRIOR_STD[name] for _, _, name in keys], np.tile(seat_std, n_seats * k)])
    presents = [sorted(m) for m in members]
    obs = [t.xy[[m[i] for i in p]] for t, m, p in zip(trials, members, presents)]
    n_data = 2 * sum(len(p) for p in presents)
    moves = [(1.0, np.zeros(2)) for _ in trials]
    work = copy.deepcopy(style)

    def laid_out(theta, j):
        _set_theta(work, keys, theta[:n_glob])
        return layout(work, trials[j].table, presents[j], _seat_noise(work, theta[n_glob:], j))

    def residuals(theta, sigma):
        out = []
        for j, (o, (scale, shift)) in enumerate(zip(obs, moves)):
            xy, _ = laid_out(theta, j)
            out.append(((o - (scale * xy + shift)) / sigma).ravel())
        return np.concatenate(out + [(theta - mean) / s_prior])

    theta, sigma = mean.copy(), 0.01
    for _ in range(2):  # fit; the noise and the moves onto the surfaces at that mode; fit again
        theta = least_squares(residuals, theta, args=(sigma,), method="lm").x
        r = residuals(theta, 1.0)[:n_data]
        sigma = float(np.clip(math.sqrt(np.mean(r ** 2) * n_data / max(n_data - n_glob, 1)), *SIGMA_RANGE))
        moves = [_surface_move(trials[j].table, *laid_out(theta, j), [work.rules[i].type for i in presents[j]])
                 for j in range(k)]
    fit = least_squares(residuals, theta, args=(sigma,), method="lm")
    _set_theta(style, keys, fit.x[:n_glob])
    return fit, keys, n_data, s_prior, sigma


def _seat_noise(style: RelationalStyle, moves: np.ndarray, j: int) -> dict:
    """layout's noise for context table j: its seats' moves (along, inset, turn) from `moves`, nothing else."""
    n_seats, z = len(style.seats), len(style.rules)
    m = moves[3 * n_seats * j:3 * n_seats * (j + 1)].reshape(n_seats, 3)
    return {"along": m[:, 0], "inset": m[:, 1], "turn": m[:, 2], "direction": np.zeros(z), "gap": np.zeros(z),
            "position": np.zeros((z, 2)), "rotation": np.zeros(z)}


def _surface_move(table: Table, xy: np.ndarray, rot: np.ndarray, types: list[str]) -> tuple[float, np.ndarray]:
    """(scale, shift) of the affine move geometry.fit_into makes of the layout `xy` on the table."""
    post = fit_into(table, xy, rot, sizes_of(types))
    if np.allclose(post, xy):
        return 1.0, np.zeros(2)
    a = np.zeros((2 * len(xy), 3))
    a[0::2, 0], a[1::2, 0] = xy[:, 0], xy[:, 1]
    a[0::2, 1], a[1::2, 2] = 1.0, 1.0
    s, dx, dy = np.linalg.lstsq(a, post.ravel(), rcond=None)[0]
    return float(s), np.array([dx, dy])


def _steps(trials: list[Trial], fit: Fit) -> list[float]:
    """Per rule, its mean placement step in the context tables that set it (scaled to [0, 1]; a rule the context
    never sets keeps its place in the rule order)."""
    n = len(fit.style.rules)
    out = []
    for i in range(n):
        seen = [trials[j].step[m[i]] for j, m in enumerate(fit.members) if i in m]
        out.append(float(np.mean(seen)) if seen else i / max(n - 1, 1))
    return out


class RelationalPosterior(PosteriorPredictor):
    """The posterior-predictive predictor of one relational dataset (module docstring)."""

    kind = "structure"

    def __init__(self, ds: Dataset, cfg, options: dict):
        self.ds, self.cfg = ds, cfg
        tables = [ds.tables[t] for t in sorted(ds.tables)]
        multi, noise = float(options.get("multi", 0.2)), float(options.get("noise", 1.0))
        self.prior = RelationalPrior.draw(ds.catalog, tables, cfg.prior_styles, cfg.seed, multi, noise)
        rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 0x7472757468]))
        self._truth_styles = [sample_relational_style(rng, f"draw{i}", ds.catalog, tables, multi, noise)
                              for i in range(cfg.samples)]
        self._prior_answer: dict[int, tuple[list[Placement], dict]] = {}

    def _expected(self, style: RelationalStyle, table: Table) -> list[Placement]:
        return expected_relational(style, table)

    def _sample(self, style: RelationalStyle, table: Table, rng) -> list[Placement]:
        return sample_relational(style, table, self.ds.catalog, rng)

    def _prior_objects(self, types: list[str]) -> list[int]:
        return self.prior.taste.prior_objects(types)

    def _fits(self, trials: list[Trial]) -> list[Fit]:
        """The `structures` structures that explain the context best at their draws' numbers, fitted."""
        n = len(self.prior.styles)
        seen = [Counter(t.types) for t in trials]
        ranked = []
        for sig, members in self.prior.groups.items():
            have = self.prior.type_counts[sig]
            if any(c["plate"] != have["plate"] or any(c[t] > have[t] for t in c) for c in seen):
                continue  # it cannot have made a context table (module docstring)
            share = math.log(len(members) / n)
            score, best = max((_screen(self.prior.styles[i], trials, self.prior), i) for i in members[:PROTOTYPES])
            if math.isfinite(score):
                ranked.append((score + share, best, share))
        ranked.sort(reverse=True)
        fits = [fit_structure(self.prior.styles[i], trials, self.prior, share)
                for _, i, share in ranked[:self.cfg.structures]]
        return [f for f in fits if f is not None]

    def _posterior_predictive(self, ep: Episode, table: Table, rng) -> tuple[list[Placement], dict]:
        ds, prior = self.ds, self.prior
        trials = [Trial.of(a, ds.tables[a.table], ds.catalog) for a in (ds.arrangement(ep.participant, t)
                                                                       for t in ep.context)]
        k = len(trials)
        fits = self._fits(trials)
        if not fits:  # no prior structure can have made this context: the prior predictive
            placements, diag = self._prior_predictive(table)
            return placements, {**diag, "context": k, "structure": "none fits"}
        weights = softmax([f.log_posterior for f in fits])
        per_fit = []
        for f in fits:
            rules = f.style.rules
            seen = [sum(i in m for m in f.members) for i in range(len(rules))]
            always = [r.p_include >= 1.0 for r in rules]
            p_next = [prior.inclusion(r.type, a, n, k) for r, a, n in zip(rules, always, seen)]
            observed = [[trials[j].objects[m[i]] for j, m in enumerate(f.members) if i in m] for i in range(len(rules))]
            objects = prior.taste.object_posterior([r.type for r in rules], observed)
            per_fit.append((seen, always, p_next, objects, distinct_modes(objects.ids, objects.predictive)))
        draws = []
        for _ in range(self.cfg.samples):
            h = int(rng.choice(len(fits), p=weights))
            f, (seen, always, _, objects, _) = fits[h], per_fit[h]
            style = copy.deepcopy(f.style)
            _set_theta(style, f.keys, rng.multivariate_normal(f.theta, f.cov, method="cholesky")
                       if len(f.theta) else f.theta)
            m = int(rng.choice(len(objects.weights), p=objects.weights))
            particle = prior.styles[m]
            favourites = sample_distinct(objects, m, rng)
            for rule, fav, a, n in zip(style.rules, favourites, always, seen):
                rule.object = fav
                rule.p_include = prior.sample_inclusion(rule.type, a, n, k, rng)
            style.colors, style.materials = list(particle.colors), list(particle.materials)
            style.strictness, style.loyalty, style.noise = particle.strictness, particle.loyalty, particle.noise
            draws.append(sample_relational(style, table, ds.catalog, rng))

        def answer(state: tuple) -> list[Placement]:
            h, include = state
            style = copy.deepcopy(fits[h].style)
            _, _, p_next, _, modes = per_fit[h]
            for rule, q, inc in zip(style.rules, p_next, include):
                rule.p_include = 0.5 + q / 2 if inc else q / 2  # ranks kept for the top-up
            idx = with_least(style, [i for i, inc in enumerate(include) if inc])
            xy, rot, _ = place(style, table, idx, None)
            placed = {i: Placement(int(modes[i]), float(x), float(y), float(r) % 360.0)
                      for i, (x, y), r in zip(idx, xy, rot)}
            steps = _steps(trials, fits[h])
            return [placed[i] for i in sorted(idx, key=lambda i: (steps[i], i))]  # the order the context shows

        likely = [h for h, w in enumerate(weights) if w >= MIN_WEIGHT] or [int(np.argmax(weights))]
        states = [(h, tuple(q >= tau for q in per_fit[h][2])) for h in likely for tau in THRESHOLDS]
        state, risk = self._least_risk(states, answer, draws)
        moves = 0
        for _ in range(self.cfg.search):
            h, include = state
            near = [(g, tuple(q >= 0.5 for q in per_fit[g][2])) for g in likely if g != h]
            near += [(h, include[:a] + (not include[a],) + include[a + 1:]) for a in range(len(include))
                     if not per_fit[h][1][a]]  # an always-set rule (every plate) stays set
            if not near:
                break
            found, found_risk = self._least_risk(near, answer, draws)
            if found_risk >= risk:
                break
            state, risk, moves = found, found_risk, moves + 1
        best = fits[state[0]]
        return answer(state), {
            "context": k, "expected_set_rmsd": round(risk, 5), "structure": best.style.template,
            "search_moves": moves, "structures": len(fits), "structure_weight": round(float(weights[state[0]]), 4),
            "set_rules": int(sum(state[1])), "position_noise": round(best.sigma, 5)}
