"""The context model behind `posterior` (SYNTHETIC data): the slots the context shows, and their geometry.

Both steps follow the naturalistic generator's model of one trial (realize.py):

1. **Tracks** (`make_tracks`, `rematch`): which context objects are the same slot of the person's style. The
   context arrangement with the most objects starts one track per object; each other arrangement is paired
   with the tracks by the Hungarian algorithm (same type required; nearer position relative to the surface
   bounds, the same object id and the same placement step preferred); an object left over, or paired
   further than `NEW_TRACK`, starts a track of its own. After a first fit every arrangement is paired again,
   against the positions that fit expects on its own table. This is the one most likely correspondence,
   not a posterior over correspondences (an approximation, docs/data.md).
2. **Geometry** (`fit_geometry`): the generator sets slot i of setting s on a table whose surface box has
   origin x0 and size wh at

       P + R(turn) [ (a_s - mean_s a) * wh + exp(log_scale) D_i ],   P = x0 + (mean_s a + shift) * wh

   (anchors a_s relative to the box, offsets D_i in physical table units), adds N(0, position^2) to each
   object and moves the layout onto the surface (geometry.fit_into). `fit_geometry` finds the posterior mode
   of the anchors, the offsets and every context trial's shift, turn and log scale (scipy least squares on
   the whitened residuals, priors below), with the fit onto each surface held at the affine move it makes of
   the mode's layout, and the Laplace approximations of the evidence and of the posterior covariance. The
   position noise is the value of largest evidence among `SIGMAS` (the prior's log-uniform range).
   Hypotheses: `single` (one setting: every template but `multi`) and `multi` (one setting per plate, as the
   `multi` template sets them: each plate at its setting's anchor, the other slots with the nearest plate).

Priors (moments of the draws in templates.py): `single` anchor N((0.5, 0.651), (0.146, 0.163)^2) (the
`ANCHORS` mixture with its N(0, 0.04) jitter); `multi` anchors N(0.5, 0.25^2) per coordinate; offsets
N(0, 0.25^2); per trial shift N(0, 0.032^2), turn N(0, 3.46 deg^2), log scale N(0, 0.053^2) (the root mean
squares of the noise ranges U[0.01, 0.05], U[0, 6], U[0.02, 0.08]).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares, linear_sum_assignment

from degusta_learn.scene import Arrangement, Catalog, Table
from degusta_learn.synth.geometry import bounds, fit_into, sizes_of

NEW_TRACK = 0.2
"""Pairing cost (about a relative distance) beyond which a context object starts a track of its own."""
REMATCH = 0.12
"""The same after the first fit, in table units from where the fit expects the slot."""
SIGMAS = tuple(float(s) for s in np.geomspace(0.004, 0.02, 9))
PRIOR = {"single_anchor": ((0.5, 0.651), (0.146, 0.163)), "multi_anchor": ((0.5, 0.5), (0.25, 0.25)),
         "offset": 0.25, "shift": 0.032, "turn": math.radians(3.46), "log_scale": 0.053}
_BIG = 1e3


@dataclass
class Trial:
    """One context arrangement as the model sees it."""

    table: Table
    types: list[str]
    objects: list[int]
    xy: np.ndarray  # (N, 2) image coordinates
    rot: np.ndarray  # (N,) degrees

    @classmethod
    def of(cls, arrangement: Arrangement, table: Table, catalog: Catalog) -> Trial:
        return cls(table, [catalog[o].type for o in arrangement.objects], list(arrangement.objects),
                   arrangement.positions, arrangement.rotations)

    @property
    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """(origin (2,), size (2,)) of the surface's bounding box."""
        x0, y0, x1, y1 = bounds(self.table)
        return np.array([x0, y0]), np.array([max(x1 - x0, 1e-9), max(y1 - y0, 1e-9)])

    @property
    def uv(self) -> np.ndarray:
        x0, wh = self.box
        return (self.xy - x0) / wh

    @property
    def step(self) -> np.ndarray:
        """(N,) placement step scaled to [0, 1]."""
        return np.arange(len(self.objects)) / max(len(self.objects) - 1, 1)


@dataclass
class Track:
    """One slot seen in the context: its type and, per context trial that set it, the placement's index."""

    type: str
    members: dict[int, int] = field(default_factory=dict)


def _pair(cost: np.ndarray, limit: float) -> list[tuple[int, int]]:
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c)) for r, c in zip(rows, cols) if cost[r, c] <= limit]


