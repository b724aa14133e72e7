"""The naturalistic generator's prior, enumerated for `posterior` (SYNTHETIC data): styles, inclusion, object taste.

`GeneratorPrior` draws `n` latent styles with the generator's own `templates.sample_style` (the same options
as the data: `plausible` from meta.json) and keeps, from them:

- `styles`: the prior predictive's candidates and samples at context 0, and the taste particles below;
- **inclusion**: per object type, every drawn slot's `p_include`. A slot set in n of k context trials is set
  in the next with probability sum p^(n+1) (1-p)^(k-n) / sum p^n (1-p)^(k-n) over those values
  (`inclusion`), and `sample_inclusion` draws p itself from the same weights;
- **objects**: each drawn style is one particle (favourite colours, materials, strictness, loyalty). Under
  particle m, a slot's favourite f is drawn with the generator's weights softmax(`favourite_logits`), and a
  trial sets f with probability loyalty, else another object o with weight exp(strictness x taste(o)).
  `object_posterior` weighs the particles by the likelihood of every track's observed objects (tracks
  independent given the particle) and returns, per track, the posterior over its favourite under each
  particle and the predictive distribution of the object it gets next.

Approximations: slots are independent (the generator shares some `p_include` draws between a `multi` style's
settings, and a person's favourites of one type are distinct); a non-favourite pick excludes only the slot's
own favourite (the generator also excludes the objects already set and the other slots' favourites).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp, softmax

from degusta_learn.scene import Catalog
from degusta_learn.synth.style import Style
from degusta_learn.synth.taste import catalog_features
from degusta_learn.synth.templates import favourite_logits, sample_style


@dataclass
class ObjectPosterior:
    """Per track: the catalog ids of its type, the predictive distribution of its next object, and the
    posterior over its favourite under each particle; and the particles' posterior weights."""

    ids: list[np.ndarray]  # per track (n_t,)
    predictive: list[np.ndarray]  # per track (n_t,)
    favourite: list[np.ndarray]  # per track (M, n_t)
    weights: np.ndarray  # (M,)


class GeneratorPrior:
    """`n` styles from the generator's prior and what `posterior` reads off them (module docstring)."""

    def __init__(self, catalog: Catalog, n: int = 0, seed: int = 0, plausible: bool = False,
                 styles: list | None = None):
        """`n` styles drawn with `seed`, or the given `styles` (any with the taste fields and `slots` or `rules`
        of a type and `p_include` each: the relational floor passes its generator's prior people)."""
        if styles is None:
            rng = np.random.default_rng(np.random.SeedSequence([seed, 0x706F7374]))
            styles = [sample_style(rng, f"prior{i}", catalog, plausible=plausible) for i in range(n)]
        self.catalog = catalog
        self.styles: list[Style] = styles
        units = [getattr(st, "slots", None) or getattr(st, "rules", []) for st in styles]
        self.p_include = {t: np.array([s.p_include for us in units for s in us if s.type == t])
                          for t in catalog.types}
        feats = catalog_features(catalog)
        self.ids = {t: feats[t].ids for t in catalog.types}
        self.index = {t: {int(o): i for i, o in enumerate(ids)} for t, ids in self.ids.items()}
        self.loyalty = np.array([s.loyalty for s in self.styles])  # (M,)
        self.logits, self.weights = {}, {}  # per type (M, n_t): favourite logits, non-favourite weights
        for t in catalog.types:
            f = feats[t]
            self.logits[t] = np.array([favourite_logits(f, set(s.colors), set(s.materials), s.strictness)
                                       for s in self.styles])
            self.weights[t] = np.array([np.exp(s.strictness * f.taste(s.colors, s.materials)) for s in self.styles])

    def inclusion(self, type_: str, seen: int, k: int) -> float:
        """P(a slot of `type_` set in `seen` of `k` trials is set in the next one)."""
        w = self._inclusion_weights(type_, seen, k)
        return float(np.sum(w * self.p_include[type_]) / np.sum(w)) if np.sum(w) > 0 else 0.0

    def sample_inclusion(self, type_: str, seen: int, k: int, rng: np.random.Generator) -> float:
        w = self._inclusion_weights(type_, seen, k)
        return float(rng.choice(self.p_include[type_], p=w / w.sum())) if np.sum(w) > 0 else 0.0

    def _inclusion_weights(self, type_: str, seen: int, k: int) -> np.ndarray:
        p = self.p_include.get(type_, np.array([1.0]))
        return p ** seen * (1.0 - p) ** (k - seen)

    def object_posterior(self, types: list[str], observed: list[list[int]]) -> ObjectPosterior:
        """Posterior and predictive objects of tracks of `types` that were seen with objects `observed`."""
        loyal = self.loyalty[:, None]  # (M, 1)
        log_w = np.zeros(len(self.styles))
        per_track = []
        for t, objs in zip(types, observed):
            ids = self.ids[t]
            log_prior = self.logits[t] - logsumexp(self.logits[t], axis=1, keepdims=True)  # (M, n_t)
            w = self.weights[t]
            z_minus = w.sum(1, keepdims=True) - w  # (M, n_t): non-favourite mass when f is the favourite
            pos = np.array([self.index[t][o] for o in objs], dtype=int)
            count = np.bincount(pos, minlength=len(ids))[None, :]  # (1, n_t) times each object was seen
            n = len(objs)
            # log P(objects | f) for every favourite f at once: loyal picks of f, taste-weighted picks of the rest
            log_lik = (count * np.log(loyal) + (n - count) * np.log(1 - loyal) + np.log(w[:, pos]).sum(1, keepdims=True)
                       - count * np.log(w) - (n - count) * np.log(z_minus))
            joint = log_prior + log_lik
            log_w += logsumexp(joint, axis=1)
            per_track.append((ids, softmax(joint, axis=1), w, z_minus))
        weights = softmax(log_w)
        predictive, favourite = [], []
        for _ids, post, w, z_minus in per_track:
            q = (post / z_minus).sum(1, keepdims=True)  # (M, 1)
            other = (1 - loyal) * w * (q - post / z_minus)  # picks of o when o is not the favourite
            predictive.append(weights @ (loyal * post + other))
            favourite.append(post)
        return ObjectPosterior([p[0] for p in per_track], predictive, favourite, weights)

    def prior_objects(self, types: list[str]) -> list[int]:
        """The most probable distinct objects for slots of `types` with nothing observed (context 0)."""
        post = self.object_posterior(types, [[] for _ in types])
        return distinct_modes(post.ids, post.predictive)


def distinct_modes(ids: list[np.ndarray], predictive: list[np.ndarray]) -> list[int]:
    """One object per track, all distinct: the most confident track picks its most probable object first."""
    order = sorted(range(len(ids)), key=lambda i: -float(np.max(predictive[i])))
    used: set[int] = set()
    out = [0] * len(ids)
    for i in order:
        for j in np.argsort(-predictive[i], kind="stable"):
            if int(ids[i][j]) not in used:
                out[i] = int(ids[i][j])
                used.add(out[i])
                break
    return out


def sample_distinct(objects: ObjectPosterior, m: int, rng: np.random.Generator) -> list[int]:
    """Favourites of every track under taste particle m, drawn from their posteriors without repeating an object."""
    used: set[int] = set()
    out = []
    for ids, post in zip(objects.ids, objects.favourite):
        p = post[m] * np.array([int(o) not in used for o in ids])
        p = p / p.sum() if p.sum() > 0 else np.full(len(ids), 1.0 / len(ids))
        out.append(int(rng.choice(ids, p=p)))
        used.add(out[-1])
    return out
