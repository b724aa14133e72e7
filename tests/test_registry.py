"""Keep the registries complete and every shipped YAML valid against its command."""

from pathlib import Path

import pytest

from degusta_learn.config import apply_overrides, from_dict, read_yaml
from degusta_learn.methods import (
    METHODS,
    TRAINERS,
    MethodSpec,
    PredictConfig,
    TrainerSpec,
    get_method,
    get_trainer,
)

CONFIGS = sorted((Path(__file__).parent.parent / "configs").glob("*.yaml"))


@pytest.mark.parametrize("name", sorted(METHODS))
def test_every_method_imports_and_has_a_predict_config(name):
    spec = get_method(name)
    assert isinstance(spec, MethodSpec) and callable(spec.run)
    assert issubclass(spec.config_cls, PredictConfig)


@pytest.mark.parametrize("name", sorted(TRAINERS))
def test_every_trainer_imports(name):
    spec = get_trainer(name)
    assert isinstance(spec, TrainerSpec) and callable(spec.run)


def test_configs_exist():
    assert CONFIGS, "configs/ has no YAML files"


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_every_config_parses_against_its_command(path):
    text = path.read_text()
    assert text.lstrip().startswith("#") and "degusta " in text.split("\n", 3)[0] + text.split("\n", 3)[1], \
        f"{path.name} must open with a comment giving its command"
    raw = read_yaml(path)
    if raw.get("kind") == "collect":  # the browser study's config (degusta collect)
        from degusta_learn.collect import StudyConfig

        from_dict(StudyConfig, raw, where=str(path))
        return
    if "kind" in raw:  # train configs (they may also name the prompt `method` they learn)
        spec = get_trainer(raw["kind"])
    elif "method" in raw:
        spec = get_method(raw["method"])
    else:
        from degusta_learn.evaluate.compare import CompareConfig  # compare configs: a list of methods

        from_dict(CompareConfig, raw, where=str(path))
        return
    from_dict(spec.config_cls, apply_overrides(raw, []), where=str(path))
