"""The oracle (method `oracle`): the participant's own latent style applied to the target table.

It dispatches on meta.json "generator" (`ORACLE_FAMILIES`): the slot styles of the naturalistic and simulated
generators here, the relational generator's placement rules in relational_oracle.py; data whose meta.json names
another generator (a study's own data, `degusta collect`) is refused in one line, naming it. Data with no
"generator" at all is read as slot styles (a `styles:` file given for it).

For slot styles it predicts the style's *expected* arrangement (realize.expected_arrangement): the slots the
person sets at least half the time, their favourite objects, at the style's anchor and spacing on the target
table, with no noise. Only a synthetic dataset has latent styles (latent_styles.json, written by
`degusta data generate`), so this is an information ceiling, not an achievable floor: it knows the style that
the context trials only hint at (`posterior` is the floor achievable from the contexts). What is left of its
error is the participant's own noise, though a method can still beat it on a single episode.

Usage:
    degusta predict --config configs/oracle.yaml
    degusta predict --config configs/oracle.yaml --set context=0 --set out=runs/oracle/k0.jsonl

    from degusta_learn.synth.oracle import predict_oracle
    preds = predict_oracle(ds, styles, episodes)       # styles: {participant: Style}
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.methods import MethodSpec, PredictConfig
from degusta_learn.scene import Dataset, Episode, Prediction
from degusta_learn.synth.realize import expected_arrangement
from degusta_learn.synth.style import STYLES_FILE, Style, read_styles

ORACLE_FAMILIES = {"naturalistic": "slots", "simulated": "slots", "relational": "relations"}
"""Generator (meta.json "generator", without the `degusta_learn.synth.` prefix) -> the kind of its latent styles."""
_PREFIX = "degusta_learn.synth."


@dataclass
class OracleConfig(PredictConfig):
    """Predict config of `oracle`."""

    styles: str | None = None
    """Latent styles file; unset = the dataset's own (meta.json "latent_styles", else latent_styles.json)."""


def _own_styles(ds: Dataset) -> Path:
    """The dataset folder's latent styles file (meta.json "latent_styles", else latent_styles.json)."""
    return ds.root / str(ds.meta.get("latent_styles") or STYLES_FILE)


def style_family(ds: Dataset, refuse: bool = True) -> str | None:
    """"slots" or "relations": the kind of latent style of the generator that made `ds` (meta.json "generator"; no
    generator: "slots"). Another generator: DegustaError naming it (`refuse`), else None."""
    generator = (ds.meta or {}).get("generator")
    if generator is None:
        return "slots"
    name = generator[len(_PREFIX):] if isinstance(generator, str) and generator.startswith(_PREFIX) else generator
    if name in ORACLE_FAMILIES:
        return ORACLE_FAMILIES[name]
    if not refuse:
        return None
    where = ds.root / "meta.json" if ds.root is not None else "the dataset's meta"
    raise DegustaError(f"oracle: {where} names generator {generator!r}, which has no oracle (the oracle knows the "
                       f"latent styles of {', '.join(_PREFIX + g for g in ORACLE_FAMILIES)})")


def styles_path(ds: Dataset, override: str | None = None) -> Path:
    """Where the dataset's latent styles are; DegustaError if there are none."""
    if override:
        path = Path(override)
    elif ds.root is not None:
        path = _own_styles(ds)
    else:
        raise DegustaError("oracle needs a synthetic dataset with latent styles (this dataset has no folder)")
    if not path.is_file():
        raise DegustaError(f"oracle needs a synthetic dataset with latent styles: {path} not found "
                           "(make one with `degusta data generate`)")
    return path


def check_style_objects(style: Style, catalog, where: str) -> None:
    """Every slot's favourite object is an object of the slot's type in `catalog` (DegustaError naming it)."""
    for i, slot in enumerate(style.slots):
        if slot.object not in catalog or catalog[slot.object].type != slot.type:
            raise DegustaError(f"{where}: participant {style.participant!r}: slots[{i}]: object {slot.object} is not "
                               f"a {slot.type} of the dataset's catalog")


def dataset_styles(ds: Dataset) -> dict | None:
    """The dataset folder's latent styles ({participant: Style}, or RelationalStyle for relational data), each
    checked and its objects found in the catalog; None if it has none."""
    if ds.root is None:
        return None
    path = _own_styles(ds)
    if not os.path.lexists(path):
        return None
    if style_family(ds, refuse=False) == "relations":
        from degusta_learn.synth.relational_oracle import read_checked

        return read_checked(path, ds.catalog)
    styles = read_styles(path)
    for style in styles.values():  # a participant without a style is fine: the oracle refuses only its episodes
        check_style_objects(style, ds.catalog, str(path))
    return styles


def predict_oracle(ds: Dataset, styles: dict[str, Style], episodes: list[Episode], method: str = "oracle",
                   where: str = "latent styles") -> list[Prediction]:
    """One noiseless expected-arrangement prediction per episode (context is not needed)."""
    out = []
    for ep in episodes:
        style = styles.get(ep.participant)
        if style is None:
            raise DegustaError(f"{where}: no latent style for participant {ep.participant!r}")
        check_style_objects(style, ds.catalog, where)
        table = ds.tables[ds.arrangement(ep.participant, ep.target).table]
        placements = expected_arrangement(style, table)
        out.append(Prediction(ep.id, ep.participant, ep.target, method, placements,
                              diagnostics={"template": style.template}))
    return out


def run(cfg: OracleConfig, ds: Dataset, episodes: list[Episode]) -> list[Prediction]:
    family = style_family(ds)  # another generator's data: refused before any file is read
    path = styles_path(ds, cfg.styles)
    if family == "relations":
        from degusta_learn.synth.relational_oracle import predict_relational_oracle, read_checked

        return predict_relational_oracle(ds, read_checked(path, ds.catalog), episodes, cfg.method, where=str(path))
    return predict_oracle(ds, read_styles(path), episodes, cfg.method, where=str(path))


ORACLE = MethodSpec(OracleConfig, run, "the participant's latent style applied to the target table without "
                                       "noise (synthetic data only): an information ceiling")
