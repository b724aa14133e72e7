"""Hardening, second pass: user paths that made `pathlib` raise, non-UTF-8 names in records, YAML 1.1 numbers,
`~` in path keys, and quickstart writing into a user's folder.

1. Paths (`files.paths.check_path`, the one check of every user path: CLI path flags, config path keys, dataset
   folders, readers and writers): a NUL byte, a 300-byte name, a 5,000-byte path, a path through a file, a broken
   symbolic link, an unknown `~user` are one line, exit 2, naming the flag or key and the path; nothing written.
2. Encodings: a non-UTF-8 path is refused up front (the toolkit writes paths into UTF-8 records it must read
   back); no JSON writer writes a record its reader refuses; file identities (`stat_tree`) stay UTF-8.
3. YAML 1.2 numbers (`config._BoundedLoader`, files and `--set` alike): `010` is 10, `0o10` 8, `0x10` 16, `1e3` a
   float; `1:30`, `1_000`, `0b10`, yes/no/on/off are text, so a number or boolean key refuses them naming the key.
   `~` is expanded in every path key (`config.PATH_KEYS`) and path flag.
4. quickstart writes only into a new or empty folder, or one holding its marker (`.degusta_quickstart.json`).

Every CLI case runs `degusta_learn.cli.main` in-process; no case trains or renders (quickstart's work is stubbed).
The permission case needs a non-root user (root may search any folder): it is skipped as root, and a unit case
checks the message with a stubbed `os.stat`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import typing
from pathlib import Path

import pytest
import yaml
from conftest import make_small_dataset

from degusta_learn import cli
from degusta_learn.config import PATH_KEYS, dump_yaml, load_config, path_key, read_yaml
from degusta_learn.errors import DegustaError
from degusta_learn.files.guard import check_output_file
from degusta_learn.files.identity import stat_tree
from degusta_learn.files.jsonio import atomic_write_json, atomic_write_jsonl, read_json, read_jsonl
from degusta_learn.files.paths import check_path, path_problem, user_path
from degusta_learn.scene import load_dataset, save_dataset

BAD = os.fsdecode(b"\xff\xfe")  # a non-UTF-8 name as Python has it from argv or os.listdir (surrogate escapes)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A dataset, a predictions file, an episodes file, a predict and a compare config, a user's file."""
    root = tmp_path_factory.mktemp("paths2")
    ds = save_dataset(make_small_dataset(n_participants=5, n_trials=4), root / "ds")
    (root / "file.txt").write_text("a user's file\n")
    predict = root / "predict.yaml"
    predict.write_text(yaml.safe_dump({"method": "random", "dataset": str(ds), "out": str(root / "pred.jsonl"),
                                       "context": 2, "split": "all"}))
    assert cli.main(["predict", "--config", str(predict)]) == 0
    assert cli.main(["data", "episodes", str(ds), "--context", "2", "--split", "all", "--out",
                     str(root / "eps.jsonl")]) == 0
    compare = root / "compare.yaml"
    compare.write_text(yaml.safe_dump({"dataset": str(ds), "out": str(root / "cmp"), "contexts": [2], "split": "all",
                                       "n_bootstrap": 10, "qualitative": 0,
                                       "methods": [{"name": "rnd", "predictions": str(root / "pred.jsonl")}]}))
    return {"root": root, "ds": ds, "pred": root / "pred.jsonl", "eps": root / "eps.jsonl", "predict": predict,
            "compare": compare}


def snapshot(folder: Path) -> dict:
    out = {}
    for dirpath, dirs, files in os.walk(folder):
        for name in files + dirs:
            p = os.path.join(dirpath, name)
            out[p] = Path(p).read_bytes() if os.path.isfile(p) and not os.path.islink(p) else None
    return out


def refused(capsys, argv) -> str:
    code = cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, (code, err)
    assert len(lines) == 1 and lines[0].startswith("degusta: error: ") and "Traceback" not in err, err
    return lines[0]


# ----------------------------------------------------------------------------- 1. paths that raised

