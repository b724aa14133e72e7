"""The paper's greedy matching (`matching="paper"`) beside the Hungarian default: hand-computed cases, the fast
path equal to the single one under both rules, the option threaded through evaluate / compare / the CLI, and the
qualitative figure drawing the scores' own pairs."""

import json
import math

import numpy as np
import pytest

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.compare import CompareConfig, MethodEntry
from degusta_learn.evaluate.qualitative import PredictionMark, match_marks, render_side_by_side
from degusta_learn.metrics import SET_PENALTY, match, matched_pairs, score_many, score_prediction
from degusta_learn.metrics.matching import MATCHINGS, greedy_assignment
from degusta_learn.scene import (
    Arrangement,
    Catalog,
    CatalogObject,
    Placement,
    Prediction,
    default_catalog,
    load_dataset,
    make_episodes,
    write_episodes,
    write_predictions,
)

BASE = dict(type="cup", color1="red", color2="red", material1="glass", material2="glass")
# Hamming distances (colours and materials compare as unordered pairs):
#   A-B = 1 (one colour), A-C = 2 (both materials), B-C = 1 + 2 = 3, A-D = 1 (one material), B-D = 2;
#   A2 has A's features under another id (A-A2 = 0).
A, B, C, D, A2 = 0, 1, 2, 3, 4
CAT = Catalog((
    CatalogObject(A, **BASE),
    CatalogObject(B, **{**BASE, "color1": "blue"}),
    CatalogObject(C, **{**BASE, "material1": "metal", "material2": "metal"}),
    CatalogObject(D, **{**BASE, "material1": "metal"}),
    CatalogObject(A2, **BASE),
))


def arrangement(*items) -> Arrangement:
    return Arrangement("p", 0, 0, tuple(Placement(o, x, y) for o, x, y in items))


def pairs(gt, pred, rule):
    return [(p.gt_index, p.pred_index) for p in matched_pairs(CAT, gt, pred, matching=rule)]


def test_greedy_and_hungarian_differ_by_hand():
    # GT [A, B], prediction [B, C]. Hamming D (rows GT, columns prediction):
    #          B   C
    #     A [  1,  2 ]
    #     B [  0,  3 ]
    # Paper: A picks first and takes B (1 < 2); B is left with C (3): total 4, no pair is the same object.
    # Hungarian: A-C + B-B = 2 + 0 = 2 < A-B + B-C = 1 + 3 = 4: B is matched to B, accuracy 1/2.
    gt = arrangement((A, 0.2, 0.5), (B, 0.6, 0.5))
    pred = [Placement(B, 0.6, 0.5), Placement(C, 0.2, 0.5)]  # every object where a true one is
    assert pairs(gt, pred, "paper") == [(0, 0), (1, 1)]
    assert pairs(gt, pred, "hungarian") == [(0, 1), (1, 0)]
    paper, ours = (score_prediction(CAT, gt, pred, matching=rule) for rule in ("paper", "hungarian"))
    assert (paper.object_accuracy, ours.object_accuracy) == (0.0, 0.5)
    # Hungarian pairs lie on top of each other: 0 everywhere.
    assert ours.rmsd_unregistered == 0.0 and ours.rmsd == pytest.approx(0.0, abs=1e-12)
    # Paper pairs A(0.2, 0.5)-B(0.6, 0.5) and B(0.6, 0.5)-C(0.2, 0.5): both 0.4 apart unregistered ...
    assert paper.rmsd_unregistered == pytest.approx(0.4)
    # ... capped at c = 0.2 in the unregistered set RMSD: sqrt((0.2^2 + 0.2^2) / 2) = 0.2 ...
    assert paper.set_rmsd_unregistered == pytest.approx(SET_PENALTY)
    # ... while Kabsch turns the swapped pair by 180 degrees onto the truth (both 0.4 long): 0.
    assert paper.rmsd == pytest.approx(0.0, abs=1e-12) and paper.set_rmsd == pytest.approx(0.0, abs=1e-12)
    assert paper.order_tau == 1.0 and ours.order_tau == -1.0  # pred steps (1, 2) vs (2, 1) in GT order


