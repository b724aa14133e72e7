"""Rendering speed and grid quantization floor.

    python benchmarks/bench_render.py                 # both tables, printed as markdown
    python benchmarks/bench_render.py --repeats 50 --quick   # speed only
    python benchmarks/bench_render.py --sizes 448,1024,2048,4096  # size -> ms of the image set, cold and warm

Speed: the full image set of one `mogma` episode (4 context GMA images, the target table with the grid,
one GoMO sheet per object type) at 448 px, in memory (PIL images, before any encoding), on one core
(thread env vars set to 1 before numpy/PIL load), warm cache (the set is rendered once first), median
over repeats. The episode is the context-4 test episode with the most context objects. PNG and JPEG
(quality 90, as the prompts send) encoding of the same 10 images are timed separately. A second line
renders with fresh rotations (rotated-sprite cache cleared each repeat: what a data loader sees
when every sample has new angles). The loaded dataset is moved out of the garbage collector's way with
`gc.freeze()` (as a data loader worker would), so GC passes do not scan it during the timing.

Quantization floor: for 4x4 .. 12x12 grids, every placement of the dataset is encoded to the cells its
footprint covers and decoded to the mean cell centre; the table gives the mean over arrangements of the
per-arrangement RMSD, unregistered and after Kabsch registration (as the evaluation scores), in
normalized units. Data: the naturalistic default (`degusta_learn.synth.naturalistic()`), or a small
built-in stand-in when the generator is not available.
"""

from __future__ import annotations

import os

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_k] = "1"

import argparse  # noqa: E402
import gc  # noqa: E402
import io  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from degusta_learn.render import sprites  # noqa: E402
from degusta_learn.render.grid import Grid, quantization_rmsd  # noqa: E402
from degusta_learn.render.lifting import Renderer  # noqa: E402
from degusta_learn.scene import (  # noqa: E402
    Arrangement,
    Dataset,
    Placement,
    default_catalog,
    default_tables,
    make_episodes,
)


def stand_in_dataset(n_participants: int = 40, seed: int = 0) -> Dataset:
    """A small dataset of Western-style settings with noise (used only without the synth generator)."""
    rng = np.random.default_rng(seed)
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    arrangements = []
    for p in range(n_participants):
        picks = {t: int(rng.choice([o.id for o in catalog.of_type(t)])) for t in ("plate", "fork", "knife", "spoon", "cup")}
        layout = {"plate": (0.0, 0.0, 0), "fork": (-0.13, 0.0, 0), "knife": (0.13, 0.0, 0),
                  "spoon": (0.17, 0.0, 0), "cup": (0.15, -0.14, 90)}
        for trial in range(5):
            table = tables[trial % len(tables)]
            cx, cy = table.center
            cx, cy = cx + rng.normal(0, 0.03), cy + rng.normal(0, 0.03)
            pl = [Placement(picks[t], float(cx + dx + rng.normal(0, 0.01)), float(cy + dy + rng.normal(0, 0.01)),
                            float((r + rng.normal(0, 5)) % 360)) for t, (dx, dy, r) in layout.items()]
            arrangements.append(Arrangement(f"p{p:03d}", trial, table.id, tuple(pl)))
    return Dataset(catalog, tables, arrangements, meta={"name": "stand-in", "synthetic": True})


def load_data() -> tuple[Dataset, str]:
    try:
        from degusta_learn.synth import naturalistic
    except ImportError:
        return stand_in_dataset(), "built-in stand-in (SYNTHETIC; synth.naturalistic unavailable)"
    return naturalistic(), "naturalistic default, seed 0 (SYNTHETIC)"


