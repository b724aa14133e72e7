"""Plausible tables: the rules, the default keeping them over many seeds, the legacy tables' violations (pinned)."""

import functools
import hashlib
import json

import pytest

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.synth import generate_dataset, naturalistic_with_styles
from degusta_learn.synth.plausible import RULES, core_mask, dataset_violations, style_violations, violations

SEEDS = range(60)
PER_SEED = 12  # participants per seed: 720 styles and 3600 tables in all


@functools.lru_cache(maxsize=2)
def many(plausible: bool):
    return [naturalistic_with_styles(seed, PER_SEED, plausible=plausible) for seed in SEEDS]


def test_rules_on_hand_made_tables():
    assert violations(["plate"] * 5 + ["knife"]) == ("plates", "utensils")  # p000 of the default
    assert violations(["plate", "fork", "knife", "spoon", "cup"]) == ()
    assert violations(["plate", "fork", "fork", "knife", "spoon", "spoon", "cup"]) == ()  # salad fork, dessert spoon
    assert violations(["plate", "plate", "cup", "cup", "cup", "fork", "fork"]) == ("cups",)
    assert violations(["knife", "knife", "cup"]) == ("knives",)  # no plate: set for one
    assert violations(["fork"] * 3 + ["spoon"] * 3 + ["plate"]) == ("forks", "spoons")
    assert violations(["plate", "plate", "fork"]) == ("utensils",)
    assert violations(["plate"] * 4 + ["fork"] * 4) == ()


def test_core_mask_keeps_plates_and_a_utensil_per_plate():
    assert core_mask(["cup", "spoon", "cup", "plate", "fork", "plate", "knife"]) == \
        [True, True, True, True, True, True, False]  # first 3, both plates; one utensil in the first 3, one more
    assert core_mask(["plate", "plate", "cup", "cup", "fork", "spoon"]) == [True, True, True, False, True, True]
    assert core_mask(["fork", "cup", "cup", "spoon"]) == [True, True, True, False]


def test_the_legacy_tables_break_the_rules_with_these_counts():
    ds, styles = naturalistic_with_styles(0, plausible=False)
    p000 = [[ds.catalog[o].type for o in a.objects] for a in ds.arrangements if a.participant == "p000"]
    assert all(sorted(t) == ["knife"] + ["plate"] * 5 for t in p000)  # five plates and a knife, every trial
    default = [[d.catalog[o].type for o in a.objects] for d in [naturalistic_with_styles(0, 1)[0]]
               for a in d.arrangements]
    assert all(violations(t) == () for t in default) and all(t.count("plate") <= 4 for t in default)
    # tables breaking each rule, participants with such a table (of 995 tables, 199 participants)
    assert dataset_violations(ds) == {"plates": (6, 2), "cups": (94, 24), "knives": (40, 9), "forks": (17, 5),
                                      "spoons": (8, 3), "utensils": (66, 19), "any": (209, 52)}
    broken = {s.participant for s in styles if style_violations(s)}
    assert {s.template for s in styles if s.participant in broken} == {"row", "freeform"}
    # over the many seeds too: a fifth of the tables, from row and freeform only
    tables = [(s.template, violations([ds.catalog[o].type for o in a.objects]))
              for ds, sts in many(False) for s in sts for a in ds.arrangements if a.participant == s.participant]
    bad = [t for t, v in tables if v]
    assert 0.1 < len(bad) / len(tables) < 0.35 and set(bad) == {"row", "freeform"}


def test_the_plausible_generator_keeps_every_rule_over_many_seeds():
    n_tables, templates = 0, set()
    for ds, styles in many(True):
        assert ds.meta["plausible"] is True
        for s in styles:
            assert style_violations(s) == (), (ds.meta["seed"], s.participant, [x.type for x in s.slots])
            templates.add(s.template)
        for a in ds.arrangements:
            types = [ds.catalog[o].type for o in a.objects]
            assert violations(types) == (), (ds.meta["seed"], a.participant, a.trial, types)
            assert len(types) >= 3 and len(set(a.objects)) == len(types)
            n_tables += 1
        assert dataset_violations(ds) == {rule: (0, 0) for rule in (*RULES, "any")}
    assert n_tables == len(SEEDS) * PER_SEED * 5 and {"row", "freeform"} <= templates


def test_plausible_changes_only_row_and_freeform_participants():
    for (d0, s0), (d1, s1) in zip(many(False), many(True)):
        for a, b in zip(s0, s1):
            if a.template in ("row", "freeform"):
                assert b.template == a.template
                continue
            assert a == b
            assert [x.to_json() for x in d0.arrangements if x.participant == a.participant] == \
                [x.to_json() for x in d1.arrangements if x.participant == b.participant]


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_default_and_the_legacy_files_are_pinned(tmp_path, capsys):
    out = generate_dataset("naturalistic", tmp_path / "d")
    # the default (seed 0): every table plausible; the numbers of README and RESULTS are measured on these files
    assert _sha(out / "arrangements.jsonl") == "dc0c2cda421399f4d7c26463bd8953a84b8379774c921f553475dffff42e1909"
    assert _sha(out / "latent_styles.json") == "39a4ab7a266b251ffd2d5815c9be19243e94d017b34bc24d8bc5c677a7ad3559"
    assert _sha(out / "meta.json") == "656f7828581ee265eecb1ad30b316caa185f08a58327128f1cad66ad36368746"
    meta = json.loads((out / "meta.json").read_text())
    assert meta["plausible"] is True and "plausibility rules" in meta["description"]
    # --legacy: the default as it was before every table kept the rules, byte for byte
    assert main(["data", "generate", "naturalistic", "--legacy", "--out", str(tmp_path / "legacy")]) == 0
    assert "legacy tables" in capsys.readouterr().out
    legacy = tmp_path / "legacy"
    assert _sha(legacy / "arrangements.jsonl") == "aae2123dca77572ad620c48cb929b1733b116ca714c00ca14acb176f3899706f"
    assert _sha(legacy / "latent_styles.json") == "e3bc403a09e044c1e9a19515c9c8af929450dd58fc01fbe7e9ac6efa9cac691e"
    assert _sha(legacy / "meta.json") == "0d0a0e1a1e1f29b528c8db2780fb5ab83e11c2313a60ccd9c9b8c2e1f2bf8ba8"
    assert "plausible" not in json.loads((legacy / "meta.json").read_text())
    for name in ("catalog.json", "tables.json"):  # the same objects and tables: the shipped base saw these
        assert _sha(legacy / name) == _sha(out / name)


def test_an_option_the_generator_cannot_honour_is_refused(tmp_path, capsys):
    with pytest.raises(DegustaError, match="legacy: only the naturalistic generator"):
        generate_dataset("simulated", tmp_path / "s", legacy=True)
    assert main(["data", "generate", "simulated", "--legacy", "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "legacy" in err
    assert not (tmp_path / "s").exists()