def test_ties_go_to_the_first_listed_prediction_not_the_nearer():
    # GT [A at (0.2, 0.2)]; prediction [B far, D on top of A]: A-B = A-D = 1, a tie.
    gt = arrangement((A, 0.2, 0.2))
    pred = [Placement(B, 0.9, 0.9), Placement(D, 0.2, 0.2)]
    assert pairs(gt, pred, "paper") == [(0, 0)]  # the first listed
    assert pairs(gt, pred, "hungarian") == [(0, 1)]  # the nearer
    # The same arrangement listed in another order, two objects of identical features (A, A2): every pairing
    # costs 0. The paper's A takes the first listed (A2), leaving A for A2: a visually perfect answer at
    # accuracy 0; the Hungarian tie goes to the nearer positions: accuracy 1.
    gt = arrangement((A, 0.2, 0.2), (A2, 0.8, 0.8))
    pred = [Placement(A2, 0.8, 0.8), Placement(A, 0.2, 0.2)]
    assert pairs(gt, pred, "paper") == [(0, 0), (1, 1)]
    assert pairs(gt, pred, "hungarian") == [(0, 1), (1, 0)]
    paper = score_prediction(CAT, gt, pred, matching="paper")
    assert paper.object_accuracy == 0.0 and paper.rmsd_unregistered == pytest.approx(math.hypot(0.6, 0.6))
    assert score_prediction(CAT, gt, pred).object_accuracy == 1.0


def test_more_predictions_than_ground_truth():
    # GT [A, B]; prediction [C, A, B]. A's row: C 2, A 0, B 1 -> A; B's row of what is left: C 3, B 0 -> B.
    gt = arrangement((A, 0.3, 0.3), (B, 0.7, 0.3))
    pred = [Placement(C, 0.5, 0.8), Placement(A, 0.3, 0.3), Placement(B, 0.7, 0.3)]
    assert pairs(gt, pred, "paper") == [(0, 1), (1, 2)] == pairs(gt, pred, "hungarian")
    s = score_prediction(CAT, gt, pred, matching="paper")
    assert (s.n_matched, s.count_error, s.object_accuracy, s.object_precision) == (2, 1, 1.0, pytest.approx(2 / 3))
    # Two perfect pairs and one extra object: sqrt((0 + 0 + c^2) / 3).
    assert s.set_rmsd == pytest.approx(SET_PENALTY / math.sqrt(3))


def test_fewer_predictions_than_ground_truth_the_first_true_objects_pick():
    # GT [A, B, C]; prediction [B]. Paper: A picks first and takes the only prediction; B and C stay unmatched.
    # Hungarian: B-B (0) beats A-B (1) and C-B (3).
    gt = arrangement((A, 0.2, 0.5), (B, 0.5, 0.5), (C, 0.8, 0.5))
    pred = [Placement(B, 0.5, 0.5)]
    assert pairs(gt, pred, "paper") == [(0, 0)]
    assert pairs(gt, pred, "hungarian") == [(1, 0)]
    assert score_prediction(CAT, gt, pred, matching="paper").object_accuracy == 0.0
    assert score_prediction(CAT, gt, pred).object_accuracy == pytest.approx(1 / 3)
    # Only one pair: Kabsch RMSD 0; two missing objects: sqrt(2/3) c in the set RMSD, under both rules.
    for rule in MATCHINGS:
        s = score_prediction(CAT, gt, pred, matching=rule)
        assert s.rmsd == 0.0 and s.set_rmsd == pytest.approx(math.sqrt(2 / 3) * SET_PENALTY)


def test_empty_and_failed_predictions_score_the_same_under_both_rules():
    gt = arrangement((A, 0.2, 0.5), (B, 0.5, 0.5))
    for rule in MATCHINGS:
        for s in (score_prediction(CAT, gt, [], matching=rule),
                  score_prediction(CAT, gt, [Placement(A, 0.2, 0.5)], failed=True, matching=rule)):
            assert (s.object_accuracy, s.n_matched, s.count_error, s.set_rmsd) == (0.0, 0, 2, SET_PENALTY)
            assert math.isnan(s.rmsd)
        failed = Prediction("e", "p", 0, "m", [Placement(A, 0.2, 0.5)], failed=True)
        assert matched_pairs(CAT, gt, failed, matching=rule) == [] == matched_pairs(CAT, gt, [], matching=rule)
        assert math.isnan(score_prediction(CAT, arrangement(), [Placement(A, 0.5, 0.5)], matching=rule).object_accuracy)


def test_greedy_assignment_batched_by_hand():
    cost = np.array([[[1, 2], [0, 3]],  # the first case above: row 0 takes column 0
                     [[5, 5], [5, 0]],  # a tie: row 0 takes column 0; row 1 gets column 1
                     [[9, 1], [1, 9]]])  # row 0 takes column 1, row 1 column 0
    gi, pi = greedy_assignment(cost)
    assert gi.tolist() == [[0, 1]] * 3 and pi.tolist() == [[0, 1], [0, 1], [1, 0]]
    gi, pi = greedy_assignment(np.zeros((2, 3, 1)))  # one prediction: only the first true object is matched
    assert gi.tolist() == [[0], [0]] and pi.tolist() == [[0], [0]]


