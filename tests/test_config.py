from dataclasses import dataclass, field
from typing import Literal

import pytest

from degusta_learn.config import load_config
from degusta_learn.errors import DegustaError


@dataclass
class Inner:
    name: str = "openai"
    n: int = 5


@dataclass
class Outer:
    method: Literal["a", "b"]
    rate: float = 0.1
    tags: list[str] = field(default_factory=list)
    inner: Inner = field(default_factory=Inner)
    path: str | None = None


def test_yaml_overrides_and_nested(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("method: a\ninner:\n  n: 3\n")
    cfg = load_config(Outer, p, ["inner.name=hf", "rate=1", "tags=[x, y]", "path=null"])
    assert cfg == Outer("a", 1.0, ["x", "y"], Inner("hf", 3), None)


@pytest.mark.parametrize("text, sets, message", [
    ("method: a\nlr: 3\n", [], "c.yaml: unknown key 'lr'"),
    ("method: a\ninner: {nn: 3}\n", [], "c.yaml: unknown key 'inner.nn'"),
    ("method: a\n", ["inner.n=five"], "c.yaml: inner.n: expected int, got 'five'"),
    ("method: c\n", [], "c.yaml: method: expected one of ['a', 'b'], got 'c'"),
    ("rate: 2\n", [], "c.yaml: missing required key 'method'"),
    ("method: [a\n", [], "c.yaml:2: invalid YAML"),
])
def test_errors_name_the_key(tmp_path, text, sets, message):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(DegustaError) as err:
        load_config(Outer, p, sets)
    assert message in str(err.value)


def test_atomic_writes_have_normal_permissions_and_leave_nothing_on_error(tmp_path):
    import os

    from degusta_learn.fileio import atomic_open, atomic_write_text

    atomic_write_text(tmp_path / "a.txt", "hi")
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o666 & ~_umask()
    with pytest.raises(RuntimeError), atomic_open(tmp_path / "b.txt") as f:
        f.write("half")
        raise RuntimeError("interrupted")
    assert sorted(os.listdir(tmp_path)) == ["a.txt"]


def _umask():
    import os

    m = os.umask(0)
    os.umask(m)
    return m


def test_choices_of_dataclasses_built_in_python_are_checked_like_the_loader_does():
    """`check_choices`: a `Literal` (or `Literal | None`) field built in Python gets the loader's one line."""
    from degusta_learn.finetune.lora import LoraConfig
    from degusta_learn.prompting.backends.openai import OpenAIConfig

    with pytest.raises(DegustaError, match=r"^lora.mode: expected one of \['lora', 'qlora', 'full'\], got 'qlora4'"):
        LoraConfig(mode="qlora4")
    with pytest.raises(DegustaError, match=r"^backend.detail: expected one of \['low', 'high', 'auto'\]"):
        OpenAIConfig(detail="medium")
    assert OpenAIConfig(detail=None).detail is None and OpenAIConfig(detail="low").detail == "low"
