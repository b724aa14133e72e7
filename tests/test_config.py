from dataclasses import dataclass, field
from typing import ClassVar, Literal

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


def test_numbers_in_exponent_notation_are_numbers_where_a_float_is_expected(tmp_path):
    """Configs are read as YAML 1.2, where 6e-3 is a number (YAML 1.1, PyYAML's, read it as text): a float key
    takes it; a string key refuses the number (its text is lost) and keeps the quoted text; other text is refused."""
    p = tmp_path / "c.yaml"
    p.write_text("method: a\nrate: 6e-3\n")
    assert load_config(Outer, p).rate == 0.006
    assert load_config(Outer, p, ["rate=-1.5E+2"]).rate == -150.0
    assert load_config(Outer, p, ["path='6e-3'"]).path == "6e-3"
    with pytest.raises(DegustaError, match="path: expected a string, got the number 0.006"):
        load_config(Outer, p, ["path=6e-3"])
    for bad in ("6e", "e-3", "fast", "1e999"):
        with pytest.raises(DegustaError, match="rate: expected"):
            load_config(Outer, p, [f"rate={bad}"])


@dataclass
class Kind:
    """A config kind whose sections default to configured instances, as PretrainConfig's optim and data do."""
    inner: Inner = field(default_factory=lambda: Inner(name="hf", n=9))
    outer: Outer = field(default_factory=lambda: Outer("b", rate=0.5, inner=Inner("local", 2)))


def test_a_partial_section_keeps_the_kinds_defaults_for_the_keys_it_does_not_give(tmp_path):
    # `--set inner.n=3` on a kind whose inner section defaults to Inner(name="hf", n=9) must keep name "hf",
    # not fall back to the class default "openai" (it did: a one-key override reset the section's other keys)
    assert load_config(Kind, None, ["inner.n=3"]) == Kind(inner=Inner("hf", 3))
    assert load_config(Kind, None, ["outer.inner.n=7"]).outer == Outer("b", 0.5, [], Inner("local", 7))
    p = tmp_path / "k.yaml"
    p.write_text("outer:\n  rate: 0.25\n")
    assert load_config(Kind, p).outer == Outer("b", 0.25, [], Inner("local", 2))
    assert load_config(Kind, None) == Kind()  # nothing given: the kind's defaults
    with pytest.raises(DegustaError, match=r"unknown key 'inner.nn'"):
        load_config(Kind, None, ["inner.nn=1"])


def test_a_partial_pretraining_mix_keeps_the_curriculums_short_prompts():
    from degusta_learn.pretrain.train import PretrainConfig

    cfg = load_config(PretrainConfig, None, ["data.curriculum_mix.lists=0", "optim.weight_decay=0.1"])
    mix = cfg.data.curriculum_mix
    assert (mix.lists, mix.scenes, mix.objects_sheet, mix.gomo, mix.describe_questions) == (0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 8)
    assert (cfg.optim.lr, cfg.optim.warmup_steps, cfg.optim.weight_decay) == (1.5e-3, 100, 0.1)


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


@dataclass
class Pruned:
    REMOVED: ClassVar[dict[str, str]] = {"old_weight": "the old loss; no shipped recipe used it"}
    kept: int = 1


@dataclass
class WithPruned:
    section: Pruned = field(default_factory=Pruned)


def test_a_removed_key_is_refused_in_one_line_that_says_it_was_removed_and_why(tmp_path):
    p = tmp_path / "x.yaml"
    p.write_text("section:\n  kept: 2\n  old_weight: 0.0\n")
    with pytest.raises(DegustaError) as err:
        load_config(WithPruned, p)
    assert str(err.value) == f"{p}: section.old_weight: removed (the old loss; no shipped recipe used it)"
    with pytest.raises(DegustaError, match="^config: section.old_weight: removed"):
        load_config(WithPruned, None, ["section.old_weight=1"])
    with pytest.raises(DegustaError, match="unknown key 'section.other'"):  # other unknown keys: as before
        load_config(WithPruned, None, ["section.other=1"])


def test_the_pretrain_configs_removed_keys_say_why(tmp_path):
    from degusta_learn.pretrain.config import PretrainConfig

    p = tmp_path / "old.yaml"
    p.write_text("kind: pretrain\ndata:\n  teacher_weight: 0.0\n")
    with pytest.raises(DegustaError) as err:
        load_config(PretrainConfig, p)
    assert str(err.value) == (f"{p}: data.teacher_weight: removed (the oracle teacher's pull on the tower's tokens; "
                              "no shipped recipe used it)")
    for key in ("freeze_projector", "retrieval_list_items"):
        with pytest.raises(DegustaError, match=f"^config: data.{key}: removed \\(.+; no shipped recipe used it\\)$"):
            load_config(PretrainConfig, None, [f"data.{key}=false"])


def test_atomic_writes_have_normal_permissions_and_leave_nothing_on_error(tmp_path):
    import os

    from degusta_learn.files.atomic import atomic_open, atomic_write_text

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


def test_an_unquoted_yaml_boolean_where_a_word_is_expected_says_to_quote_it():
    """`--set cache=off` is the boolean False in YAML: the message said so but not what to do."""
    from degusta_learn.config import from_dict

    @dataclass
    class C:
        cache: str = "auto"
        mode: Literal["on", "off"] = "on"

    for data in ({"cache": False}, {"mode": True}):
        with pytest.raises(DegustaError, match="write the word in quotes"):
            from_dict(C, data, "c.yaml")
    with pytest.raises(DegustaError) as e:
        from_dict(C, {"cache": 5}, "c.yaml")
    assert "write the word in quotes" not in str(e.value)


@pytest.mark.parametrize("raw, message", [("9" * 5000, "a number with too many digits"),
                                          ("[" * 5000, "nested too deeply")])
def test_a_set_value_refused_by_the_parser_says_why_in_words(raw, message):
    """Was Python's text cut mid-word ("use sys.set_int_max_str_digits() t") or "maximum recursion depth"."""
    from degusta_learn.config import apply_overrides

    with pytest.raises(DegustaError, match=rf"^--set seed: refused value \({message}\)$"):
        apply_overrides({}, [f"seed={raw}"])