def variants(root: Path, base: Path, suffix: str) -> dict[str, tuple[str, str]]:
    """name -> (path text, what of it the message must show); `root` holds the user's file.txt."""
    base.mkdir(parents=True, exist_ok=True)
    dangling = base / f"dangling{suffix}"
    if not os.path.lexists(dangling):
        os.symlink(base / f"nowhere{suffix}", dangling)
    return {
        "nul": (f"{base}/a\0b{suffix}", "a\\x00b"),
        "name of 300 bytes": (f"{base}/{'x' * 300}{suffix}", "x" * 40),
        "path of 5,000 bytes": (f"{base}/" + "d/" * 2500 + f"f{suffix}", "d/d/d/d"),
        "through a file": (f"{root}/file.txt/x{suffix}", "file.txt"),
        "broken link": (str(dangling), "dangling"),
        "unknown ~user": (f"~nosuchuser_dg/x{suffix}", "~nosuchuser_dg"),
    }


def _set(cfg_key, key):
    return lambda w, p: ["predict" if cfg_key == "predict" else "compare", "--config", w[cfg_key], "--set", f"{key}={p}"]


def _method_config(w, p):
    cfg = w["root"] / "cmp_method.yaml"
    data = yaml.safe_load(w["compare"].read_text())
    cfg.write_text(yaml.safe_dump({**data, "methods": [{"name": "rnd", "config": p}]}))
    return ["compare", "--config", cfg]


SLOTS = {  # slot -> (what the message names, suffix, argv)
    "data generate --out": ("--out", "", lambda w, p: ["data", "generate", "simulated", "--out", p]),
    "data validate DIR": ("dir", "", lambda w, p: ["data", "validate", p]),
    "data episodes DIR": ("dir", "", lambda w, p: ["data", "episodes", p, "--context", "2", "--out",
                                                   w["root"] / "e.jsonl"]),
    "data episodes --out": ("--out", ".jsonl", lambda w, p: ["data", "episodes", w["ds"], "--context", "2", "--out", p]),
    "predict --config": ("--config", ".yaml", lambda w, p: ["predict", "--config", p]),
    "predict dataset": ("dataset", "", _set("predict", "dataset")),
    "predict out": ("out", ".jsonl", _set("predict", "out")),
    "predict episodes": ("episodes", ".jsonl", _set("predict", "episodes")),
    "evaluate --dataset": ("--dataset", "", lambda w, p: ["evaluate", "--dataset", p, "--predictions", w["pred"],
                                                         "--out", w["root"] / "ev"]),
    "evaluate --predictions": ("--predictions", ".jsonl", lambda w, p: ["evaluate", "--dataset", w["ds"],
                                                                       "--predictions", p, "--out", w["root"] / "ev"]),
    "evaluate --episodes": ("--episodes", ".jsonl", lambda w, p: ["evaluate", "--dataset", w["ds"], "--predictions",
                                                                 w["pred"], "--episodes", p, "--out", w["root"] / "ev"]),
    "evaluate --out": ("--out", "", lambda w, p: ["evaluate", "--dataset", w["ds"], "--predictions", w["pred"],
                                                 "--out", p]),
    "compare --config": ("--config", ".yaml", lambda w, p: ["compare", "--config", p]),
    "compare dataset": ("dataset", "", _set("compare", "dataset")),
    "compare out": ("out", "", _set("compare", "out")),
    "compare episodes": ("episodes", ".jsonl", _set("compare", "episodes")),
    "compare methods[0].config": ("methods[0].config", ".yaml", _method_config),
    "render catalog DATASET": ("dataset", "", lambda w, p: ["render", "catalog", p, "--out", w["root"] / "c.png"]),
    "render catalog --out": ("--out", ".png", lambda w, p: ["render", "catalog", w["ds"], "--out", p]),
    "quickstart --out": ("--out", "", lambda w, p: ["quickstart", "--out", p, "--small"]),
    "configs copy DEST": ("dest", "", lambda w, p: ["configs", "copy", "learned_cpu", p]),
}


