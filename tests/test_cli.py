"""The CLI: thin verbs, one-line errors with exit status 2, outputs written atomically."""

import json

from degusta_learn.cli import build_parser, main


def test_validate_ok_and_bad(small_dataset_dir, capsys):
    assert main(["data", "validate", str(small_dataset_dir)]) == 0
    assert "valid" in capsys.readouterr().out
    path = small_dataset_dir / "arrangements.jsonl"
    lines = path.read_text().splitlines()
    row = json.loads(lines[1])
    row["placements"][0]["x"] = -0.2
    lines[1] = json.dumps(row)
    path.write_text("\n".join(lines) + "\n")
    assert main(["data", "validate", str(small_dataset_dir)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert "arrangements.jsonl:2: field 'placements[0].x'" in err


def test_validate_notes_placements_off_the_table_surface(small_dataset_dir, capsys):
    """A centre inside [0, 1] but off the table's surface polygon loads (an edge may be overhung) and is named."""
    from degusta_learn.scene import load_dataset

    ds = load_dataset(small_dataset_dir)
    assert main(["data", "validate", str(small_dataset_dir)]) == 0
    assert "note:" not in capsys.readouterr().out  # the generator sets every object on the table
    path = small_dataset_dir / "arrangements.jsonl"
    lines = path.read_text().splitlines()
    row = json.loads(lines[2])
    assert not ds.tables[row["table"]].contains(0.001, 0.999)  # a corner outside every shipped table's surface
    row["placements"][1].update(x=0.001, y=0.999)
    lines[2] = json.dumps(row)
    path.write_text("\n".join(lines) + "\n")
    assert main(["data", "validate", str(small_dataset_dir)]) == 0
    out = capsys.readouterr().out
    obj = row["placements"][1]["object"]
    assert "valid" in out and "note: 1 of " in out
    assert f"participant {row['participant']} trial {row['trial']} object {obj} at (0.001, 0.999)" in out


def test_episodes_verb_writes_file(small_dataset_dir, tmp_path, capsys):
    out = tmp_path / "eps.jsonl"
    assert main(["data", "episodes", str(small_dataset_dir), "--context", "2", "--split", "test", "--out", str(out)]) == 0
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    assert rows and set(rows[0]) == {"id", "participant", "context", "target", "task"}
    assert str(out) in capsys.readouterr().out


def test_predict_with_unknown_method_or_key_is_one_line(tmp_path, small_dataset_dir, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"method: nope\ndataset: {small_dataset_dir}\nout: {tmp_path / 'p.jsonl'}\n")
    assert main(["predict", "--config", str(cfg)]) == 2
    assert "unknown method 'nope'" in capsys.readouterr().err
    cfg.write_text(f"method: random\ndataset: {small_dataset_dir}\nout: {tmp_path / 'p.jsonl'}\nbogus: 1\n")
    assert main(["predict", "--config", str(cfg)]) == 2
    assert "unknown key 'bogus'" in capsys.readouterr().err
    assert not (tmp_path / "p.jsonl").exists()


def test_every_verb_has_a_function():
    parser = build_parser()
    verbs = parser._subparsers._group_actions[0].choices
    assert {"data", "predict", "train", "evaluate"} <= set(verbs)