def make_tracks(trials: list[Trial]) -> list[Track]:
    """The first correspondence (module docstring, step 1)."""
    ref = max(range(len(trials)), key=lambda j: (len(trials[j].objects), -j))
    tracks = [Track(t, {ref: n}) for n, t in enumerate(trials[ref].types)]
    for j, trial in enumerate(trials):
        if j == ref:
            continue
        uv = np.array([np.mean([trials[i].uv[n] for i, n in tr.members.items()], axis=0) for tr in tracks])
        step = np.array([np.mean([trials[i].step[n] for i, n in tr.members.items()]) for tr in tracks])
        cost = np.linalg.norm(uv[:, None] - trial.uv[None], axis=-1) + 0.05 * np.abs(step[:, None] - trial.step[None])
        for a, tr in enumerate(tracks):
            ids = {trials[i].objects[n] for i, n in tr.members.items()}
            cost[a] += [0.0 if o in ids else 0.02 for o in trial.objects]
            cost[a] += [0.0 if t == tr.type else _BIG for t in trial.types]
        paired = _pair(cost, NEW_TRACK)
        for a, n in paired:
            tracks[a].members[j] = n
        taken = {n for _, n in paired}
        tracks += [Track(t, {j: n}) for n, t in enumerate(trial.types) if n not in taken]
    return tracks


def rematch(trials: list[Trial], tracks: list[Track], geometry: Geometry) -> list[Track]:
    """Pair every context trial again with the tracks, against the positions `geometry` expects on its table."""
    out = [Track(tr.type) for tr in tracks]
    extra: list[Track] = []
    for j, trial in enumerate(trials):
        expected = geometry.positions(trials, j)  # (T, 2)
        cost = np.linalg.norm(expected[:, None] - trial.xy[None], axis=-1)
        cost += np.array([[0.0 if t == tr.type else _BIG for t in trial.types] for tr in tracks])
        paired = _pair(cost, REMATCH)
        for a, n in paired:
            out[a].members[j] = n
        taken = {n for _, n in paired}
        extra += [Track(t, {j: n}) for n, t in enumerate(trial.types) if n not in taken]
    return [tr for tr in out if tr.members] + extra


@dataclass
class Geometry:
    """One hypothesis fitted to the context (module docstring, step 2)."""

    hypothesis: str
    anchors: np.ndarray  # (S, 2) relative to the surface box
    seat: np.ndarray  # (T,) setting of each track
    offsets: np.ndarray  # (T, 2) physical offsets from the setting's anchor
    shift: np.ndarray  # (K, 2) per context trial
    turn: np.ndarray  # (K,) radians
    log_scale: np.ndarray  # (K,)
    moves: np.ndarray  # (K, 3): the fit onto each surface as (scale, dx, dy)
    sigma: float
    log_evidence: float
    mean: np.ndarray  # (P,) the posterior mode of [anchors, free offsets]
    cov: np.ndarray  # (P, P) its Laplace covariance
    free: np.ndarray  # (T,) bool: the offsets that are parameters (multi: not the plates)

    def positions(self, trials: list[Trial], j: int) -> np.ndarray:
        """(T, 2) where the mode puts every track in context trial j (its shift, turn, scale and fit move)."""
        x0, wh = trials[j].box
        return _place(self.anchors, self.seat, self.offsets, x0, wh, self.shift[j], self.turn[j], self.log_scale[j],
                      self.moves[j])

    def sample(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(anchors, offsets) drawn from the Laplace posterior."""
        theta = rng.multivariate_normal(self.mean, self.cov, method="eigh") if len(self.mean) else self.mean
        anchors = theta[:self.anchors.size].reshape(-1, 2)
        offsets = np.zeros_like(self.offsets)
        offsets[self.free] = theta[self.anchors.size:].reshape(-1, 2)
        return anchors, offsets


def _place(anchors, seat, offsets, x0, wh, shift, turn, log_scale, move) -> np.ndarray:
    """Positions of slots (anchors[seat] + offsets) on one table: realize.layout's arithmetic, then `move`."""
    mean = anchors.mean(0)
    rel = (anchors[seat] - mean) * wh + math.exp(log_scale) * offsets
    c, s = math.cos(turn), math.sin(turn)
    pre = x0 + (mean + shift) * wh + np.c_[c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1]]
    return move[0] * pre + move[1:]