VARIANTS = ["nul", "name of 300 bytes", "path of 5,000 bytes", "through a file", "broken link", "unknown ~user"]


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("slot", list(SLOTS))
def test_a_bad_path_is_one_line_naming_the_flag_or_key_and_nothing_is_written(slot, variant, world, tmp_path,
                                                                              monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # a literal '~nosuchuser_dg' folder would land here
    key, suffix, argv = SLOTS[slot]
    path, shown = variants(world["root"], world["root"] / "v" / slot.replace(" ", "_"), suffix)[variant]
    args = argv(world, path)
    before = snapshot(world["root"])
    line = refused(capsys, args)
    assert key in line and shown in line, line
    assert snapshot(world["root"]) == before
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("key", ["trainer.run_dir", "dataset", "model.name"])
def test_train_config_path_keys_are_checked_when_the_config_loads(key, world, capsys):
    from degusta_learn.finetune.config import FinetuneConfig

    for path, shown in (("a\0b", "a\\x00b"), ("x" * 300, "x" * 40), (f"{world['root']}/file.txt/x", "file.txt")):
        with pytest.raises(DegustaError) as e:
            load_config(FinetuneConfig, None, [f"{key}={path}"])
        assert str(e.value).startswith(f"config: {key}: ") and shown in str(e.value) and "\n" not in str(e.value)


def test_library_entry_points_say_one_line_not_oserror(world, tmp_path):
    from degusta_learn.evaluate.compare import CompareConfig
    from degusta_learn.files.folders import OutputKind, write_folder

    kind = OutputKind("test output", ("a.txt",))
    calls = (load_dataset, read_json, lambda p: list(read_jsonl(p)), lambda p: atomic_write_json(p, {}),
             check_output_file, lambda p: write_folder(p, kind).__enter__(), lambda p: user_path(p, "--x"),
             lambda p: load_config(CompareConfig, p))
    for bad in ("a\0b", str(tmp_path / ("x" * 300)), str(tmp_path / ("d/" * 2500)), f"{world['root']}/file.txt/x"):
        for call in calls:
            with pytest.raises(DegustaError):
                call(bad)
    assert not list(tmp_path.iterdir())


def test_a_record_of_paths_as_they_were_is_text_checked_not_probed(world):
    """A fine-tuning record names the dataset it was trained on; that folder may have moved since."""
    from degusta_learn.config import from_dict
    from degusta_learn.vlm.record import TrainingData

    moved = f"{world['root']}/file.txt/ds"
    data = {"dataset": moved, "fingerprint": "f", "seed": 0, "contexts": [4], "train_participants": [],
            "val_participants": []}
    assert from_dict(TrainingData, data, probe_paths=False).dataset == moved
    with pytest.raises(DegustaError, match="dataset: .*file.txt, is a file"):
        from_dict(TrainingData, data)
    with pytest.raises(DegustaError, match="NUL byte"):
        from_dict(TrainingData, {**data, "dataset": "a\0b"}, probe_paths=False)


@pytest.mark.skipif(os.geteuid() == 0, reason="root may search any folder: the permission case needs another user")
def test_a_folder_that_may_not_be_searched(world, tmp_path, capsys):
    locked = tmp_path / "locked"
    (locked / "inner").mkdir(parents=True)
    locked.chmod(0)
    try:
        line = refused(capsys, ["data", "validate", locked / "inner" / "ds"])
        assert "dir" in line and "permission denied" in line
    finally:
        locked.chmod(0o755)


def test_permission_denied_message(monkeypatch):
    def denied(*a, **k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "stat", denied)
    assert "permission denied" in path_problem("/somewhere/x")


def test_tilde_is_expanded_in_path_flags_and_path_keys(world, tmp_path, monkeypatch, capsys):
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(tmp_path)
    shutil.copytree(world["ds"], home / "ds")
    assert cli.main(["predict", "--config", str(world["predict"]), "--set", "dataset=~/ds",
                     "--set", "out=~/runs/p.jsonl"]) == 0
    assert (home / "runs" / "p.jsonl").is_file()
    assert cli.main(["data", "episodes", "--context", "2", "--split", "all", "~/ds", "--out=~/eps.jsonl"]) == 0
    assert (home / "eps.jsonl").is_file()
    assert cli.main(["evaluate", "--dataset=~/ds", "--predictions", "~/runs/p.jsonl", "--out=~/ev",
                     "--bootstrap", "5"]) == 0
    assert (home / "ev" / "metrics.json").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith("~")]  # never a literal '~' folder
    assert check_path("~")[0] == str(home)
    assert all(path_key(k) for k in ("dataset", "trainer.run_dir", "methods[0].config", "model.name", "model.adapter"))
    assert not any(path_key(k) for k in ("method", "backend.name", "title", "trainer.run_name"))


# ----------------------------------------------------------------------------- 2. encodings

