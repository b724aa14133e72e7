"""Hub ids behave as in transformers / peft / TRL: downloaded into the standard cache when online, refused in one
line when offline, every Hub problem one line naming the key. Online cases run in a subprocess against a
stand-in Hub on 127.0.0.1 (tests/fake_hub.py) with the real huggingface_hub client: nothing leaves the machine."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fake_hub import FakeHub
from finetune_support import tiny_dir

from degusta_learn.errors import DegustaError
from degusta_learn.vlm.hub import resolve_model

CONFIGS = Path(__file__).parent.parent / "configs"
LOAD = ("import sys\nfrom degusta_learn.errors import DegustaError\nfrom degusta_learn.vlm.load import load_vlm\n"
        "try:\n    m, p = load_vlm({!r}, device='cpu', key='model.name')\n"
        "except DegustaError as e:\n    sys.exit(f'degusta: error: {{e}}')\nprint('loaded', m.config._name_or_path)")


@pytest.fixture(scope="module")
def repo(tmp_path_factory) -> Path:
    """A tiny VLM as a Hub repository would hold it, with an ONNX sub-folder that must not be downloaded."""
    import shutil

    folder = tmp_path_factory.mktemp("repo") / "tiny-vlm"
    shutil.copytree(tiny_dir("idefics3"), folder)
    (folder / "onnx").mkdir()
    (folder / "onnx" / "model.onnx").write_bytes(b"\0" * 1000)
    (folder / "pytorch_model.bin").write_bytes(b"not loaded: degusta reads safetensors only")
    return folder


def run(code_or_args, env: dict, cwd: Path, timeout: float = 180) -> subprocess.CompletedProcess:
    args = ["-c", code_or_args] if isinstance(code_or_args, str) else ["-m", "degusta_learn.cli", *code_or_args]
    return subprocess.run([sys.executable, *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def hub_env(tmp_path: Path, hub: FakeHub | None, offline: bool) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("TRANSFORMERS_OFFLINE", "HF_HUB_OFFLINE", "HF_TOKEN")}
    env.update(HF_HOME=str(tmp_path / "hf"), HF_HUB_OFFLINE="1" if offline else "0", HF_HUB_DISABLE_TELEMETRY="1")
    if hub is not None:
        env["HF_ENDPOINT"] = hub.url
    return env


def one_line_error(done: subprocess.CompletedProcess) -> str:
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode in (1, 2) and "Traceback" not in done.stderr, done.stderr[-3000:]
    return lines[-1]


@pytest.mark.slow
def test_a_hub_id_downloads_into_the_standard_cache_then_loads_offline(tmp_path, repo):
    with FakeHub({"acme/tiny-vlm": repo}) as hub:
        done = run(LOAD.format("acme/tiny-vlm"), hub_env(tmp_path, hub, offline=False), tmp_path)
        assert done.returncode == 0, done.stderr[-3000:]
        assert done.stdout.strip().endswith("loaded acme/tiny-vlm")  # the name peft records, not the cache path
        asked = list(hub.requests)
    snapshot = next((tmp_path / "hf" / "hub" / "models--acme--tiny-vlm" / "snapshots").iterdir())
    got = {p.name for p in snapshot.iterdir()}
    assert {"config.json", "model.safetensors", "tokenizer.json", "processor_config.json"} <= got
    assert "onnx" not in got and "pytorch_model.bin" not in got  # top-level configs and safetensors only
    assert not any("onnx" in r or r.endswith(".bin") for r in asked)
    # Offline now: the cached copy loads and nothing is asked (the stand-in Hub is gone).
    done = run(LOAD.format("acme/tiny-vlm"), hub_env(tmp_path, None, offline=True), tmp_path)
    assert done.returncode == 0 and "loaded acme/tiny-vlm" in done.stdout, done.stderr[-3000:]

    # A half-finished download (the weights missing from the snapshot): offline, one line saying so; online, the
    # next load completes it.
    (snapshot / "model.safetensors").unlink()
    done = run(LOAD.format("acme/tiny-vlm"), hub_env(tmp_path, None, offline=True), tmp_path)
    line = one_line_error(done)
    assert "model.name: the cached copy of 'acme/tiny-vlm' is incomplete" in line and "model.safetensors" in line
    assert "hf download acme/tiny-vlm" in line
    with FakeHub({"acme/tiny-vlm": repo}) as hub:
        done = run(LOAD.format("acme/tiny-vlm"), hub_env(tmp_path, hub, offline=False), tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (snapshot / "model.safetensors").is_file()


@pytest.mark.slow
def test_predict_with_a_hub_id_downloads_then_answers(tmp_path, repo, small_dataset_dir):
    out = tmp_path / "pred" / "predictions.jsonl"
    args = ["predict", "--config", str(CONFIGS / "predict_hf_tiny_zeroshot.yaml"), "--set", f"dataset={small_dataset_dir}",
            "--set", "model.name=acme/tiny-vlm", "--set", "context=2", "--set", f"out={out}",
            "--set", "render_size=64", "--set", "decoding.max_new_tokens=140"]
    with FakeHub({"acme/tiny-vlm": repo}) as hub:
        done = run(args, hub_env(tmp_path, hub, offline=False), tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert out.is_file() and out.read_text().count("\n") >= 1


def test_a_typo_in_a_hub_id_is_one_line_naming_the_key(tmp_path, repo, small_dataset_dir):
    with FakeHub({"acme/tiny-vlm": repo}) as hub:
        done = run(["predict", "--config", str(CONFIGS / "predict_hf_tiny_zeroshot.yaml"), "--set",
                    f"dataset={small_dataset_dir}", "--set", "model.name=acme/tiny-vml", "--set", "context=2",
                    "--set", f"out={tmp_path / 'p.jsonl'}"], hub_env(tmp_path, hub, offline=False), tmp_path)
    line = one_line_error(done)
    assert done.returncode == 2 and line.startswith("degusta: error: model.name: 'acme/tiny-vml': no such model "
                                                    "on the Hugging Face Hub"), line
    assert not (tmp_path / "p.jsonl").exists()


@pytest.mark.parametrize("name, message", [
    ("not a valid/id!", "is neither a local folder nor a valid Hugging Face Hub id"),
    ("acme/uncached-vlm", "is not in the local Hugging Face cache and downloads are off (HF_HUB_OFFLINE is set): "
                          "download it with `hf download acme/uncached-vlm`"),
])
def test_offline_hub_ids_are_refused_at_once(tmp_path, monkeypatch, name, message):
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))  # read per call for the cache folder? the id is refused anyway
    start = time.monotonic()
    with pytest.raises(DegustaError) as e:
        resolve_model(name, key="model.name")
    assert message in str(e.value) and str(e.value).startswith("model.name: ") and "\n" not in str(e.value)
    assert time.monotonic() - start < 10  # no network timeout


def test_local_files_only_refuses_like_offline_mode(tmp_path):
    with pytest.raises(DegustaError, match=r"downloads are off \(local_files_only is set\)"):
        resolve_model("acme/never-cached", key="model.name", local_files_only=True)


def test_the_shipped_base_is_found_by_name_from_any_folder(tmp_path, monkeypatch):
    from degusta_learn.shipped import BASE_DIR

    monkeypatch.chdir(tmp_path)
    assert resolve_model("tiny_vlm_base", key="model.name") == BASE_DIR
    (tmp_path / "tiny_vlm_base").mkdir()  # a folder of that name here wins, as a path always does
    with pytest.raises(DegustaError, match="without config.json"):
        resolve_model("tiny_vlm_base", key="model.name")


def test_training_a_gpu_config_offline_without_its_model_is_one_line_within_seconds(tmp_path, small_dataset_dir):
    """`degusta train --config finetune_smolvlm_256m` on a machine without the model in its cache, offline: the
    one-line refusal names the key and the `hf download` command (the test machine's own offline mode)."""
    env = hub_env(tmp_path, None, offline=True)
    start = time.monotonic()
    done = run(["train", "--config", "finetune_smolvlm_256m", "--set", f"dataset={small_dataset_dir}", "--dry-run"],
               env, tmp_path)
    line = one_line_error(done)
    assert done.returncode == 2 and time.monotonic() - start < 120, (done.returncode, line)
    assert line.startswith("degusta: error: model.name: 'HuggingFaceTB/SmolVLM-256M-Instruct' is not in the local "
                           "Hugging Face cache") and "`hf download HuggingFaceTB/SmolVLM-256M-Instruct`" in line
