"""The domain tokenizer: ids, cells and answer literals are single tokens; text round-trips exactly."""

from __future__ import annotations

import functools

from degusta_learn.pretrain.base import SPECIAL
from degusta_learn.pretrain.vocab import answer_literals, domain_tokenizer
from degusta_learn.render.grid import Grid
from degusta_learn.scene import Placement, default_catalog
from degusta_learn.task.answer_format import answer_items, format_answer


@functools.cache
def tokenizer():
    return domain_tokenizer(SPECIAL, 2048)


def test_ids_cells_and_literals_are_single_tokens():
    tok = tokenizer()
    assert all(len(tok.encode(str(i)).ids) == 1 for i in range(256))
    assert all(len(tok.encode(c).ids) == 1 for c in Grid(12, 12).cells)
    assert all(len(tok.encode(s).ids) == 1 for s in answer_literals())
    assert [tok.token_to_id(s) for s in SPECIAL] == list(range(len(SPECIAL)))  # special tokens first


def test_an_answer_item_costs_about_thirteen_tokens_and_round_trips():
    tok = tokenizer()
    catalog = default_catalog()
    placements = [Placement(80, 0.5, 0.5, 0.0), Placement(30, 0.3, 0.5, 0.0), Placement(3, 0.7, 0.3, 90.0)]
    items = answer_items(placements, catalog, "grid", Grid(8, 8))
    text = format_answer(items, "grid")
    ids = tok.encode(text).ids
    # per item: opening literal, type, "', 'id': ", id, position literal, cells with "', '" between them,
    # direction literal, direction; then the closing "'}]"
    assert len(ids) == sum(6 + 2 * len(it.cells) for it in items) + 1
    assert tok.decode(ids) == text
    prose = "Placement order in final_state_2.jpg: plate, fork, knife. Cell C7 — naïve “quotes” ✓"
    assert tok.decode(tok.encode(prose).ids) == prose  # byte-level: any text encodes and decodes exactly