def test_a_non_utf8_path_is_refused_up_front(world, tmp_path, capsys):
    bad_ds = tmp_path / f"ds{BAD}"
    shutil.copytree(world["ds"], bad_ds)
    link = tmp_path / "ds_link"  # a UTF-8 name that resolves into it
    link.symlink_to(bad_ds)
    before = snapshot(tmp_path)
    cases = [
        (["data", "validate", bad_ds], "dir"),
        (["data", "episodes", world["ds"], "--context", "2", "--out", tmp_path / f"e{BAD}.jsonl"], "--out"),
        (["evaluate", "--dataset", link, "--predictions", world["pred"], "--out", tmp_path / "ev"], "--dataset"),
        (["predict", "--config", world["predict"], "--set", f"dataset={bad_ds}"], "dataset"),
        (["predict", "--config", world["predict"], "--set", f"out={tmp_path / BAD / 'p.jsonl'}"], "out"),
        (["compare", "--config", world["compare"], "--set", f"out={tmp_path / BAD}"], "out"),
        (["quickstart", "--out", tmp_path / f"qs{BAD}"], "--out"),
        (["compare", "--config", world["compare"], "--set", f"title=report{BAD}"], "title"),  # any text key
    ]
    for argv, key in cases:
        line = refused(capsys, argv)
        assert key in line and "not UTF-8 (byte 0xff)" in line and "\\udcff" in line, line
    assert snapshot(tmp_path) == before


def test_no_json_writer_writes_a_record_its_reader_refuses(tmp_path):
    for write in (atomic_write_json, lambda p, o: atomic_write_jsonl(p, [{"ok": 1}, o])):
        target = tmp_path / "record.json"
        with pytest.raises(DegustaError, match=r"field 'trained_on.dataset' is not UTF-8 \(byte 0xff\)"):
            write(target, {"trained_on": {"dataset": f"/data/{BAD}"}})
        assert not list(tmp_path.iterdir())  # nothing written, no temporary file left
    atomic_write_json(tmp_path / "fine.json", {"dataset": "/data/café \\udcff"})  # UTF-8 text, a literal backslash
    assert read_json(tmp_path / "fine.json") == {"dataset": "/data/café \\udcff"}


def test_a_yaml_lone_surrogate_escape_is_refused_naming_the_key(tmp_path):
    from degusta_learn.evaluate.compare import CompareConfig

    p = tmp_path / "c.yaml"
    p.write_text('dataset: d\nout: o\ntitle: "x\\udcff"\nmethods: [{name: a, predictions: p.jsonl}]\n')
    with pytest.raises(DegustaError, match=r"c.yaml: title: .*not UTF-8 \(byte 0xff\)"):
        load_config(CompareConfig, p)


def test_file_identities_of_non_utf8_names_stay_readable(tmp_path):
    folder = tmp_path / "pictures"
    folder.mkdir()
    (folder / f"{BAD}.png").write_bytes(b"x")
    (folder / "café.png").write_bytes(b"y")
    tree = stat_tree(folder)
    assert sorted(name for name, *_ in tree) == ["\\xff\\xfe.png", "café.png"]
    atomic_write_json(tmp_path / "fingerprint.json", {"files": tree})
    assert read_json(tmp_path / "fingerprint.json")["files"] == tree


# ----------------------------------------------------------------------------- 3. YAML 1.2 numbers

SEEDS = [("010", 10), ("007", 7), ("0o10", 8), ("0x10", 16), ("+12", 12), ("-0", 0), ("12", 12),
         ("1:30", None), ("1_000", None), ("0b10", None), ("1e3", None), ("yes", None), ("on", None),
         (".inf", None), ("2024-01-05", None), ("'010'", None)]


@pytest.mark.parametrize("how", ["file", "--set"])
@pytest.mark.parametrize("text,want", SEEDS)
def test_seeds_are_read_as_yaml_1_2(text, want, how, world, tmp_path):
    from degusta_learn.methods import build_config, get_method

    if how == "file":
        path = tmp_path / "p.yaml"
        path.write_text(f"method: random\ndataset: {world['ds']}\nout: o.jsonl\nseed: {text}\n")
        load = lambda: build_config(path, [], "method", get_method)[1].seed  # noqa: E731
    else:
        load = lambda: build_config(world["predict"], [f"seed={text}"], "method", get_method)[1].seed  # noqa: E731
    if want is None:
        with pytest.raises(DegustaError) as e:
            load()
        assert ": seed: expected" in str(e.value) and "\n" not in str(e.value)
    else:
        assert load() == want