def test_match_takes_the_rule():
    gxy, pxy = np.array([[0.2, 0.5], [0.6, 0.5]]), np.array([[0.6, 0.5], [0.2, 0.5]])
    assert [a.tolist() for a in match(CAT, [A, B], [B, C], gxy, pxy, matching="paper")] == [[0, 1], [0, 1]]
    assert [a.tolist() for a in match(CAT, [A, B], [B, C], gxy, pxy)] == [[0, 1], [1, 0]]


def test_unknown_rules_are_refused_listing_the_choices():
    gt = arrangement((A, 0.2, 0.5))
    message = r"^matching: expected one of \['hungarian', 'paper'\], got 'greedy'$"
    for call in (lambda: score_prediction(CAT, gt, [], matching="greedy"),
                 lambda: score_many(CAT, [gt], [[]], matching="greedy"),
                 lambda: matched_pairs(CAT, gt, [], matching="greedy"),
                 lambda: match(CAT, [A], [A], [[0, 0]], [[0, 0]], matching="greedy")):
        with pytest.raises(DegustaError, match=message):
            call()
    with pytest.raises(DegustaError, match=r"^matching: expected one of \['hungarian', 'paper'\], got 'Paper'$"):
        CompareConfig(dataset="d", out="o", methods=[MethodEntry("a", predictions="p")], matching="Paper")


def test_score_many_equals_score_prediction_under_both_rules():
    cat = default_catalog()
    rng = np.random.default_rng(1)
    gts, preds, failed = [], [], []
    for e in range(300):
        n, m = int(rng.integers(1, 7)), int(rng.integers(0, 8))
        ids = rng.choice(125, n, replace=False)
        gt = Arrangement("p", e, 0, tuple(Placement(int(i), *rng.random(2), float(rng.random() * 360)) for i in ids))
        # half the objects from the ground truth (so exact and near matches occur), half at random; repeats allowed
        pool = np.concatenate([ids, rng.choice(125, 3)])
        pl = [Placement(int(i), *rng.random(2), float(rng.random() * 360)) for i in rng.choice(pool, m)]
        gts.append(gt)
        failed.append(bool(rng.random() < 0.1))
        preds.append(Prediction(f"e{e}", "p", e, "m", pl, failed=failed[-1]))
    differ = 0
    for rule in MATCHINGS:
        got = score_many(cat, gts, preds, matching=rule)
        want = [score_prediction(cat, gt, p.placements, failed=f, matching=rule) for gt, p, f in zip(gts, preds, failed)]
        for a, b in zip(got, want):
            for x, y in zip(vars(a).values(), vars(b).values()):
                assert (math.isnan(x) and math.isnan(y)) if isinstance(x, float) and math.isnan(x) else \
                    math.isclose(x, y, rel_tol=1e-12, abs_tol=1e-14)
        if rule == "paper":
            ours = score_many(cat, gts, preds)
            differ = sum(a.object_accuracy != b.object_accuracy for a, b in zip(ours, got))
    assert differ > 10  # the sample does tell the rules apart


def test_match_marks_by_hand():
    gt = arrangement((A, 0.2, 0.5), (B, 0.5, 0.5), (C, 0.8, 0.5))
    pred = [Placement(B, 0.5, 0.5), Placement(D, 0.3, 0.3)]
    # Paper: A's row is B 1, D 1, a tie: the first listed, B; B gets D (2); C picks last and finds nothing left.
    marks = match_marks(CAT, gt, pred, "paper")
    assert marks.predictions == (PredictionMark(1, 1, False), PredictionMark(2, 2, False))
    assert marks.pairs == ((0, 0), (1, 1)) and marks.missed == (3,)
    # Hungarian: B-B 0 + A-D 1 = B-B 0 + C-D 1 = 1 is the least total; D at (0.3, 0.3) is nearer A (0.22) than C
    # (0.54): the first prediction is B's own (step 2), the second A's (step 1), and C is missed.
    marks = match_marks(CAT, gt, pred, "hungarian")
    assert marks.predictions == (PredictionMark(1, 2, True), PredictionMark(2, 1, False)) and marks.missed == (3,)
    failed = Prediction("e", "p", 0, "m", pred, failed=True)  # drawn as the scores see it: nothing matched
    marks = match_marks(CAT, gt, failed)
    assert marks.predictions == (PredictionMark(1, None, False), PredictionMark(2, None, False))
    assert marks.missed == (1, 2, 3) and marks.pairs == ()


