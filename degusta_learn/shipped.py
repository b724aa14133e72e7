"""What ships inside the package: the configs (list them, find one by name, copy one out to edit) and the models.

Usage:
    degusta configs list                             # every shipped config and its one-line purpose
    degusta configs copy finetune_tiny_cpu my_runs/  # -> my_runs/finetune_tiny_cpu.yaml, yours to edit
    degusta train --config finetune_tiny_cpu         # every --config takes a path or a shipped name

The files live in `degusta_learn/configs/` (package data, installed by a plain `pip install .`); a source
checkout also reaches them as `configs/`, so `--config configs/learned_cpu.yaml` works in the checkout and,
through the name, from any other folder. The shipped models live in `degusta_learn/shipped_models/`
(package data too); a config names one by its folder name (`model: tiny_vlm_base`), see vlm/hub.py.
"""

from __future__ import annotations

import difflib
import re
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.files.atomic import atomic_write_bytes

SHIPPED_DIR = Path(__file__).resolve().parent / "configs"
PURPOSE_CHARS = 110  # a purpose longer than this is cut at a word boundary and ends with "…"


MODELS_DIR = Path(__file__).resolve().parent / "shipped_models"
"""The models shipped inside the package (package data, like the configs): every install has them."""
BASE_NAME = "tiny_vlm_base"
BASE_DIR = MODELS_DIR / BASE_NAME
"""The perception-pretrained tiny base VLM (configs/pretrain_tiny_vlm_cpu.yaml built it); configs name it
`tiny_vlm_base`."""


def shipped_model_names() -> list[str]:
    """The names of the shipped models (their folder names), sorted."""
    return sorted(p.name for p in MODELS_DIR.iterdir() if (p / "config.json").is_file()) if MODELS_DIR.is_dir() else []


def shipped_model(name: str) -> Path | None:
    """The folder of the shipped model `name` (e.g. "tiny_vlm_base"), or None if no shipped model has that name."""
    return MODELS_DIR / name if name in shipped_model_names() else None


def is_shipped_base(name: str | Path) -> bool:
    """Whether a model name or folder is the shipped tiny base (its name, or its folder by any path)."""
    path = Path(name).expanduser()
    folder = path if path.is_dir() else shipped_model(str(name))  # a folder wins, as in vlm.hub.resolve_model
    return folder is not None and folder.resolve() == BASE_DIR.resolve()


def shipped_base() -> Path | None:
    """The shipped tiny base's folder, or None where its weights are absent (a broken install)."""
    return BASE_DIR if (BASE_DIR / "config.json").is_file() and (BASE_DIR / "model.safetensors").is_file() else None


def shipped_names() -> list[str]:
    """The names (file stems) of every shipped config, sorted."""
    return sorted(p.stem for p in SHIPPED_DIR.glob("*.yaml"))


def _name_of(value: str) -> str | None:
    """`learned_cpu`, `learned_cpu.yaml` or `configs/learned_cpu.yaml` -> `learned_cpu`; any other path -> None."""
    path = Path(value)
    if path.parent not in (Path("."), Path("configs")):
        return None
    return path.stem if path.suffix in (".yaml", ".yml") else path.name


def shipped_config(name: str) -> Path:
    """The installed file of the shipped config `name` (with or without .yaml); unknown -> DegustaError."""
    found = _name_of(name)
    if found in shipped_names():
        return SHIPPED_DIR / f"{found}.yaml"
    close = difflib.get_close_matches(found or name, shipped_names(), n=3, cutoff=0.5)
    hint = f"close matches: {', '.join(close)}" if close else "`degusta configs list` shows every name"
    raise DegustaError(f"{name!r}: no shipped config of that name ({hint})")


def resolve_config(value: str | Path) -> Path:
    """A `--config` value: an existing path wins, else a shipped config name; neither -> DegustaError."""
    path = Path(value)
    if path.exists():
        return path
    try:
        return shipped_config(str(value))
    except DegustaError as e:
        raise DegustaError(f"{str(value)!r}: no such file, and {str(e).split(': ', 1)[1]}") from None


def resolve_or_keep(value: str) -> str:
    """`value` itself if it exists or names no shipped config (its user reports the problem), else the shipped file."""
    try:
        return str(resolve_config(value))
    except DegustaError:
        return value


def purpose(path: Path) -> str:
    """The config's one-line purpose: the first sentence of its header comment, after the command lines.

    The header's leading command lines (`# degusta ...` and the indented `#   override example: ...`
    under it) are skipped; the purpose is the text from there to the first sentence end (". "), stopping
    at a blank comment line, the end of the header, or an indented example block the text introduces
    with ":". It is cut at a word boundary to PURPOSE_CHARS characters.
    """
    lines: list[str] = []
    for raw in path.read_text(encoding="utf-8").splitlines():
        body = raw[1:] if raw.startswith("#") else None
        text = (body or "").strip()
        indented = body is not None and body.startswith("  ")
        if not lines:
            if body is None:
                break
            if text and not indented and not text.startswith("degusta "):
                lines.append(text)
            continue
        if body is None or not text or (indented and lines[-1].endswith(":")):
            break
        lines.append(text)
    sentence = re.split(r"(?<!e\.g\.)(?<!i\.e\.)(?<=\.)\s", " ".join(lines), maxsplit=1)[0].rstrip(":")
    if len(sentence) > PURPOSE_CHARS:
        sentence = sentence[:PURPOSE_CHARS - 1].rsplit(" ", 1)[0].rstrip(",;:") + "…"
    return sentence


def list_configs() -> list[tuple[str, str]]:
    """(name, one-line purpose) of every shipped config."""
    return [(name, purpose(SHIPPED_DIR / f"{name}.yaml")) for name in shipped_names()]


def run_command(path: Path, target: Path) -> str | None:
    """The header's launch command (`degusta VERB --config ...`) pointed at `target`, or None without one."""
    first = path.read_text(encoding="utf-8").partition("\n")[0]
    match = re.fullmatch(r"#\s*(degusta \w+) --config \S+(.*)", first)
    return f"{match[1]} --config {target}{match[2]}" if match else None


def copy_config(name: str, dest: str | Path = ".") -> Path:
    """Write the shipped config `name` into folder `dest` (or to `dest` itself if it ends in .yaml); never overwrites."""
    src = shipped_config(name)
    dest = Path(dest)
    if dest.suffix and dest.suffix not in (".yaml", ".yml") and not dest.is_dir():  # `copy NAME notes.txt`
        raise DegustaError(f"{dest}: a config is written into a folder or to a .yaml file; {dest.name!r} is neither "
                           f"an existing folder nor a .yaml name (give {dest.with_suffix('.yaml')} or a folder)")
    target = dest if dest.suffix in (".yaml", ".yml") else dest / src.name
    if target.exists() or target.is_symlink():
        raise DegustaError(f"{target}: already exists; not overwritten (remove it, or copy into another folder)")
    atomic_write_bytes(target, src.read_bytes())
    return target
