"""Where a model named in a config comes from: a local folder, a model shipped with degusta, or the Hub.

`resolve_model(name, key)` turns a config's model name into a local folder, in this order:

1. an existing folder (`runs/my_run/model`, `~/models/smolvlm`): used as it is;
2. the name of a model shipped inside the package (`tiny_vlm_base`, in `degusta_learn/shipped_models/`);
3. a Hugging Face Hub id (`HuggingFaceTB/SmolVLM-256M-Instruct`): taken from the standard Hugging Face
   cache (`HF_HOME`, `HF_HUB_CACHE`), downloaded into it first when missing, as transformers, peft and TRL
   do. Downloads are the top-level config, processor, tokenizer and safetensors files (`HUB_FILES`; no
   ONNX or other sub-folders, no pickled `.bin` weights); `weights=False` (the dry run) takes all but the
   weights.

Offline, the Hugging Face way: with `HF_HUB_OFFLINE=1` (or `local_files_only=True`) nothing is
downloaded and a hub id missing from the cache is refused at once, in one line naming the config key and
the command that fetches it (`hf download ID`). degusta never sets `HF_HUB_OFFLINE` itself; its tests do.
Every other Hub problem (a typo'd id, a gated or private repo, a half-finished download, no network, a full
disk) is one line naming the key, never a traceback.

Usage:
    folder = resolve_model("HuggingFaceTB/SmolVLM-256M-Instruct", key="model.name")   # downloads if needed
    folder = resolve_model("tiny_vlm_base", key="model.name")                         # the shipped base
"""

from __future__ import annotations

import json
from pathlib import Path

from degusta_learn.errors import DegustaError

HUB_FILES = ["*.json", "*.safetensors", "*.txt", "*.model", "*.jinja", "*.tiktoken"]
"""What a hub id's download takes: configs (model, generation, processor, tokenizer, chat template),
tokenizer vocabularies and the safetensors weights."""
HUB_SKIP = ["*/*"]
"""Never a file in a sub-folder (ONNX exports, other precisions, training logs): only the top level loads."""
WEIGHT_FILES = ["*.safetensors"]

MODEL_JSON_FILES = ("config.json", "generation_config.json", "processor_config.json", "preprocessor_config.json",
                    "tokenizer_config.json", "special_tokens_map.json", "tokenizer.json", "adapter_config.json")


def offline(local_files_only: bool = False) -> bool:
    """Whether the Hub may not be asked: `local_files_only`, or `HF_HUB_OFFLINE` set (read by huggingface_hub
    when it is first imported, as for every Hugging Face library)."""
    from huggingface_hub.constants import is_offline_mode

    return local_files_only or is_offline_mode()


def looks_like_a_path(name: str) -> bool:
    """A name that can only be a folder: starts with `.`, `/` or `~`, or has more than one `/` (a hub id has one)."""
    return name.startswith((".", "/", "~")) or name.count("/") > 1 or "\\" in name


def resolve_model(name: str, key: str = "model", weights: bool = True, local_files_only: bool = False) -> Path:
    """The local folder of the model `name` (a folder, a shipped model name or a hub id; see the module doc).

    Args:
        name: the config's value.
        key: the config key named in every error.
        weights: False takes a hub model's config and processor files only (the dry run).
        local_files_only: never ask the Hub, as if `HF_HUB_OFFLINE=1`.
    """
    from degusta_learn.shipped import shipped_model, shipped_model_names

    name = str(name)
    path = Path(name).expanduser()
    if path.is_dir():
        return checked_folder(path, key)
    shipped = shipped_model(name)
    if shipped is not None:
        return checked_folder(shipped, key)
    if looks_like_a_path(name) or not name.strip():
        raise DegustaError(f"{key}: model folder {name} not found{_shipped_hint(name, shipped_model_names())}")
    return checked_folder(download(name, key, weights=weights, local_files_only=local_files_only), key, hub_id=name)


