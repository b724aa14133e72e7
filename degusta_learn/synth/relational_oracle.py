"""The relational oracle: a relational participant's own placement rules applied to the target table, noiseless.

`method: oracle` reaches it on data whose meta.json names the relational generator (oracle.py dispatches on
meta.json "generator"). It predicts `relational_realize.expected_relational`: the rules the person sets at least
half the time, their favourite objects, in rule order, each object against its reference on the target table
with no noise. Like the naturalistic oracle it is an information ceiling: it knows the hidden rules that the
context tables only show through noise, so what is left of its error is the person's own noise.

Usage:
    degusta data generate relational --out data/relational
    degusta predict --config oracle --set dataset=data/relational --set out=runs/oracle_relational/predictions.jsonl

    from degusta_learn.synth.relational_oracle import predict_relational_oracle
    preds = predict_relational_oracle(ds, styles, episodes)     # styles: {participant: RelationalStyle}
"""

from __future__ import annotations

from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.scene import Catalog, Dataset, Episode, Prediction
from degusta_learn.synth.relational_realize import expected_relational
from degusta_learn.synth.relational_style import RelationalStyle, read_relational_styles


def check_rule_objects(style: RelationalStyle, catalog: Catalog, where: str) -> None:
    """Every rule's favourite object is an object of the rule's type in `catalog` (DegustaError naming it)."""
    for i, rule in enumerate(style.rules):
        if rule.object not in catalog or catalog[rule.object].type != rule.type:
            raise DegustaError(f"{where}: participant {style.participant!r}: rules[{i}]: object {rule.object} is not "
                               f"a {rule.type} of the dataset's catalog")


def read_checked(path: str | Path, catalog: Catalog) -> dict[str, RelationalStyle]:
    """The relational styles of `path`, each checked and its objects found in `catalog`."""
    styles = read_relational_styles(path)
    for style in styles.values():
        check_rule_objects(style, catalog, str(path))
    return styles


def predict_relational_oracle(ds: Dataset, styles: dict[str, RelationalStyle], episodes: list[Episode],
                              method: str = "oracle", where: str = "latent styles") -> list[Prediction]:
    """One noiseless expected-arrangement prediction per episode (the context is not needed)."""
    out = []
    for ep in episodes:
        style = styles.get(ep.participant)
        if style is None:
            raise DegustaError(f"{where}: no latent style for participant {ep.participant!r}")
        check_rule_objects(style, ds.catalog, where)
        table = ds.tables[ds.arrangement(ep.participant, ep.target).table]
        out.append(Prediction(ep.id, ep.participant, ep.target, method, expected_relational(style, table),
                              diagnostics={"template": style.template}))
    return out