def hypotheses(tracks: list[Track]) -> list[str]:
    """`single` always; `multi` when 2-4 tracks are plates (the `multi` template's 2-4 settings)."""
    plates = sum(tr.type == "plate" for tr in tracks)
    return ["single", "multi"] if 2 <= plates <= 4 else ["single"]


def _seats(trials: list[Trial], tracks: list[Track], hypothesis: str) -> np.ndarray:
    if hypothesis == "single":
        return np.zeros(len(tracks), dtype=int)
    plates = [a for a, tr in enumerate(tracks) if tr.type == "plate"]
    seat = np.zeros(len(tracks), dtype=int)
    for a, tr in enumerate(tracks):
        if a in plates:
            seat[a] = plates.index(a)
            continue
        dist = []
        for p in plates:
            shared = [j for j in tr.members if j in tracks[p].members]
            if shared:
                d = np.mean([np.linalg.norm(trials[j].xy[tr.members[j]] - trials[j].xy[tracks[p].members[j]])
                             for j in shared])
            else:
                d = 1.0 + np.linalg.norm(_mean_uv(trials, tr) - _mean_uv(trials, tracks[p]))
            dist.append(d)
        seat[a] = int(np.argmin(dist))
    return seat


def _mean_uv(trials: list[Trial], track: Track) -> np.ndarray:
    return np.mean([trials[j].uv[n] for j, n in track.members.items()], axis=0)


def fit_geometry(trials: list[Trial], tracks: list[Track], hypothesis: str) -> Geometry:
    """The posterior mode and Laplace evidence of one hypothesis (module docstring, step 2)."""
    k, n_tracks = len(trials), len(tracks)
    seat = _seats(trials, tracks, hypothesis)
    n_seats = int(seat.max()) + 1
    free = np.array([hypothesis == "single" or tr.type != "plate" for tr in tracks])
    obs_t = np.array([a for a, tr in enumerate(tracks) for _ in tr.members])
    obs_j = np.array([j for tr in tracks for j in tr.members])
    obs_xy = np.array([trials[j].xy[n] for tr in tracks for j, n in tr.members.items()])
    boxes = [t.box for t in trials]
    x0 = np.array([b[0] for b in boxes])[obs_j]
    wh = np.array([b[1] for b in boxes])[obs_j]
    (mu_a, s_a) = PRIOR["single_anchor" if hypothesis == "single" else "multi_anchor"]
    mu_a, s_a = np.array(mu_a), np.array(s_a)
    s_prior = np.concatenate([np.tile(s_a, n_seats), np.full(2 * int(free.sum()), PRIOR["offset"]),
                              np.full(2 * k, PRIOR["shift"]), np.full(k, PRIOR["turn"]), np.full(k, PRIOR["log_scale"])])
    n_geo = 2 * n_seats + 2 * int(free.sum())

    def unpack(theta):
        anchors = theta[:2 * n_seats].reshape(-1, 2)
        offsets = np.zeros((n_tracks, 2))
        offsets[free] = theta[2 * n_seats:n_geo].reshape(-1, 2)
        rest = theta[n_geo:]
        return anchors, offsets, rest[:2 * k].reshape(-1, 2), rest[2 * k:3 * k], rest[3 * k:]

    def predicted(theta, moves):
        anchors, offsets, shift, turn, log_scale = unpack(theta)
        mean = anchors.mean(0)
        rel = (anchors[seat[obs_t]] - mean) * wh + np.exp(log_scale[obs_j])[:, None] * offsets[obs_t]
        c, s = np.cos(turn[obs_j]), np.sin(turn[obs_j])
        pre = x0 + (mean + shift[obs_j]) * wh + np.c_[c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1]]
        return moves[obs_j, :1] * pre + moves[obs_j, 1:]

    prior_mean = np.concatenate([np.tile(mu_a, n_seats), np.zeros(len(s_prior) - 2 * n_seats)])

    def residuals(theta, moves, sigma):
        return np.concatenate([((obs_xy - predicted(theta, moves)) / sigma).ravel(), (theta - prior_mean) / s_prior])

    theta = _initial(trials, tracks, seat, free, n_seats, mu_a, prior_mean)
    moves = np.tile([1.0, 0.0, 0.0], (k, 1))
    sigma = float(np.sqrt(np.mean(np.square(SIGMAS))))
    for _ in range(2):  # fit; pick sigma and the surface moves at that mode; fit again
        theta = least_squares(residuals, theta, args=(moves, sigma), method="lm").x
        sigma = _best_sigma(residuals, theta, moves, len(obs_xy) * 2)
        anchors, offsets, shift, turn, log_scale = unpack(theta)
        moves = np.empty((k, 3))
        for j in range(k):
            set_here = [a for a, tr in enumerate(tracks) if j in tr.members]
            pre = _place(anchors, seat, offsets, *boxes[j], shift[j], turn[j], log_scale[j], (1.0, 0.0, 0.0))
            moves[j] = _surface_move(trials[j], [tracks[a].members[j] for a in set_here], pre[set_here])
    fit = least_squares(residuals, theta, args=(moves, sigma), method="lm")
    log_ev = log_evidence(fit.fun, fit.jac, len(obs_xy) * 2, sigma, s_prior)
    anchors, offsets, shift, turn, log_scale = unpack(fit.x)
    jtj = fit.jac.T @ fit.jac
    cov = np.linalg.pinv(jtj)[:n_geo, :n_geo]
    return Geometry(hypothesis, anchors, seat, offsets, shift, turn, log_scale, moves, sigma, log_ev,
                    fit.x[:n_geo].copy(), (cov + cov.T) / 2, free)