def test_the_figure_is_written_and_draws_the_scores_pairs(small_dataset, tmp_path):
    from degusta_learn.render.lifting import Renderer

    ds = small_dataset
    gt = ds.arrangements[0]
    pred = list(reversed(gt.placements))[:-1] + [Placement(gt.placements[0].object, 0.5, 0.5)]  # reordered, moved
    renderer = Renderer.for_dataset(ds, size=128)
    for rule in MATCHINGS:
        marks = match_marks(ds.catalog, gt, pred, rule)
        assert [tuple(p) for p in marks.pairs] == [(p.gt_index, p.pred_index)
                                                  for p in matched_pairs(ds.catalog, gt, pred, matching=rule)]
        path = render_side_by_side(ds, renderer, gt.participant, gt.trial, {"m": (pred, "score"), "none": ([], "-")},
                                   tmp_path / f"{rule}.png", matching=rule)
        assert path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _write(ds, episodes, path):
    """Each prediction: the ground truth without its first object, the rest listed in reverse order."""
    preds = []
    for e in episodes:
        gt = ds.arrangement(e.participant, e.target)
        preds.append(Prediction(e.id, e.participant, e.target, "drop_first", list(reversed(gt.placements[1:]))))
    write_predictions(path, preds)
    return preds


def test_evaluate_and_the_cli_take_the_rule_and_record_it(small_dataset_dir, tmp_path, capsys):
    ds = load_dataset(small_dataset_dir)
    eps = make_episodes(ds, 2, "all")
    write_episodes(tmp_path / "eps.jsonl", eps)
    preds = _write(ds, eps, tmp_path / "p.jsonl")
    gts = [ds.arrangement(p.participant, p.target) for p in preds]
    for rule in MATCHINGS:
        out = tmp_path / f"ev_{rule}"
        assert main(["evaluate", "--dataset", str(small_dataset_dir), "--predictions", str(tmp_path / "p.jsonl"),
                     "--out", str(out), "--bootstrap", "20", "--matching", rule]) == 0, capsys.readouterr().err
        metrics = json.loads((out / "metrics.json").read_text())["drop_first"]
        assert metrics["matching"] == rule
        want = np.mean([s.object_accuracy for s in score_many(ds.catalog, gts, preds, matching=rule)])
        assert metrics["object_accuracy"]["mean"] == pytest.approx(want)
        report = (out / "report.md").read_text()
        assert report.index(f"(`matching: {rule}`)") < report.index("## Results")  # stated above the tables
    # Hungarian recovers every object that is there; the paper's first true object takes someone else's.
    ours, paper = (json.loads((tmp_path / f"ev_{r}" / "metrics.json").read_text())["drop_first"]["object_accuracy"]
                   ["mean"] for r in ("hungarian", "paper"))
    assert paper < ours
    assert main(["evaluate", "--dataset", str(small_dataset_dir), "--predictions", str(tmp_path / "p.jsonl"),
                 "--out", str(tmp_path / "bad"), "--matching", "greedy"]) == 2
    assert "invalid choice: 'greedy' (choose from" in capsys.readouterr().err


def test_compare_scores_records_and_draws_with_its_rule(small_dataset_dir, tmp_path):
    from degusta_learn.config import load_config
    from degusta_learn.evaluate.compare import compare

    ds = load_dataset(small_dataset_dir)
    eps = make_episodes(ds, 2, "all")[:6]
    write_episodes(tmp_path / "eps.jsonl", eps)
    _write(ds, eps, tmp_path / "p.jsonl")
    cfg = CompareConfig(dataset=str(small_dataset_dir), out=str(tmp_path / "cmp"), episodes=str(tmp_path / "eps.jsonl"),
                        methods=[MethodEntry("drop_first", predictions=str(tmp_path / "p.jsonl"))], n_bootstrap=20,
                        qualitative=0, render_size=64, matching="paper")
    out = compare(cfg, log=lambda m: None).out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["matching"] == "paper" and metrics["methods"]["drop_first"]["matching"] == "paper"
    report = (out / "report.md").read_text()
    assert "Matching: the paper's greedy rule" in report and "(matching: paper)" in report  # the figures' note
    assert sorted(p.name for p in (out / "qualitative").iterdir()) == ["00.png", "01.png"]  # best and worst
    assert CompareConfig(dataset="d", out="o", methods=[MethodEntry("a", predictions="p")]).matching == "hungarian"
    (tmp_path / "c.yaml").write_text("dataset: d\nout: o\nmethods: [{name: a, predictions: p}]\n")
    with pytest.raises(DegustaError, match=r"matching: expected one of \['hungarian', 'paper'\]"):
        load_config(CompareConfig, tmp_path / "c.yaml", ["matching=greedy"])
