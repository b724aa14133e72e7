"""How well does colour alone tell a type's objects apart at a render size? A reference for the tower's ids.

A lifted scene draws no id marks: which of a type's objects covers a cell can only be read from how it
looks. This renders every catalog object alone on a random table at a random position and rotation
(`finetune/pretrain/scenes.random_rotation`, the pretraining's draw), `--views` times per size, takes the
pixels the object changed against the empty grid-marked table, and describes them by a normalised RGB
histogram (8 bins a channel). Half of an object's views are averaged into its reference; each other view
is named by its nearest reference (L1) among the objects of its type. The score is that top-1 id accuracy
within the type (chance: 1 / objects of the type); "pooled": all of an object's query views averaged first
(one object seen in several scenes, as a person's favourite objects are across their context tables). It
needs no training and no model: a floor on what the pixels of one view allow (a learned tower may also use
shape and pattern), to set beside `benchmarks/bench_tower_ids.py`'s learned readout (0.5-0.56 at 256 px) and
the `--sizes` a base could use.

Usage:
    python benchmarks/bench_id_colour.py                        # sizes 128 256 384 512, 8 views: ~40 s
    python benchmarks/bench_id_colour.py --dataset data/naturalistic --sizes 256 --views 12
"""

from __future__ import annotations

import argparse

import numpy as np


def colour_histogram(image: np.ndarray, empty: np.ndarray, bins: int = 8, threshold: int = 30) -> np.ndarray | None:
    """Normalised RGB histogram of the pixels that differ from the empty table (None: nothing differs)."""
    changed = np.abs(image.astype(np.int16) - empty.astype(np.int16)).sum(-1) > threshold
    pixels = image[changed].astype(np.int64)
    if len(pixels) == 0:
        return None
    q = (pixels * bins // 256).clip(0, bins - 1)
    h = np.bincount((q[:, 0] * bins + q[:, 1]) * bins + q[:, 2], minlength=bins ** 3).astype(float)
    return h / h.sum()


def views(renderer, catalog, tables, grid, object_id: int, n: int, rng) -> list[np.ndarray]:
    """n colour histograms of one object, each alone on a random table at a random position and rotation."""
    from degusta_learn.finetune.pretrain.scenes import random_rotation
    from degusta_learn.scene import Placement
    from degusta_learn.synth.geometry import bounds, footprint_points, inside, sizes_of

    out, type_, ids = [], catalog[object_id].type, sorted(tables)
    while len(out) < n:
        table = tables[ids[int(rng.integers(len(ids)))]]
        x0, y0, x1, y1 = bounds(table)
        r, xy = random_rotation(rng, type_), np.array([[rng.uniform(x0, x1), rng.uniform(y0, y1)]])
        if not inside(table, footprint_points(xy, np.array([r]), sizes_of([type_]))).all():
            continue
        image = renderer.gma(table.id, [Placement(object_id, float(xy[0, 0]), float(xy[0, 1]), r)], grid)
        empty = renderer.table(table.id, grid)
        h = colour_histogram(np.asarray(image.convert("RGB")), np.asarray(empty.convert("RGB")))
        if h is not None:
            out.append(h)
    return out


def id_accuracy(renderer, catalog, tables, grid, n_views: int, seed: int) -> tuple[dict[str, float], dict[str, float]]:
    """Per type: top-1 nearest-reference id accuracy within the type of each held-out view, and of all of an
    object's held-out views pooled (their mean histogram: the same object seen in several scenes)."""
    rng = np.random.default_rng(seed)
    half = n_views // 2
    scores, pooled = {}, {}
    for type_ in catalog.types:
        objects = [o.id for o in catalog.of_type(type_)]
        hists = {o: views(renderer, catalog, tables, grid, o, n_views, rng) for o in objects}
        refs = np.stack([np.mean(hists[o][:half], axis=0) for o in objects])
        hits = [int(np.argmin(np.abs(refs - h).sum(1)) == i) for i, o in enumerate(objects) for h in hists[o][half:]]
        scores[type_] = float(np.mean(hits))
        pooled[type_] = float(np.mean([int(np.argmin(np.abs(refs - np.mean(hists[o][half:], axis=0)).sum(1)) == i)
                                       for i, o in enumerate(objects)]))
    return scores, pooled


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default=None, help="a dataset folder (catalog.json, tables.json); default: embedded")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 384, 512])
    ap.add_argument("--views", type=int, default=8, help="renders per object: half reference, half queries")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.views < 2:
        ap.error("--views: at least 2 (one reference, one query)")

    from degusta_learn.finetune.pretrain.train import catalog_and_tables
    from degusta_learn.render.grid import Grid
    from degusta_learn.render.lifting import Renderer

    catalog, tables, root = catalog_and_tables(args.dataset)
    grid = Grid(8, 8)
    counts = {t: len(catalog.of_type(t)) for t in catalog.types}
    print(f"colour-histogram nearest reference, id within type ({args.views // 2} reference + "
          f"{args.views - args.views // 2} query views per object); chance: "
          + ", ".join(f"{t} {1 / n:.2f}" for t, n in counts.items()))
    print(f"{'size':>6s} " + " ".join(f"{t:>7s}" for t in catalog.types) + f"    mean  pooled {args.views - args.views // 2}")
    for size in args.sizes:
        scores, pooled = id_accuracy(Renderer(catalog, tables, root, size=size), catalog, tables, grid, args.views,
                                     args.seed)
        print(f"{size:4d}px " + " ".join(f"{scores[t]:7.2f}" for t in catalog.types)
              + f" {np.mean(list(scores.values())):7.2f} {np.mean(list(pooled.values())):9.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
