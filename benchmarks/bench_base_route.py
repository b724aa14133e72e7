"""Rows of seed-averaged predictions with participant-clustered intervals and paired tests; a base's record.

What a tiny base's route is measured with when it is rebuilt (docs/tiny_base.md, "Shipping a rebuilt base"): each
row is one method's predictions files on the same episodes, one file per training seed; a row's per-episode score
is the mean over its seeds (nan where no seed scored it), its intervals resample participants, and each `--pair A B`
is the paired, participant-clustered difference mean(A - B) (metrics.paired_bootstrap, as `degusta compare`
reports). Scoring is `degusta evaluate`'s (evaluate.scoring). Every file must cover the same episodes.

With `--record BASE --section validation|test` the rows and pairs are written into `BASE/selection.json` under that
section (the other sections kept), with `--protocol` (how the build was chosen) when given; the model card
(`pretrain.export.write_card`) shows them. The test section may be written once: a second `--section test` is
refused unless `--replace-test` says why the first is withdrawn.

Usage:
    python benchmarks/bench_base_route.py --dataset data/naturalistic --split val \
        --row "images + text=O/val_both_s0.jsonl,O/val_both_s1.jsonl,O/val_both_s2.jsonl" \
        --row "text only=O/val_text_s0.jsonl,O/val_text_s1.jsonl,O/val_text_s2.jsonl" \
        --pair "images + text" "text only" --record runs/tiny_vlm_base --section validation
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import sys
from pathlib import Path

import numpy as np

from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.scoring import score_file
from degusta_learn.files.jsonio import atomic_write_json
from degusta_learn.metrics import bootstrap_ci, paired_bootstrap
from degusta_learn.pretrain.export import SELECTION
from degusta_learn.scene import load_dataset, make_episodes

FIELDS = ("set_rmsd", "object_accuracy", "rmsd", "count_error", "order_tau")
"""The columns of a row: set RMSD (the ranking), object accuracy and Kabsch RMSD (the paper's), count error, order."""
PAIRED = ("set_rmsd", "object_accuracy")
SECTIONS = ("validation", "test")


def parse_row(text: str) -> tuple[str, list[Path]]:
    """'NAME=FILE[,FILE...]' -> (name, files)."""
    name, sep, files = text.partition("=")
    paths = [Path(f) for f in files.split(",") if f.strip()]
    if not sep or not name.strip() or not paths:
        raise SystemExit(f"--row {text!r}: expected NAME=FILE[,FILE...]")
    for p in paths:
        if not p.is_file():
            raise SystemExit(f"--row {name}: {p}: no such file")
    return name.strip(), paths


def seed_means(ds, episodes: dict, files: list[Path]) -> dict[str, dict[str, float]]:
    """{episode: {field: mean over the files}} for one row (nan-mean; nan where no file scored the field)."""
    per_file = []
    for path in files:
        try:
            rows = score_file(ds, path, episodes, note=lambda text: print(f"note: {text}", file=sys.stderr))
        except DegustaError as e:
            raise SystemExit(str(e)) from None
        per_file.append({r.episode: r for r in rows})
    out = {}
    for e in episodes:
        vals = {f: [float(getattr(rows[e], f)) for rows in per_file] for f in FIELDS}
        out[e] = {f: (float(np.nanmean(v)) if np.isfinite(v).any() else math.nan) for f, v in vals.items()}
    return out


def _num(v: float) -> float | None:
    """A finite value rounded for the record; None (JSON null) where it is undefined."""
    return round(float(v), 4) if math.isfinite(v) else None


def measure(ds, episodes: dict, rows: dict[str, list[Path]], pairs: list[tuple[str, str]], n_bootstrap: int) -> dict:
    """{"rows": [...], "pairs": [...]} (see the module docstring)."""
    order = sorted(episodes)
    people = [episodes[e].participant for e in order]
    scores = {name: seed_means(ds, episodes, files) for name, files in rows.items()}
    out_rows = []
    for name, files in rows.items():
        entry = {"name": name, "files": len(files)}
        for f in FIELDS:
            mean, lo, hi = bootstrap_ci([scores[name][e][f] for e in order], n_bootstrap, 0, clusters=people)
            entry[f] = [_num(mean), _num(lo), _num(hi)]
        out_rows.append(entry)
    out_pairs = []
    for a, b in pairs:
        entry = {"a": a, "b": b}
        for f in PAIRED:
            d = paired_bootstrap([scores[a][e][f] for e in order], [scores[b][e][f] for e in order], n_bootstrap, 0,
                                 clusters=people)
            entry[f] = {k: _num(v) for k, v in d.items()}
        out_pairs.append(entry)
    return {"episodes": len(order), "participants": len(set(people)), "rows": out_rows, "pairs": out_pairs}


def _ci(v: list, digits: int = 3) -> str:
    mean, lo, hi = v
    if mean is None:
        return "-"
    return f"{mean:.{digits}f}" if lo is None else f"{mean:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def markdown(result: dict) -> list[str]:
    lines = ["| row | seeds | set RMSD [95% CI] | object accuracy (paper) | Kabsch RMSD (paper) | count error | order τ |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(f"| {r['name']} | {r['files']} | {_ci(r['set_rmsd'])} | {_ci(r['object_accuracy'])} | "
                     f"{_ci(r['rmsd'])} | {_ci(r['count_error'], 2)} | {_ci(r['order_tau'][:1] + [None, None], 2)} |")
    for p in result["pairs"]:
        parts = []
        for f in PAIRED:
            d = p[f]
            if d["diff"] is None or d["p_value"] is None:
                parts.append(f"{f} -")
                continue
            pv = "p < 0.001" if d["p_value"] < 0.001 else f"p {d['p_value']:.3f}"
            parts.append(f"{f} {d['diff']:+.4f} [{d['lo']:+.4f}, {d['hi']:+.4f}], {pv}")
        lines.append(f"\n{p['a']} minus {p['b']}: " + "; ".join(parts))
    return lines


def record(base: Path, section: str, result: dict, protocol: str | None, replace_test: str | None) -> Path:
    """Write `result` into base/selection.json's `section` (atomically; the other sections kept)."""
    path = base / SELECTION
    data = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}
    if section == "test" and "test" in data and not replace_test:
        raise SystemExit(f"{path}: the test split was measured already ({data['test'].get('date')}); the test is "
                         "looked at once. --replace-test REASON withdraws the first look and says why")
    if section == "test" and "test" in data:
        data.setdefault("withdrawn_test_looks", []).append({**data["test"], "withdrawn_because": replace_test})
    if protocol:
        data["protocol"] = protocol
    data[section] = {**result, "date": datetime.date.today().isoformat()}
    atomic_write_json(path, data)  # refuses a value the strict reader would not take back (NaN)
    return path


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", type=Path, default=Path("data/naturalistic"))
    ap.add_argument("--split", choices=("val", "test"), required=True)
    ap.add_argument("--context", type=int, default=4)
    ap.add_argument("--split-seed", type=int, default=0)
    ap.add_argument("--row", action="append", required=True, help="NAME=FILE[,FILE...]: one file per training seed")
    ap.add_argument("--pair", nargs=2, action="append", default=[], metavar=("A", "B"), help="paired test of A - B")
    ap.add_argument("--n-bootstrap", type=int, default=2000)
    ap.add_argument("--record", type=Path, default=None, help="a base folder: write the result into its selection.json")
    ap.add_argument("--section", choices=SECTIONS, default=None, help="with --record: which section")
    ap.add_argument("--protocol", default=None, help="with --record: how the build was chosen (one paragraph)")
    ap.add_argument("--replace-test", default=None, metavar="REASON")
    args = ap.parse_args(argv)
    rows = dict(parse_row(r) for r in args.row)
    if len(rows) != len(args.row):
        ap.error("--row: two rows have the same name")
    for a, b in args.pair:
        for name in (a, b):
            if name not in rows:
                ap.error(f"--pair: {name!r} is not a --row name ({sorted(rows)})")
    if args.record and args.section is None:
        ap.error("--record needs --section validation|test")
    if args.record and {"val": "validation", "test": "test"}[args.split] != args.section:
        ap.error(f"--section {args.section} with --split {args.split}: the section names the split it measures")
    ds = load_dataset(args.dataset)
    episodes = {e.id: e for e in make_episodes(ds, args.context, args.split, args.split_seed)}
    result = measure(ds, episodes, rows, [tuple(p) for p in args.pair], args.n_bootstrap)
    result.update(split=args.split, context=args.context, split_seed=args.split_seed, dataset=str(args.dataset))
    print("\n".join(markdown(result)))
    if args.record:
        print(f"recorded: {record(args.record, args.section, result, args.protocol, args.replace_test)}")


if __name__ == "__main__":
    main()