def local_folder(name: str | None) -> Path | None:
    """The folder `name` stands for without asking the Hub: an existing folder or a shipped model; else None."""
    from degusta_learn.shipped import shipped_model

    if not name:
        return None
    path = Path(str(name)).expanduser()
    return path if path.is_dir() else shipped_model(str(name))


def metadata_folder(name: str | None, key: str, adapter: bool = False) -> Path | None:
    """Where to read a model's or adapter's degusta record before loading it: an existing folder or a shipped
    model as it is (unchecked); a hub id's JSON files, downloaded if missing (refused offline when uncached); None
    for a local path that does not exist (the load reports it)."""
    found = local_folder(name) if not adapter else (Path(str(name)).expanduser() if name else None)
    if found is not None and found.is_dir():
        return found
    if not name or looks_like_a_path(str(name)) or Path(str(name)).expanduser().exists():
        return None
    return resolve_adapter(name, key) if adapter else resolve_model(name, key, weights=False)


def resolve_adapter(name: str, key: str = "adapter", local_files_only: bool = False) -> Path:
    """The local folder of a peft adapter: a folder, or a hub id (an adapter published with `hf upload`)."""
    name = str(name)
    path = Path(name).expanduser()
    if path.is_dir() or looks_like_a_path(name) or not name.strip():
        return path  # load_adapter names a missing folder or a folder without adapter_config.json
    folder = download(name, key, local_files_only=local_files_only)
    if not (folder / "adapter_config.json").is_file():
        raise DegustaError(f"{key}: {name!r} (cached at {folder}) has no adapter_config.json: not a peft adapter")
    return folder


def _shipped_hint(name: str, shipped: list[str]) -> str:
    """`; the shipped base is named tiny_vlm_base` when the missing folder ends in a shipped model's name."""
    base = Path(name.rstrip("/")).name
    if base in shipped:
        return f" (the shipped model {base!r} is named by its name alone: `{base}`)"
    return f" (the shipped models are named {', '.join(shipped)})" if shipped else ""


def download(repo_id: str, key: str, weights: bool = True, local_files_only: bool = False) -> Path:
    """The cached snapshot folder of hub model `repo_id`, downloaded into the standard cache when missing."""
    from huggingface_hub import errors, snapshot_download
    from huggingface_hub.errors import (
        GatedRepoError,
        HfHubHTTPError,
        HFValidationError,
        LocalEntryNotFoundError,
        RepositoryNotFoundError,
        RevisionNotFoundError,
    )

    incomplete = getattr(errors, "IncompleteSnapshotError", ())  # a LocalEntryNotFoundError; newer hubs only

    import degusta_learn

    fetch = f"`hf download {repo_id}`"
    is_offline = offline(local_files_only)
    try:
        folder = snapshot_download(repo_id, allow_patterns=HUB_FILES if weights else
                                   [p for p in HUB_FILES if p not in WEIGHT_FILES],
                                   ignore_patterns=HUB_SKIP, local_files_only=is_offline, library_name="degusta_learn",
                                   library_version=degusta_learn.__version__)
    except HFValidationError as e:
        raise DegustaError(f"{key}: {repo_id!r} is neither a local folder nor a valid Hugging Face Hub id "
                           f"({_first_line(e)}){_folder_hint(repo_id)}") from None
    except incomplete as e:  # a download that was interrupted, now offline or unreachable
        raise DegustaError(f"{key}: the cached copy of {repo_id!r} is incomplete (an interrupted download?: "
                           f"{_missing(e)}); complete it with {fetch} on a machine that reaches the Hub") from None
    except GatedRepoError:  # a RepositoryNotFoundError: first
        raise DegustaError(f"{key}: {repo_id!r} is gated on the Hugging Face Hub: accept its terms on "
                           f"https://huggingface.co/{repo_id}, then log in with `hf auth login`") from None
    except RepositoryNotFoundError:
        raise DegustaError(f"{key}: {repo_id!r}: no such model on the Hugging Face Hub (a typo? a private repo needs "
                           f"`hf auth login`){_folder_hint(repo_id)}") from None
    except RevisionNotFoundError as e:
        raise DegustaError(f"{key}: {repo_id!r}: {_first_line(e)}") from None
    except LocalEntryNotFoundError as e:
        if is_offline:
            why = "HF_HUB_OFFLINE is set" if not local_files_only else "local_files_only is set"
            raise DegustaError(f"{key}: {repo_id!r} is not in the local Hugging Face cache and downloads are off "
                               f"({why}): download it with {fetch} (or unset HF_HUB_OFFLINE){_folder_hint(repo_id)}"
                               ) from None
        raise DegustaError(f"{key}: {repo_id!r} could not be downloaded and is not in the local Hugging Face cache "
                           f"(no connection to the Hub? {_first_line(e.__cause__ or e)}); retry, or fetch it with "
                           f"{fetch}{_folder_hint(repo_id)}") from None
    except HfHubHTTPError as e:
        raise DegustaError(f"{key}: downloading {repo_id!r} from the Hugging Face Hub failed: {_first_line(e)}") from None
    except OSError as e:  # a full disk, a read-only cache folder
        raise DegustaError(f"{key}: downloading {repo_id!r} into the Hugging Face cache failed: {_first_line(e)} "
                           "(set HF_HOME to a folder with space and write permission)") from None
    folder = Path(folder)
    if weights and not any(folder.glob("*.safetensors")):
        raise DegustaError(f"{key}: {repo_id!r} has no safetensors weights at the top of its repository (degusta "
                           "loads safetensors only, never pickled .bin files)")
    return folder


