"""One writer at a time (issue "Hardening, second pass", item 3): degusta_learn/files/locks.py and where it is taken.

A second process writing an output folder, a dataset folder or a run folder while a first one writes it is
refused in one line naming the folder and the first (pid, command, start time), and the first's output is
complete afterwards; a lock left by a SIGKILLed process does not block; lock files live beside what they lock
(never inside an output, run or model folder) and are gone after a clean run. The first writer is a real
separate process (a few lines of Python, started in a second); the second is `degusta` run in this process.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

sys.path.insert(0, str(Path(__file__).parent))
from conftest import make_small_dataset  # noqa: E402

from degusta_learn import cli
from degusta_learn.files import locks  # noqa: E402
from degusta_learn.files.locks import LockHeld, hold, is_lock_file, lock_file  # noqa: E402
from degusta_learn.scene import load_dataset, save_dataset  # noqa: E402

HOLD = """
import sys, time, pathlib
from degusta_learn.files.locks import hold
path, ready, go = sys.argv[1:4]
with hold(path, "test folder"):
    pathlib.Path(ready).write_text("held")
    t0 = time.time()
    while not pathlib.Path(go).exists() and time.time() - t0 < 60:
        time.sleep(0.05)
"""
GENERATE = """
import sys, time, pathlib
import degusta_learn.synth.generate as g
from degusta_learn.synth import generate_dataset
out, ready, go = sys.argv[1:4]
real = g.save_dataset
def slow(ds, tmp):  # the dataset is written; hold the folder until the test says go
    real(ds, tmp)
    pathlib.Path(ready).write_text("held")
    t0 = time.time()
    while not pathlib.Path(go).exists() and time.time() - t0 < 60:
        time.sleep(0.05)
