"""One-to-one matching of predicted to ground-truth objects (DESIGN.md section 6).

Objects are compared by the Hamming distance between their discrete features (`MATCH_FEATURES`: type,
colours, materials, shape, pattern; integer codes from `Catalog.features`), and matched by scipy's
Hungarian solver (`linear_sum_assignment`; the default, `matching="hungarian"`) or by the paper's greedy rule
(`matching="paper"`, below), either giving `N = min(len(gt), len(pred))` pairs. The two colours
and the two materials are compared as unordered pairs (`UNORDERED_PAIRS`; the paper's multi-label colours
and materials): a pair counts the positions that differ in the better of its two alignments, so red/blue
vs blue/red is 0, red/blue vs blue/green 1, red/red vs blue/blue 2 (`hamming`).

Hungarian ties break toward nearer positions. The cost of pairing ground-truth object i with prediction j is

    cost[i, j] = hamming[i, j] + eps * dist[i, j],   eps = 0.5 / (N * max(dist))

with `dist` the Euclidean distance between their (x, y) positions. Any assignment's distance term adds up
to at most N * eps * max(dist) = 0.5 < 1, the smallest possible difference between two total Hamming
distances, so distance never overrides Hamming: the result has the minimum total Hamming distance, and
among those assignments the minimum total distance (a lexicographic optimum). Exact ties left after that
(same features and same distances) go to scipy's deterministic choice.

The paper's rule (`matching="paper"`, `greedy_assignment`). The paper's appendix: "We match points between
the predicted and ground truth frames by computing their similarity matrix D, using the Hamming distance over
features as our distance function. Then for each object in the ground truth frame, we find the most similar
object in the predicted setting, ensuring that each object only matches with one object from the other
setting." Our reading, deterministic:

- the ground-truth objects pick one after another in their list order (the placement order: the only order a
  ground-truth frame has);
- each takes, among the predictions not yet taken, the one of least Hamming distance (the same `hamming` as
  above: D is a distance, "most similar" is its minimum);
- ties go to the prediction listed first in the answer (what an argmin over a row of D returns); positions
  play no part, since the paper's similarity is over features only;
- once every prediction is taken, the remaining ground-truth objects stay unmatched, so the rule also gives
  `N = min(len(gt), len(pred))` pairs ("each ordering is of the same length, N").

Greedy is not optimal: an early ground-truth object can take the prediction a later one needed, leaving the
later one a worse match (a higher total Hamming distance than the Hungarian assignment). Both rules share the
cost tables, so `score_many` and `score_prediction` agree under either (`assign`).

Speed: the catalog's pairwise Hamming table is computed once per catalog (cached while the catalog
lives), so a cost matrix is one table lookup plus the distances; positions travel as complex numbers
x + iy so a distance matrix is one subtraction and one abs.

Usage:
    from degusta_learn.metrics import match
    gt_idx, pred_idx = match(catalog, gt.objects, pred_ids, gt.positions, pred_xy)
    gt_idx, pred_idx = match(catalog, gt.objects, pred_ids, gt.positions, pred_xy, matching="paper")
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from degusta_learn.errors import DegustaError
from degusta_learn.metrics.plan import symmetry_order
from degusta_learn.scene.catalog import MATCH_FEATURES, UNORDERED_PAIRS, Catalog, object_size

_TABLE_MAX_OBJECTS = 2048  # pairwise table up to 2048^2 int8 = 4 MiB; larger catalogs compare features
_CACHE: dict[int, tuple[weakref.ref, FeatureTable]] = {}
_PAIRS = [(MATCH_FEATURES.index(first), MATCH_FEATURES.index(second)) for first, second in UNORDERED_PAIRS]

MATCHINGS = ("hungarian", "paper")
"""The matching rules (`matching=`): "hungarian" (the default: minimum total Hamming distance, ties to nearer
positions) and "paper" (the paper's greedy rule: see the module docstring)."""
MATCHING_DESCRIPTIONS = {
    "hungarian": "Hungarian assignment: the one-to-one pairing of least total Hamming distance, ties to nearer "
                 "positions",
    "paper": "the paper's greedy rule: each ground-truth object, in placement order, takes the least-Hamming "
             "prediction not yet taken (ties: the one listed first)",
}
"""One line per rule, as the reports state it."""


def check_matching(matching) -> str:
    """`matching` if it names a rule of `MATCHINGS`, else DegustaError listing the choices."""
    if not isinstance(matching, str) or matching not in MATCHINGS:
        shown = " ".join(repr(matching).split())[:60]
        raise DegustaError(f"matching: expected one of {list(MATCHINGS)}, got {shown}")
    return matching


def matching_line(matching: str) -> str:
    """The report's one line naming the matching rule behind every score."""
    return f"Matching: {MATCHING_DESCRIPTIONS[check_matching(matching)]} (`matching: {matching}`)."


def hamming(fa: np.ndarray, fb: np.ndarray) -> np.ndarray:
    """Feature distances between rows of `Catalog.features`: (..., n, F) and (..., m, F) -> (..., n, m).

    The number of differing features, where each `UNORDERED_PAIRS` pair (colours, materials) counts the
    differences of its better alignment (straight or swapped): pairs compare as unordered pairs.
    """
    a, b = fa[..., :, None, :], fb[..., None, :, :]  # (..., n, 1, F), (..., 1, m, F)
    diff = a != b
    out = diff.sum(-1)
    for i, j in _PAIRS:
        straight = diff[..., i].astype(np.int64) + diff[..., j]
        swapped = (a[..., i] != b[..., j]).astype(np.int64) + (a[..., j] != b[..., i])
        out = out - straight + np.minimum(straight, swapped)
    return out


class FeatureTable:
    """Per-catalog lookup: object id -> row, the pairwise Hamming distances between rows, and per row the
    object's rotational symmetry order (`plan.symmetry_order`) and footprint (width, length)."""

    def __init__(self, catalog: Catalog):
        ids = np.asarray(catalog.ids, dtype=np.int64)
        self.size = len(ids)
        self.row = None  # dense id -> row table only when ids are compact (an id of 1e11 must not allocate 745 GiB)
        if ids.size and ids.min() >= 0 and ids.max() < 4 * len(ids) + 1024:
            self.row = np.full(int(ids.max()) + 1, -1, dtype=np.int64)
            self.row[ids] = np.arange(len(ids))
        self._order = np.argsort(ids, kind="stable")
        self._sorted = ids[self._order]
        self.row_of = {int(i): r for r, i in enumerate(ids.tolist())}  # fast path for a few ids
        self.features = catalog.features(ids)  # (K, F)
        self._objects = tuple(getattr(catalog, "objects", ()))  # rows in catalog order (for symmetry, sizes)
        self._symmetry: np.ndarray | None = None
        self._sizes: np.ndarray | None = None
        self.hamming = None
        if len(ids) <= _TABLE_MAX_OBJECTS:
            self.hamming = hamming(self.features, self.features).astype(np.int8)  # (K, K)

    @property
    def symmetry(self) -> np.ndarray:
        """(K,) rotational symmetry order per row (`plan.symmetry_order`; built on first use)."""
        if self._symmetry is None:
            self._symmetry = np.array([symmetry_order(o) for o in self._objects], dtype=np.int64).reshape(-1)
        return self._symmetry

    @property
    def sizes(self) -> np.ndarray:
        """(K, 2) footprint (width, length) per row (`scene.object_size`; built on first use)."""
        if self._sizes is None:
            self._sizes = np.array([object_size(o) for o in self._objects], dtype=float).reshape(-1, 2)
        return self._sizes

    def rows(self, ids, what: str) -> np.ndarray:
        """Rows of `ids` (any shape); DegustaError naming the first id the catalog lacks."""
        ids = np.asarray(ids, dtype=np.int64)
        if self.row is not None:
            ok = (ids >= 0) & (ids < len(self.row))
            rows = np.where(ok, self.row[np.where(ok, ids, 0)], -1)
        else:
            pos = np.clip(np.searchsorted(self._sorted, ids), 0, max(self.size - 1, 0))
            found = (self._sorted[pos] == ids) if self.size else np.zeros(ids.shape, dtype=bool)
            rows = np.where(found, self._order[pos] if self.size else -1, -1)
        if (rows < 0).any():
            bad = ids.ravel()[np.argmax(rows.ravel() < 0)]
            raise DegustaError(f"{what}: unknown object id {int(bad)} (not in the catalog of {self.size} objects)")
        return rows

    def rows_of(self, ids: Sequence[int], what: str) -> list[int]:
        """Like `rows` for a short list of ids, in plain Python (cheaper for a handful)."""
        try:
            return [self.row_of[i] for i in ids]
        except (KeyError, TypeError):
            return self.rows(ids, what).tolist()

    def hamming_between(self, gt_rows: np.ndarray, pred_rows: np.ndarray) -> np.ndarray:
        """(E, n) and (E, m) rows -> (E, n, m) Hamming distances."""
        if self.hamming is not None:
            return self.hamming[gt_rows[:, :, None], pred_rows[:, None, :]]
        return hamming(self.features[gt_rows], self.features[pred_rows])  # (E, n, F), (E, m, F) -> (E, n, m)


def feature_table(catalog: Catalog) -> FeatureTable:
    """The cached FeatureTable of `catalog` (built on first use, dropped when the catalog is)."""
    hit = _CACHE.get(id(catalog))
    if hit is not None and hit[0]() is catalog:
        return hit[1]
    table = FeatureTable(catalog)
    key = id(catalog)
    _CACHE[key] = (weakref.ref(catalog, lambda _ref: _CACHE.pop(key, None)), table)
    return table


def match_costs(hamming: np.ndarray, gt_z: np.ndarray, pred_z: np.ndarray) -> np.ndarray:
    """Batched matching costs (Hamming + eps * distance, see the module docstring).

    Args:
        hamming: (E, n, m) Hamming distances, n, m > 0.
        gt_z: (E, n) complex ground-truth positions x + iy.
        pred_z: (E, m) complex predicted positions.

    Returns:
        (E, n, m) float costs; one `linear_sum_assignment` per episode gives the matching.
    """
    dist = np.abs(gt_z[:, :, None] - pred_z[:, None, :])  # (E, n, m)
    n_pairs = min(dist.shape[1], dist.shape[2])
    dmax = dist.reshape(len(dist), -1).max(axis=1)  # (E,)
    # Where dmax == 0 every distance is 0, so any finite eps adds nothing.
    eps = 0.5 / np.maximum(n_pairs * dmax, np.finfo(float).tiny)
    return hamming + eps[:, None, None] * dist


def greedy_assignment(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The paper's greedy one-to-one matching, batched: (E, n, m) costs -> (gt_idx, pred_idx), each (E, k).

    Row i = 0, 1, ..., k - 1 (k = min(n, m)) in turn takes the cheapest column no earlier row took; an exact
    tie goes to the lowest column index (argmin's first). With n > m the rows after the m-th stay unmatched.
    gt_idx is 0..k-1 in every episode (ascending, like `linear_sum_assignment`'s rows).
    """
    n_ep, n, m = cost.shape
    k = min(n, m)
    taken = np.zeros((n_ep, m), dtype=bool)
    pred_idx = np.empty((n_ep, k), dtype=np.int64)
    episodes = np.arange(n_ep)
    for i in range(k):  # k <= a table's objects: a short loop, vectorized over the episodes
        j = np.where(taken, np.inf, cost[:, i, :]).argmin(axis=1)
        pred_idx[:, i] = j
        taken[episodes, j] = True
    return np.broadcast_to(np.arange(k, dtype=np.int64), (n_ep, k)).copy(), pred_idx


def assign(hamming: np.ndarray, gt_z: np.ndarray, pred_z: np.ndarray, matching: str = "hungarian"
           ) -> tuple[np.ndarray, np.ndarray]:
    """Batched matching under rule `matching` (`MATCHINGS`): (E, n, m) Hamming distances, (E, n) and (E, m)
    complex positions, n, m > 0 -> (gt_idx, pred_idx), each (E, min(n, m)), gt_idx ascending.

    "hungarian": one `linear_sum_assignment` per episode on `match_costs`; "paper": `greedy_assignment` on the
    Hamming distances alone. Both score paths call this, so they match bit for bit under either rule.
    """
    if check_matching(matching) == "paper":
        return greedy_assignment(hamming)
    cost = match_costs(hamming, gt_z, pred_z)
    k = min(cost.shape[1], cost.shape[2])
    gt_idx, pred_idx = np.empty((len(cost), k), dtype=np.int64), np.empty((len(cost), k), dtype=np.int64)
    for e in range(len(cost)):
        gt_idx[e], pred_idx[e] = linear_sum_assignment(cost[e])
    return gt_idx, pred_idx


def as_complex(xy) -> np.ndarray:
    """(..., N, 2) positions -> (..., N) complex x + iy."""
    return np.ascontiguousarray(xy, dtype=np.float64).view(np.complex128)[..., 0]


def match(catalog: Catalog, gt_ids: Sequence[int], pred_ids: Sequence[int], gt_xy, pred_xy,
          matching: str = "hungarian") -> tuple[np.ndarray, np.ndarray]:
    """Match predicted to ground-truth objects: by default minimum total Hamming distance, ties toward nearer
    positions; `matching="paper"`: the paper's greedy rule (module docstring).

    Args:
        catalog: the catalog holding every id.
        gt_ids: ground-truth object ids, length n.
        pred_ids: predicted object ids, length m (repeats allowed).
        gt_xy: (n, 2) ground-truth positions.
        pred_xy: (m, 2) predicted positions.
        matching: the rule, one of `MATCHINGS`.

    Returns:
        (gt_idx, pred_idx): index arrays of the min(n, m) matched pairs, gt_idx ascending.

    Raises:
        DegustaError: an id is not in the catalog, positions do not fit the ids, or `matching` is unknown.
    """
    check_matching(matching)
    table = feature_table(catalog)
    g, p = table.rows(list(gt_ids), "ground truth"), table.rows(list(pred_ids), "prediction")
    gxy = np.asarray(gt_xy, dtype=float).reshape(-1, 2)
    pxy = np.asarray(pred_xy, dtype=float).reshape(-1, 2)
    if len(gxy) != len(g) or len(pxy) != len(p):
        raise DegustaError(f"match: {len(g)} ground-truth ids with {len(gxy)} positions, "
                           f"{len(p)} predicted ids with {len(pxy)} positions")
    if len(g) == 0 or len(p) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    gi, pi = assign(table.hamming_between(g[None], p[None]), as_complex(gxy)[None], as_complex(pxy)[None], matching)
    return gi[0], pi[0]