@pytest.mark.parametrize("section,key,text,want", [
    ("data", "group_by_length", "true", True), ("data", "group_by_length", "False", False),
    ("data", "group_by_length", "TRUE", True), ("data", "group_by_length", "yes", None),
    ("data", "group_by_length", "off", None), ("data", "group_by_length", "y", None),
    ("optim", "lr", "1e-3", 0.001), ("optim", "lr", "6E-3", 0.006), ("optim", "lr", ".5", 0.5),
    ("optim", "lr", "010", 10.0), ("optim", "lr", "1:30.5", None), ("optim", "lr", "1_0.5", None),
    ("optim", "lr", ".nan", None), ("optim", "lr", "-.inf", None),
])
def test_booleans_and_floats_are_read_as_yaml_1_2(section, key, text, want, tmp_path):
    from degusta_learn.finetune.config import FinetuneConfig

    path = tmp_path / "f.yaml"
    path.write_text(f"{section}:\n  {key}: {text}\n")
    for load in (lambda: load_config(FinetuneConfig, path), lambda: load_config(FinetuneConfig, None,
                                                                               [f"{section}.{key}={text}"])):
        if want is None:
            with pytest.raises(DegustaError, match=f"{section}.{key}: expected"):
                getattr(getattr(load(), section), key)
        else:
            got = getattr(getattr(load(), section), key)
            assert got == want and type(got) is type(want)


def test_the_refusals_say_what_yaml_1_1_read_differently(world):
    from degusta_learn.finetune.config import FinetuneConfig
    from degusta_learn.methods import build_config, get_method

    with pytest.raises(DegustaError, match="base-60 1:30"):
        build_config(world["predict"], ["seed=1:30"], "method", get_method)
    with pytest.raises(DegustaError, match="only true and false are booleans"):
        load_config(FinetuneConfig, None, ["data.group_by_length=yes"])


def test_words_and_dates_stay_text(tmp_path):
    from degusta_learn.evaluate.compare import CompareConfig

    base = {"dataset": "d", "out": "o", "methods": [{"name": "a", "predictions": "p.jsonl"}]}
    for text in ("on", "no", "off", "2024-01-05", "=", "1:30"):
        assert load_config(CompareConfig, None, [f"title={text}"], data=base).title == text
        p = tmp_path / "c.yaml"
        p.write_text(yaml.safe_dump(base) + f"title: {text}\n")
        assert load_config(CompareConfig, p).title == text
    with pytest.raises(DegustaError, match="title: expected a string, got the number 8"):
        load_config(CompareConfig, None, ["title=0o10"], data=base)
    assert read_yaml_text(tmp_path, "on: 1\nyes: 2\n") == {"on": 1, "yes": 2}  # keys too: never True


def read_yaml_text(tmp_path, text):
    p = tmp_path / "k.yaml"
    p.write_text(text)
    return read_yaml(p)


def test_cli_integer_flags_read_digits_as_a_config_does(world, tmp_path, capsys):
    line = refused(capsys, ["data", "episodes", world["ds"], "--context", "2", "--seed", "1_000",
                            "--out", tmp_path / "e.jsonl"])
    assert "--seed" in line and "1_000" in line
    assert cli.main(["data", "episodes", str(world["ds"]), "--context", "2", "--split", "all", "--seed", "010",
                     "--out", str(tmp_path / "e10.jsonl")]) == 0
    assert cli.main(["data", "episodes", str(world["ds"]), "--context", "2", "--split", "all", "--seed", "10",
                     "--out", str(tmp_path / "e10b.jsonl")]) == 0
    assert (tmp_path / "e10.jsonl").read_bytes() == (tmp_path / "e10b.jsonl").read_bytes()


def test_every_shipped_config_means_what_it_meant_under_yaml_1_1():
    from degusta_learn.shipped import SHIPPED_DIR

    for path in sorted(SHIPPED_DIR.glob("*.yaml")):
        assert read_yaml(path) == (yaml.safe_load(path.read_text()) or {}), path.name


def test_dump_yaml_round_trips_under_both_readers(tmp_path):
    data = {"a": "1e3", "b": "0o17", "c": "yes", "d": "010", "e": "1:30", "f": 0.001, "g": True, "h": None,
            "i": "café", "j": "6e-3", "k": "0x1F", "l": [1, "2"], "m": "~", "n": "null"}
    text = dump_yaml(data)
    assert yaml.safe_load(text) == data
    assert read_yaml_text(tmp_path, text) == data


def _config_classes():
    from degusta_learn.evaluate.compare import CompareConfig
    from degusta_learn.methods import METHODS, TRAINERS, get_method, get_trainer
    from degusta_learn.prompting.backends.base import BACKENDS, backend_class

    classes = {("", CompareConfig)}
    classes |= {("", get_method(m).config_cls) for m in METHODS}
    classes |= {("", get_trainer(t).config_cls) for t in TRAINERS}
    classes |= {("backend.", backend_class(b).config_class) for b in BACKENDS}
    return classes


