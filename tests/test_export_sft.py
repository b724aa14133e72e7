"""`degusta data export-sft`: the trainer's own examples as TRL / LLaMA-Factory "messages + images" data."""

import json
from pathlib import Path

import pytest
import yaml
from PIL import Image

from degusta_learn.cli import main
from degusta_learn.config import from_dict
from degusta_learn.errors import DegustaError
from degusta_learn.finetune.config import FinetuneConfig
from degusta_learn.finetune.export_sft import export_sft
from degusta_learn.finetune.train import build_examples
from degusta_learn.render.grid import Grid
from degusta_learn.scene import load_dataset
from degusta_learn.vlm.inputs import prompt_messages

RENDER = 96


def write_config(tmp_path, dataset_dir, **data) -> str:
    cfg = {"kind": "finetune", "dataset": str(dataset_dir), "method": "mogma", "seed": 0,
           "model": {"name": str(tmp_path / "no-model-needed")},
           "data": {"contexts": [0, 2], "val_contexts": [2], "val_episodes": 3, "max_train_episodes": 6,
                    "render_size": RENDER, "compose": ["objects"], **data},
           "trainer": {"run_dir": str(tmp_path / "ckpt")}}
    path = tmp_path / "ft.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


def read_rows(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_export_is_the_training_examples(tmp_path, small_dataset_dir):
    config = write_config(tmp_path, small_dataset_dir)
    out = tmp_path / "sft"
    assert main(["data", "export-sft", "--config", config, "--out", str(out)]) == 0
    rows = read_rows(out / "train.jsonl")
    cfg = from_dict(FinetuneConfig, yaml.safe_load(Path(config).read_text()))
    train, _ = build_examples(cfg, load_dataset(small_dataset_dir), Grid(8, 8))
    assert len(rows) == len(train) == 6
    for i, row in enumerate(rows):
        user, assistant = row["messages"]
        assert user["role"] == "user" and assistant["role"] == "assistant"
        ex = train[i]  # epoch 0, as training's first epoch sees it
        messages, images = prompt_messages(ex.prompt)
        assert user["content"] == messages[0]["content"]
        assert assistant["content"] == [{"type": "text", "text": ex.answer}]
        assert sum(part["type"] == "image" for part in user["content"]) == len(row["images"]) == len(images) > 0
        for name, image in zip(row["images"], images):
            with Image.open(out / name) as im:
                assert im.format == "PNG" and im.size == (RENDER, RENDER)
                assert list(im.convert("RGB").getdata()) == list(image.getdata())  # the same pixels
    shared = read_rows(out / "train_sharegpt.jsonl")
    assert len(shared) == len(rows)
    for row, sg in zip(rows, shared):
        assert sg["images"] == row["images"]
        assert sg["messages"][0]["content"].count("<image>") == len(row["images"])
        assert sg["messages"][1]["content"] == row["messages"][1]["content"][0]["text"]
    info = json.loads((out / "dataset_info.json").read_text())["degusta_train"]
    assert info["formatting"] == "sharegpt" and info["file_name"] == "train_sharegpt.jsonl"
    assert info["columns"] == {"messages": "messages", "images": "images"}
    assert "load_dataset(\"json\"" in (out / "README.md").read_text()


def test_val_split_and_rerun_into_the_same_folder(tmp_path, small_dataset_dir):
    config = write_config(tmp_path, small_dataset_dir)
    out = tmp_path / "sft"
    export_sft(config, out)
    _, n, _ = export_sft(config, out, split="val")  # replaces the folder it wrote, whole
    assert n == 3 and len(read_rows(out / "val.jsonl")) == 3 and not (out / "train.jsonl").exists()
    referenced = {p for r in read_rows(out / "val.jsonl") for p in r["images"]}
    assert {f"images/{p.name}" for p in (out / "images").iterdir()} == referenced  # no stale train image


def test_a_foreign_folder_is_refused_and_left_alone(tmp_path, small_dataset_dir):
    config = write_config(tmp_path, small_dataset_dir)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    with pytest.raises(DegustaError, match="refusing to replace a folder"):
        export_sft(config, out)
    (out / "notes.txt").unlink()
    (out / "README.md").write_text("a user's own readme")  # a name we write, but no marker: not ours
    with pytest.raises(DegustaError, match="refusing to replace a folder"):
        export_sft(config, out)
    assert (out / "README.md").read_text() == "a user's own readme" and len(list(out.iterdir())) == 1


def test_bad_input_is_one_line(tmp_path, small_dataset_dir, capsys):
    learned = tmp_path / "learned.yaml"
    learned.write_text(yaml.safe_dump({"kind": "learned", "dataset": str(small_dataset_dir)}))
    assert main(["data", "export-sft", "--config", str(learned), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "kind: finetune" in err and not (tmp_path / "x").exists()
    config = write_config(tmp_path, small_dataset_dir, val_episodes=0)
    with pytest.raises(DegustaError, match="no val examples"):
        export_sft(config, tmp_path / "y", split="val")
    assert not (tmp_path / "y").exists()
