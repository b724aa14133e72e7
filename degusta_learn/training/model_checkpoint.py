"""Reading a trained arrangement model's checkpoint back: the file a run folder names, loaded weights-only, its
`kind` and `format` checked, its weights loaded into a freshly built model; every problem one line naming the file.

Used by the methods trained with `degusta train` that predict from a checkpoint (the learned slot model, the set
transformer). A checkpoint holds plain data only (`torch.load(..., weights_only=True)`), `hyper_parameters` with
`kind` (which model) and `format` (which version of it), and a `state_dict` whose model weights are under `model.`.

Example:
    path, ckpt, hp = read_checkpoint("runs/learned_cpu", "cpu", kind="learned", fmt=2, what="learned-model")
    model = load_weights(SlotModel(...), ckpt, path, "slot model")
"""

from __future__ import annotations

from pathlib import Path

from degusta_learn.errors import DegustaError


def resolve_checkpoint(path: str | Path) -> Path:
    """A run folder -> its best.ckpt (else last.ckpt); a file -> itself."""
    path = Path(path)
    if path.is_dir():
        for name in ("best.ckpt", "last.ckpt"):
            if (path / name).is_file():
                return path / name
        raise DegustaError(f"{path}: no best.ckpt or last.ckpt in this run folder (train it first)")
    if not path.is_file():
        raise DegustaError(f"{path}: checkpoint not found")
    return path


def read_checkpoint(path: str | Path, device, kind: str, fmt: int, what: str) -> tuple[Path, dict, dict]:
    """(the checkpoint file, its contents, its hyper_parameters) for a checkpoint of model `kind` and format `fmt`.

    `what` names the model in the messages ("learned-model", "set-transformer"). Raises DegustaError for a file that
    is not a weights-only checkpoint, one of another kind (use that method's predict config) or another format
    (retrain it)."""
    import torch

    ckpt_path = resolve_checkpoint(path)
    try:
        ckpt = torch.load(ckpt_path, map_location=device, weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling/format problem is a bad user file
        raise DegustaError(f"{ckpt_path}: not a loadable weights-only checkpoint ({type(e).__name__}: "
                           f"{str(e).splitlines()[0][:200] if str(e) else ''})") from None
    hp = ckpt.get("hyper_parameters") if isinstance(ckpt, dict) else None
    found = hp.get("kind") if isinstance(hp, dict) else None
    if found != kind:
        raise DegustaError(f"{ckpt_path}: a checkpoint of kind {found!r}, not a {kind!r} model "
                           f"(use the predict config of the method that trained it)")
    if hp.get("format") != fmt:
        raise DegustaError(f"{ckpt_path}: a {what} checkpoint of format {hp.get('format')!r}; this version reads "
                           f"format {fmt}: retrain it with `degusta train`")
    if not isinstance(ckpt.get("state_dict"), dict):
        raise DegustaError(f"{ckpt_path}: a {what} checkpoint without its weights (state_dict)")
    return ckpt_path, ckpt, hp


def load_weights(model, ckpt: dict, ckpt_path: Path, what: str):
    """`model` with the checkpoint's `model.` weights loaded; one line when they do not fit this version's model."""
    state = {k.removeprefix("model."): v for k, v in ckpt["state_dict"].items() if k.startswith("model.")}
    try:
        model.load_state_dict(state)
    except RuntimeError as e:  # weights that do not fit this version's model
        raise DegustaError(f"{ckpt_path}: its weights do not fit this version's {what} "
                           f"({str(e).splitlines()[-1].strip()[:200]}); retrain it with `degusta train`") from None
    return model