def _string_keys(cls, prefix, seen):
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        args = [a for a in typing.get_args(tp) if a is not type(None)] if typing.get_origin(tp) in (
            typing.Union, __import__("types").UnionType) else [tp]
        for a in args:
            if a is str:
                seen.add(prefix + f.name)
            elif typing.get_origin(a) is list and typing.get_args(a) and dataclasses.is_dataclass(typing.get_args(a)[0]):
                _string_keys(typing.get_args(a)[0], f"{prefix}{f.name}[0].", seen)
            elif dataclasses.is_dataclass(a):
                _string_keys(a, f"{prefix}{f.name}.", seen)


NOT_PATHS = {"method", "kind", "title", "device", "image_format", "accelerator", "strategy", "precision", "monitor",
             "run_name", "build_tiny", "attention_init", "name", "base_url", "api_key_env"}


def test_every_string_key_of_every_config_kind_is_a_path_key_or_known_text():
    """A new string key is a decision: add it to config.PATH_KEYS (a path: `~` expanded, checked) or here."""
    seen: set[str] = set()
    for prefix, cls in _config_classes():
        _string_keys(cls, prefix, seen)
    unclassified = sorted(k for k in seen if not path_key(k) and k.rsplit(".", 1)[-1] not in NOT_PATHS)
    assert not unclassified, f"classify these string keys (config.PATH_KEYS or NOT_PATHS): {unclassified}"
    assert {k for k in seen if path_key(k)} >= {"dataset", "out", "episodes", "trainer.run_dir", "model.name",
                                                "model.adapter", "methods[0].config", "methods[0].predictions"}
    assert set(PATH_KEYS) >= {"checkpoint", "cache", "adapter"}


# ----------------------------------------------------------------------------- 4. quickstart's folder

class Reached(Exception):
    """Quickstart's work began (its first step is stubbed: nothing is generated or trained)."""


@pytest.fixture
def stub_quickstart(monkeypatch):
    import degusta_learn.synth as synth

    def stop(*a, **k):
        raise Reached()

    monkeypatch.setattr(synth, "generate_dataset", stop)


@pytest.mark.parametrize("files", [
    {"episodes.jsonl": "my notes\n"}, {"report/report.md": "# mine\n"}, {"configs/learned_cpu.yaml": "mine: 1\n"},
    {"data/naturalistic/notes.txt": "x\n"}, {"thesis.tex": "\\documentclass{article}\n"},
    {".degusta_quickstart.json": '{"kind": "something else"}\n', "episodes.jsonl": "mine\n"},
    {".degusta_quickstart.json/x": "a folder, not the marker\n"},
], ids=["episodes", "report", "configs", "data", "unrelated", "foreign marker", "marker folder"])
def test_quickstart_never_writes_into_a_folder_it_did_not_create(files, tmp_path, stub_quickstart, capsys):
    out = tmp_path / "mine"
    for rel, text in files.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(text)
    before = snapshot(out)
    line = refused(capsys, ["quickstart", "--out", out, "--small"])
    assert "--out" in line and str(out) in line, line
    assert snapshot(out) == before


def test_quickstart_refuses_a_file_as_its_folder(tmp_path, stub_quickstart, capsys):
    (tmp_path / "f").write_text("mine\n")
    assert "not a folder" in refused(capsys, ["quickstart", "--out", tmp_path / "f"])
    assert (tmp_path / "f").read_text() == "mine\n"


@pytest.mark.parametrize("prepare", [lambda o: None, lambda o: o.mkdir()], ids=["new folder", "empty folder"])
def test_quickstart_claims_a_new_or_empty_folder_and_resumes_its_own(prepare, tmp_path, stub_quickstart):
    out = tmp_path / "qs"
    prepare(out)
    with pytest.raises(Reached):
        cli.main(["quickstart", "--out", str(out), "--small"])
    assert sorted(p.name for p in out.iterdir()) == [".degusta_quickstart.json"]  # the marker, written first
    assert json.loads((out / ".degusta_quickstart.json").read_text())["kind"] == "degusta quickstart output folder"
    (out / "episodes.jsonl").write_text("what an earlier run wrote\n")
    with pytest.raises(Reached):  # its own folder, marker and all: a re-run resumes
        cli.main(["quickstart", "--out", str(out), "--small"])