def _initial(trials, tracks, seat, free, n_seats, mu_a, prior_mean) -> np.ndarray:
    """Anchors at the plates' mean relative position (multi) or the prior mean (single); offsets the mean
    observed distance from them; nuisances 0."""
    theta = prior_mean.copy()
    if not free.all():
        for a, tr in enumerate(tracks):
            if not free[a]:
                theta[2 * seat[a]:2 * seat[a] + 2] = _mean_uv(trials, tr)
    anchors = theta[:2 * n_seats].reshape(-1, 2)
    offs = []
    for a, tr in enumerate(tracks):
        if free[a]:
            offs.append(np.mean([trials[j].xy[n] - trials[j].box[0] - anchors[seat[a]] * trials[j].box[1]
                                 for j, n in tr.members.items()], axis=0))
    theta[2 * n_seats:2 * n_seats + 2 * len(offs)] = np.ravel(offs) if offs else []
    return theta


def _best_sigma(residuals, theta, moves, n_data: int) -> float:
    """The position noise in `SIGMAS` with the largest Laplace evidence at the mode `theta` (the data rows of
    the whitened residuals and their Jacobian scale as 1 / sigma; the prior rows do not)."""
    r = residuals(theta, moves, 1.0)
    jac = _jacobian(lambda t: residuals(t, moves, 1.0), theta, r)
    best, best_ev = SIGMAS[0], -math.inf
    for sigma in SIGMAS:
        scale = np.ones(len(r))
        scale[:n_data] = 1.0 / sigma
        ev = log_evidence(r * scale, jac * scale[:, None], n_data, sigma, 1.0)
        if ev > best_ev:
            best, best_ev = sigma, ev
    return float(best)


def _jacobian(fun, theta: np.ndarray, r0: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    out = np.empty((len(r0), len(theta)))
    for i in range(len(theta)):
        t = theta.copy()
        t[i] += eps
        out[:, i] = (fun(t) - r0) / eps
    return out


def log_evidence(r: np.ndarray, jac: np.ndarray, n_data: int, sigma: float, s_prior) -> float:
    """Laplace log evidence of whitened residuals `r` (n_data data entries, then one prior entry per parameter):
    -|r|^2 / 2 - n_data log(sigma sqrt(2 pi)) - sum log s_prior - log det(J^T J) / 2."""
    _, logdet = np.linalg.slogdet(jac.T @ jac)
    return float(-0.5 * r @ r - n_data * math.log(sigma * math.sqrt(2 * math.pi)) - np.sum(np.log(s_prior))
                 - 0.5 * logdet)


def _surface_move(trial: Trial, members: list[int], pre: np.ndarray) -> np.ndarray:
    """(scale, dx, dy) of the affine move geometry.fit_into makes of layout `pre` on the trial's table."""
    if not len(members):
        return np.array([1.0, 0.0, 0.0])
    rot = trial.rot[members]
    post = fit_into(trial.table, pre, rot, sizes_of([trial.types[n] for n in members]))
    if np.allclose(post, pre):
        return np.array([1.0, 0.0, 0.0])
    a = np.zeros((2 * len(pre), 3))
    a[0::2, 0], a[1::2, 0] = pre[:, 0], pre[:, 1]
    a[0::2, 1], a[1::2, 2] = 1.0, 1.0
    return np.linalg.lstsq(a, post.ravel(), rcond=None)[0]