def _folder_hint(name: str) -> str:
    """For a relative name that reads as a hub id: where it would have been as a folder (and the shipped model's
    name, when the folder would have been one)."""
    from degusta_learn.shipped import shipped_model_names

    if "/" not in name:
        return ""
    return (f"; as a folder it would be {Path(name).absolute()}: a relative path is read from the current directory"
            + _shipped_hint(name, [n for n in shipped_model_names() if Path(name).name == n]))


def _missing(e: Exception) -> str:
    """"missing model.safetensors" from huggingface_hub's IncompleteSnapshotError message."""
    import re

    found = re.search(r"file\(s\) are missing \((.*?)\)\. ", str(e))
    return f"missing {found.group(1)}" if found else _first_line(e)


def checked_folder(folder: Path, key: str, hub_id: str | None = None) -> Path:
    """`folder` if it holds a model: config.json present and its JSON files readable (`check_json_files`)."""
    what = f"{hub_id!r} (cached at {folder})" if hub_id else str(folder)
    if not (folder / "config.json").is_file():
        raise DegustaError(f"{key}: {what} is a folder without config.json (not a saved model)")
    check_json_files(folder, key)
    return folder


def check_json_files(folder: Path, key: str) -> None:
    """The folder's JSON files the loaders read (model, processor, adapter) parse as JSON objects; else one line
    naming the file (the libraries' own errors name none, or fail later with an AttributeError). Every size they
    state is then bounded before anything is built (`vlm/bounds.py`: file sizes before reading, config, processor,
    generation and adapter sizes, chat templates), each refusal one line naming the file, the key and the bound."""
    from degusta_learn.vlm import bounds

    parsed = {}
    for name in MODEL_JSON_FILES:
        path = folder / name
        if not path.is_file():
            continue
        bounds.check_size(path, key)
        try:
            data = json.loads(path.read_bytes())
        except (OSError, ValueError, RecursionError) as e:  # UnicodeDecodeError and JSONDecodeError included
            raise DegustaError(f"{key}: {path}: not readable as JSON ({_first_line(e)[:200]})") from None
        if not isinstance(data, dict):
            raise DegustaError(f"{key}: {path}: expected a JSON object, got {type(data).__name__}")
        bounds.check_json(path, data, key)
        parsed[name] = data
    bounds.check_folder(folder, key, parsed)


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}"[:400]
