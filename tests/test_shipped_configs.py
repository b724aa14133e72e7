"""Configs are package data: in the wheel, listed and copied by `degusta configs`, found by name by --config."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tarfile
import time
import zipfile
from pathlib import Path

import pytest
import yaml

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.evaluate.compare import MethodEntry
from degusta_learn.shipped import (
    PURPOSE_CHARS,
    SHIPPED_DIR,
    copy_config,
    list_configs,
    purpose,
    resolve_config,
    shipped_names,
)

ROOT = Path(__file__).resolve().parent.parent
CHECKOUT_CONFIGS = sorted(p.name for p in (ROOT / "configs").glob("*.yaml"))


def _build(kind: str, out: Path) -> Path:
    """Build a wheel or sdist with setuptools' build API (offline) from a copy of the source tree."""
    src = out / "src"
    if not src.exists():
        src.mkdir(parents=True)
        for name in ("pyproject.toml", "README.md"):
            (src / name).write_bytes((ROOT / name).read_bytes())
        import shutil

        shutil.copytree(ROOT / "degusta_learn", src / "degusta_learn",
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    code = f"import setuptools.build_meta as b; print(b.build_{kind}({str(out)!r}))"
    done = subprocess.run([sys.executable, "-c", code], cwd=src, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return out / done.stdout.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    return _build("wheel", tmp_path_factory.mktemp("dist"))


def test_the_root_configs_folder_is_the_package_data():
    # Every `configs/x.yaml` in README, docs and config headers keeps working in a checkout.
    assert (ROOT / "configs").resolve() == SHIPPED_DIR
    assert CHECKOUT_CONFIGS and [f"{n}.yaml" for n in shipped_names()] == CHECKOUT_CONFIGS


def test_the_wheel_and_sdist_hold_every_shipped_config(wheel):
    with zipfile.ZipFile(wheel) as z:
        in_wheel = sorted(Path(n).name for n in z.namelist() if n.startswith("degusta_learn/configs/"))
        assert "degusta_learn/shipped.py" in z.namelist()
    assert in_wheel == CHECKOUT_CONFIGS
    sdist = _build("sdist", wheel.parent)  # what `python -m build` builds its wheel from
    with tarfile.open(sdist) as t:
        in_sdist = sorted(Path(n).name for n in t.getnames() if "/degusta_learn/configs/" in n)
    assert in_sdist == CHECKOUT_CONFIGS


def test_every_shipped_config_states_its_purpose():
    for name, text in list_configs():
        assert text and not text.startswith("degusta ") and len(text) <= PURPOSE_CHARS, (name, text)


def test_purpose_is_the_first_sentence_after_the_command_lines(tmp_path):
    path = tmp_path / "x.yaml"
    path.write_text("# degusta predict --config configs/x.yaml\n"
                    "#   override example: degusta predict --config configs/x.yaml --set a=1\n"
                    "# A method that looks at the context (e.g. two tables) and\n"
                    "# sets the target table. Needs: the data.\n"
                    "a: 1\n")
    assert purpose(path) == "A method that looks at the context (e.g. two tables) and sets the target table."
    path.write_text("# degusta predict --config x.yaml\n# Served locally:\n#   vllm serve M --port 8000\n# Then x.\n")
    assert purpose(path) == "Served locally"
    path.write_text("# " + "word " * 60 + "\n")
    assert len(purpose(path)) <= PURPOSE_CHARS and purpose(path).endswith("word…")
    path.write_text("# degusta predict --config x.yaml\na: 1\n# not the header\n")
    assert purpose(path) == ""


def test_configs_list_prints_every_name_with_its_purpose(capsys):
    assert main(["configs", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith(f"{len(shipped_names())} shipped configs")
    for name, text in list_configs():
        assert any(line.split() and line.split()[0] == name and line.endswith(text) for line in lines[1:]), name


def test_configs_copy_writes_the_file_and_never_overwrites(tmp_path, capsys):
    assert main(["configs", "copy", "learned_cpu", str(tmp_path / "mine")]) == 0
    target = tmp_path / "mine" / "learned_cpu.yaml"
    assert target.read_bytes() == (SHIPPED_DIR / "learned_cpu.yaml").read_bytes()
    assert capsys.readouterr().out.strip() == f"wrote {target}; run it with: degusta train --config {target}"
    target.write_text("edited: true\n")
    assert main(["configs", "copy", "learned_cpu.yaml", str(tmp_path / "mine")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "already exists; not overwritten" in err and str(target) in err
    assert target.read_text() == "edited: true\n"
    assert copy_config("oracle.yaml", tmp_path / "o.yaml") == tmp_path / "o.yaml"  # a .yaml DEST is the file
    assert (tmp_path / "o.yaml").read_bytes() == (SHIPPED_DIR / "oracle.yaml").read_bytes()
    # a DEST that is neither a folder nor a .yaml name was made a folder called notes.txt
    assert main(["configs", "copy", "oracle", str(tmp_path / "notes.txt")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "notes.txt" in err and "notes.yaml" in err
    assert not (tmp_path / "notes.txt").exists()
    (tmp_path / "runs.v2").mkdir()  # an existing folder with a dot in its name is a folder
    assert copy_config("oracle", tmp_path / "runs.v2") == tmp_path / "runs.v2" / "oracle.yaml"


def test_configs_copy_of_an_unknown_name_lists_close_matches(tmp_path, capsys):
    assert main(["configs", "copy", "finetune_tiny", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'finetune_tiny': no shipped config" in err and "finetune_tiny_cpu" in err
    assert not list(tmp_path.iterdir())
    assert main(["configs", "copy", "zzzz", str(tmp_path)]) == 2
    assert "degusta configs list" in capsys.readouterr().err


def test_config_names_resolve_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shipped = SHIPPED_DIR / "learned_cpu.yaml"
    for value in ("learned_cpu", "learned_cpu.yaml", "configs/learned_cpu.yaml"):
        assert resolve_config(value) == shipped, value
    (tmp_path / "learned_cpu").write_text("kind: learned\n")  # a path that exists wins over a name
    assert resolve_config("learned_cpu") == Path("learned_cpu")
    with pytest.raises(DegustaError, match=r"'learnd_cpu.yaml': no such file, and no shipped config .*learned_cpu"):
        resolve_config("learnd_cpu.yaml")
    with pytest.raises(DegustaError, match="no such file"):
        resolve_config("elsewhere/learned_cpu.yaml")  # a path with other folders is only a path


def test_every_config_verb_accepts_a_shipped_name(small_dataset_dir, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "random.jsonl"
    assert main(["predict", "--config", "baseline_random", "--set", f"dataset={small_dataset_dir}",
                 "--set", f"out={out}", "--set", "context=2"]) == 0
    assert out.is_file() and out.read_text().count("\n") > 0
    for verb in ("predict", "train", "compare"):
        assert main([verb, "--config", "baseline_randm"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "argument --config: 'baseline_randm': no such file" in err
        assert "close matches: baseline_random" in err


def test_compare_entries_and_quickstart_find_shipped_configs_outside_a_checkout(tmp_path, monkeypatch):
    from degusta_learn.quickstart import _config

    monkeypatch.chdir(tmp_path)
    assert MethodEntry(name="o", config="configs/oracle.yaml").config == str(SHIPPED_DIR / "oracle.yaml")
    assert MethodEntry(name="o", config="oracle").config == str(SHIPPED_DIR / "oracle.yaml")
    assert MethodEntry(name="m", config="mine.yaml").config == "mine.yaml"  # reported when it runs, as before
    path = _config("learned_cpu", tmp_path / "qs", ["trainer.max_epochs=1"], "degusta train")
    assert "max_epochs: 1" in path.read_text()


def test_configs_list_into_a_closed_pipe_is_quiet():
    proc = subprocess.Popen([sys.executable, "-m", "degusta_learn.cli", "configs", "list"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # like `degusta configs list | head -1`: the reader is gone before the list is printed
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 0 and err == ""


def venv_seeing_these_packages(venv: Path) -> Path:
    """A fresh venv (its python returned) that sees the packages of the interpreter running the tests, whether that
    is itself a venv or a machine-wide install: `--system-site-packages` would see only the base interpreter's. The
    outer site-packages are appended by a .pth file, so what is installed into the new venv comes first, and the
    outer .pth files (an editable install of degusta_learn among them) are not run."""
    import site
    import sysconfig

    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    inner = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                           capture_output=True, text=True, check=True).stdout.strip()
    outer = dict.fromkeys([sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"], *site.getsitepackages()])
    Path(inner, "outer_packages.pth").write_text("".join(f"{p}\n" for p in outer if Path(p).is_dir()))
    return python


def test_a_venv_made_for_a_test_sees_the_test_interpreters_packages(tmp_path):
    python = venv_seeing_these_packages(tmp_path / "venv")
    done = subprocess.run([str(python), "-c", "import PIL, torch, yaml; import sys; print(sys.prefix)"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert Path(done.stdout.strip()).resolve() == (tmp_path / "venv").resolve()
    where = subprocess.run([str(python), "-c", "import importlib.util as u; print(u.find_spec('degusta_learn'))"],
                           cwd=tmp_path, capture_output=True, text=True, timeout=120).stdout
    assert "None" in where, where  # the checkout's editable install does not leak in: the wheel is what is tested


def test_the_wheel_holds_the_shipped_base_with_its_card(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        card = z.read("degusta_learn/shipped_models/tiny_vlm_base/README.md").decode()
    for name in ("config.json", "model.safetensors", "tokenizer.json", "processor_config.json", "degusta_base.json"):
        assert f"degusta_learn/shipped_models/tiny_vlm_base/{name}" in names, name
    assert card.startswith("---\n") and "pipeline_tag: image-text-to-text" in card


@pytest.mark.slow
def test_quickstart_small_end_to_end_from_a_non_editable_install(wheel, tmp_path):
    """The main job at a reduced size, as a user gets it: `pip install` of the wheel (not -e) into a fresh venv, then
    `degusta quickstart --small` in another folder: every method, one report, every linked file present, every
    config it ran written beside the results. (One run of the quickstart for both: it is the suite's slowest step.)"""
    venv = tmp_path / "venv"
    python = venv_seeing_these_packages(venv)
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps", "--no-index",
                    "--force-reinstall", str(wheel)], check=True)
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "OPENAI_API_KEY")}
    env.update(HF_HUB_OFFLINE="1", TRANSFORMERS_OFFLINE="1")
    where = subprocess.run([str(python), "-c", "import degusta_learn; print(degusta_learn.__file__)"], cwd=work,
                           env=env, capture_output=True, text=True, check=True).stdout
    assert Path(where).resolve().is_relative_to(venv.resolve()), where  # the wheel's copy, not the checkout
    t0 = time.time()
    done = subprocess.run([str(venv / "bin" / "degusta"), "quickstart", "--small"], cwd=work, env=env,
                          capture_output=True, text=True, timeout=1800)
    assert done.returncode == 0, done.stderr[-3000:]
    print(f"quickstart --small from a wheel install: {time.time() - t0:.0f} s")
    report = work / "quickstart" / "report"
    assert done.stdout.strip().splitlines()[-1].endswith("report.html in a browser)")
    assert (report / "report.html").is_file()
    assert "export OPENAI_API_KEY" in done.stdout  # how to add the GPT-4o rows
    metrics = json.loads((report / "metrics.json").read_text())
    assert set(metrics["methods"]) == {"random", "population_mean", "copy_nearest", "consensus", "oracle", "learned",
                                       "tiny_base_zeroshot", "tiny_base_finetuned"}
    assert "LoRA fine-tuning the shipped tiny base VLM (tiny_vlm_base" in done.stdout  # never a random-weight stand-in
    ran = (work / "quickstart" / "configs" / "predict_hf_base_finetuned.yaml").read_text()
    assert yaml.safe_load(ran)["model"]["name"] == "tiny_vlm_base"
    assert not metrics["failed_methods"]
    text = (report / "report.md").read_text()
    for link in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text):
        assert (report / link).is_file(), link
    # Every config it ran is written beside the results, so each step can be re-run by hand.
    assert {p.name for p in (work / "quickstart" / "configs").glob("*.yaml")} >= {"learned_cpu.yaml",
                                                                                  "finetune_tiny_base_cpu.yaml"}


def test_the_set_transformer_configs_choose_on_the_set_score_and_pair_up():
    train = yaml.safe_load((SHIPPED_DIR / "set_transformer_cpu.yaml").read_text())
    predict = yaml.safe_load((SHIPPED_DIR / "set_transformer_predict.yaml").read_text())
    assert (train["trainer"]["monitor"], train["trainer"]["monitor_mode"]) == ("val/set_rmsd", "min")
    assert train["trainer"]["early_stopping_patience"] >= 1  # early stopping watches the same set-aware score
    assert predict["checkpoint"] == f"{train['trainer']['run_dir']}/{train['trainer']['run_name']}"
    assert (predict["seed"], predict["dataset"], predict["method"]) == (train["seed"], train["dataset"], train["kind"])