def bench_speed(ds: Dataset, repeats: int) -> list[str]:
    episodes = make_episodes(ds, 4, "test", 0)
    ep = max(episodes, key=lambda e: sum(len(ds.arrangement(e.participant, t).placements) for t in e.context))
    n_obj = sum(len(ds.arrangement(ep.participant, t).placements) for t in ep.context)
    renderer, grid = Renderer.for_dataset(ds, 448), Grid(8, 8)

    def image_set():
        ims = []
        for t in ep.context:
            arr = ds.arrangement(ep.participant, t)
            ims.append(renderer.gma(arr.table, arr.placements, grid))
        ims.append(renderer.table(ds.arrangement(ep.participant, ep.target).table, grid))
        ims += [renderer.gomo(t) for t in ds.catalog.types]
        return ims

    t0 = time.perf_counter()
    ims = image_set()
    cold = time.perf_counter() - t0

    def timed(fn, before=None):
        out = []
        for _ in range(repeats):
            if before:
                before()
            t = time.perf_counter()
            fn()
            out.append((time.perf_counter() - t) * 1e3)
        return statistics.median(out), min(out)

    warm = timed(image_set)
    fresh = timed(image_set, before=sprites._rotated.cache_clear)

    def encode(fmt):
        for im in ims:
            buf = io.BytesIO()
            if fmt == "PNG":
                im.save(buf, format="PNG", compress_level=6)
            else:
                im.save(buf, format="JPEG", quality=90)

    png, jpeg = timed(lambda: encode("PNG")), timed(lambda: encode("JPEG"))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return [
        f"Episode {ep.id}: {len(ep.context)} context images with {n_obj} objects, target table, "
        f"{len(ds.catalog.types)} GoMO sheets = {len(ims)} images of 448 px; {repeats} repeats, one thread.",
        "",
        "| what | median ms | min ms |",
        "|---|---|---|",
        f"| full mogma image set, warm cache (bar: < 20 ms) | {warm[0]:.1f} | {warm[1]:.1f} |",
        f"| same, rotated-sprite cache cleared each repeat (new angles) | {fresh[0]:.1f} | {fresh[1]:.1f} |",
        f"| PNG encoding of the {len(ims)} images (compress_level 6) | {png[0]:.1f} | {png[1]:.1f} |",
        f"| JPEG encoding of the {len(ims)} images (quality 90) | {jpeg[0]:.1f} | {jpeg[1]:.1f} |",
        f"| first (cold) render of the set, incl. drawing sprites and tables | {cold * 1e3:.0f} | |",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} CPUs shared with other jobs "
        f"(1-min load average {load:.1f} at the end of the run), Python {platform.python_version()}.",
    ]


def bench_sizes(ds: Dataset, sizes: list[int], old_filter: bool = False, repeats: int = 3) -> list[str]:
    """size -> ms of the same episode's full mogma image set: cold (sprite and table caches cleared, a new
    Renderer: what a first render at that size costs) and warm (a new Renderer, caches kept; median of `repeats`).
    `old_filter` draws the table rim with Pillow's MinFilter, as before 2026-12-01 (kernel^2 per pixel, and the
    kernel grows with the size: size^4 in all)."""
    import resource

    import numpy as np
    from PIL import Image, ImageFilter

    from degusta_learn.render import tables

    if old_filter:
        tables._min_filter = lambda a, k: np.asarray(Image.fromarray(a).filter(ImageFilter.MinFilter(k)))
    episodes = make_episodes(ds, 4, "test", 0)
    ep = max(episodes, key=lambda e: sum(len(ds.arrangement(e.participant, t).placements) for t in e.context))
    grid = Grid(8, 8)

    def image_set(r: Renderer) -> list:
        ims = [r.gma(ds.arrangement(ep.participant, t).table, ds.arrangement(ep.participant, t).placements, grid)
               for t in ep.context]
        ims.append(r.table(ds.arrangement(ep.participant, ep.target).table, grid))
        return ims + [r.gomo(t) for t in ds.catalog.types]

    lines = ["| size px | cold ms | warm ms | max RSS MB |", "|---:|---:|---:|---:|"]
    for size in sizes:
        for cache in (sprites._sprite, sprites._rotated, tables._table_image):
            cache.cache_clear()
        t = time.perf_counter()
        image_set(Renderer.for_dataset(ds, size))
        cold = (time.perf_counter() - t) * 1e3
        warm = []
        for _ in range(repeats):
            r = Renderer.for_dataset(ds, size)
            t = time.perf_counter()
            image_set(r)
            warm.append((time.perf_counter() - t) * 1e3)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        lines.append(f"| {size} | {cold:.0f} | {statistics.median(warm):.0f} | {rss:.0f} |")
        print(lines[-1], flush=True)
    return lines


def bench_quantization(ds: Dataset) -> list[str]:
    lines = ["| grid | cells | cell size | RMSD (unregistered) | RMSD (Kabsch) |", "|---|---|---|---|---|"]
    for n in (4, 6, 8, 10, 12):
        g = Grid(n, n)
        lines.append(f"| {n}x{n} | {n * n} | {1 / n:.3f} | {quantization_rmsd(ds, g, registered=False):.4f} | "
                     f"{quantization_rmsd(ds, g, registered=True):.4f} |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--quick", action="store_true", help="speed only")
    ap.add_argument("--sizes", help="comma-separated image sizes: time the image set at each (cold and warm) only")
    ap.add_argument("--pillow-minfilter", action="store_true",
                    help="with --sizes: the table rim as drawn before 2026-12-01 (Pillow's MinFilter: size^4)")
    args = ap.parse_args()
    ds, label = load_data()
    gc.freeze()  # the dataset's ~10^5 Python objects would otherwise make every gen-2 GC pass slow
    print(f"Data: {label}; {len(ds.arrangements)} arrangements.\n")
    if args.sizes:
        bench_sizes(ds, [int(x) for x in args.sizes.split(",")], old_filter=args.pillow_minfilter)
        return
    print("\n".join(bench_speed(ds, args.repeats)))
    if not args.quick:
        print()
        print("\n".join(bench_quantization(ds)))


if __name__ == "__main__":
    main()