g.save_dataset = slow
generate_dataset("simulated", out, seed=7, overwrite=True)
"""


class Holder:
    """A separate process running `code` (HOLD / GENERATE) with `path`; it holds the lock until `release`."""

    def __init__(self, tmp_path: Path, code: str, path: Path):
        self.ready, self.go = tmp_path / f"ready-{path.name}", tmp_path / f"go-{path.name}"
        self.proc = subprocess.Popen([sys.executable, "-c", code, str(path), str(self.ready), str(self.go)],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 60
        while not self.ready.exists():
            assert self.proc.poll() is None, self.proc.communicate()
            assert time.monotonic() < deadline, "the holder did not start"
            time.sleep(0.05)

    def release(self) -> int:
        self.go.write_text("go")
        _, err = self.proc.communicate(timeout=60)
        assert self.proc.returncode == 0, err
        return self.proc.returncode


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("degusta: error: "), err
    return err[0]


def refused_by(line: str, path: Path, holder: Holder) -> None:
    assert f"{path}" in line and f"pid {holder.proc.pid}" in line and "is writing this" in line, line
    assert "since 20" in line, line  # the holder's start time


@pytest.fixture(scope="module")
def data_root(tmp_path_factory) -> Path:
    return save_dataset(make_small_dataset(), tmp_path_factory.mktemp("locks") / "data")


# ---------------------------------------------------------------- the lock itself
def test_lock_file_lives_beside_and_is_removed(tmp_path):
    target = tmp_path / "out"
    with hold(target, "output folder") as lock:
        assert lock.file == tmp_path / ".out.degusta-lock" and lock.file.is_file() and is_lock_file(lock.file.name)
        record = json.loads(lock.file.read_text())
        assert record["pid"] == os.getpid() and record["command"] and record["started"].startswith("20")
        assert not target.exists()  # nothing is made inside (or for) the folder itself
    assert sorted(tmp_path.iterdir()) == []


def test_every_spelling_of_a_folder_shares_one_lock(tmp_path, monkeypatch):
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    monkeypatch.chdir(tmp_path)
    assert lock_file("real") == lock_file(tmp_path / "link") == lock_file(tmp_path / "x" / ".." / "real")


def test_reentrant_in_its_thread_refused_in_another(tmp_path):
    target = tmp_path / "out"
    seen = []
    with hold(target, "output folder"):
        with hold(target, "output folder"):  # a trainer holds its run folder and fit asks again
            pass
        assert lock_file(target).exists()  # the inner release kept the outer lock

        def other():
            try:
                with hold(target, "output folder"):
                    seen.append("taken")
            except LockHeld as e:
                seen.append(str(e))

        t = threading.Thread(target=other)
        t.start()
        t.join()
    assert len(seen) == 1 and "another thread of this process" in seen[0], seen
    with hold(target, "output folder"):  # released: free again
        pass


def test_a_second_process_is_refused_in_one_line_naming_the_holder(tmp_path):
    target = tmp_path / "out"
    holder = Holder(tmp_path, HOLD, target)
    try:
        with pytest.raises(LockHeld) as e, hold(target, "evaluation report"):
            pass
        text = str(e.value)
        assert "\n" not in text and "evaluation report" in text and str(lock_file(target)) in text
        assert f"pid {holder.proc.pid}" in text and "python" in text  # the holder's command
    finally:
        holder.release()
    with hold(target, "evaluation report"):
        pass


def test_a_lock_left_by_a_killed_process_does_not_block(tmp_path):
    target = tmp_path / "out"
    holder = Holder(tmp_path, HOLD, target)
    holder.proc.send_signal(signal.SIGKILL)
    holder.proc.wait(timeout=30)
    assert lock_file(target).is_file()  # the stale file stays; the OS released its lock
    with hold(target, "output folder") as lock:
        assert json.loads(lock.file.read_text())["pid"] == os.getpid()  # taken over, record rewritten
    assert not lock_file(target).exists()


def test_a_file_system_without_locks_degrades_with_a_note(tmp_path, monkeypatch, capsys):
    import errno

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(locks.fcntl, "flock", no_locks)
    monkeypatch.setattr(locks, "_noted", set())
    with hold(tmp_path / "out", "output folder"), hold(tmp_path / "out2", "output folder"):
        pass
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("refuses file locks" in line for line in err), err


def test_an_uncreatable_lock_file_leaves_the_error_to_the_write(tmp_path):
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    with hold(blocker / "sub" / "out", "output folder") as lock:  # its parent is a file: nothing to lock
        assert lock.fd is None


# ---------------------------------------------------------------- where the locks are taken
def test_data_generate_into_a_folder_being_generated_is_refused_and_the_first_completes(tmp_path, capsys):
    out = tmp_path / "data"
    holder = Holder(tmp_path, GENERATE, out)
    try:
        assert cli.main(["data", "generate", "simulated", "--out", str(out), "--overwrite", "--seed", "3"]) == 2
        line = one_error_line(capsys)
        refused_by(line, out, holder)
        assert "is writing this dataset right now" in line
    finally:
        holder.release()
    ds = load_dataset(out)  # the first writer's dataset, whole
    assert ds.meta["seed"] == 7
    assert not [p for p in tmp_path.iterdir() if is_lock_file(p.name) or p.name.endswith(".tmp")]
    assert cli.main(["data", "generate", "simulated", "--out", str(out), "--overwrite", "--seed", "3"]) == 0
    assert load_dataset(out).meta["seed"] == 3


def test_render_and_evaluate_into_a_held_folder_are_refused(tmp_path, data_root, capsys):
    out = tmp_path / "out"
    holder = Holder(tmp_path, HOLD, out)
    try:
        assert cli.main(["render", "episode", str(data_root), "--participant", "p000", "--target", "2",
                         "--context", "2", "--method", "mogma", "--out", str(out), "--size", "64"]) == 2
        refused_by(one_error_line(capsys), out, holder)
        from degusta_learn.scene import Prediction, make_episodes, write_predictions

        ds = load_dataset(data_root)
        preds = [Prediction(e.id, e.participant, e.target, "copy", list(ds.arrangement(e.participant, e.target)
                                                                          .placements))
                 for e in make_episodes(ds, 2, "all")]
        write_predictions(tmp_path / "p.jsonl", preds)
        assert cli.main(["evaluate", "--dataset", str(data_root), "--predictions", str(tmp_path / "p.jsonl"),
                         "--out", str(out), "--bootstrap", "10"]) == 2
        refused_by(one_error_line(capsys), out, holder)
        assert not out.exists()
    finally:
        holder.release()


def _learned_yaml(tmp_path: Path, data: Path) -> Path:
    cfg = {"kind": "learned", "num_threads": 1, "dataset": str(data),
           "data": {"batch_size": 8, "repeats": 1, "val_contexts": [2]},
           "model": {"d_model": 16, "n_layers": 1, "n_heads": 2, "d_ff": 32, "max_objects": 8},
           "trainer": {"run_dir": str(tmp_path / "runs"), "run_name": "tiny", "max_epochs": -1, "max_steps": 1,
                       "val_check_interval": 1, "accelerator": "cpu", "devices": 1, "progress_bar": False}}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


@pytest.mark.usefixtures("one_torch_thread")
def test_a_second_run_into_a_run_folder_in_use_is_refused_and_leaves_it_alone(tmp_path, data_root, capsys):
    """The first run has made its folder but not yet its first checkpoint: the refused second run must not
    take the folder for one it created and remove it (a user mistake removes only a folder of its own)."""
    run = tmp_path / "runs" / "tiny"
    run.mkdir(parents=True)
    (run / "config.yaml").write_text("kind: learned\n")  # as the first run writes it before training
    holder = Holder(tmp_path, HOLD, run)
    try:
        assert cli.main(["train", "--config", str(_learned_yaml(tmp_path, data_root))]) == 2
        line = one_error_line(capsys)
        refused_by(line, run, holder)
        assert "run folder" in line
        assert sorted(p.name for p in run.iterdir()) == ["config.yaml"]
    finally:
        holder.release()
    assert cli.main(["train", "--config", str(_learned_yaml(tmp_path, data_root))]) == 0
    assert (run / "last.ckpt").is_file()
    assert not [p for p in (tmp_path / "runs").iterdir() if is_lock_file(p.name)]
