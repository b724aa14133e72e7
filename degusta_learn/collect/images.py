"""The pictures the study page draws: the dataset's own (catalog and table `image`s) or the toolkit's procedural
ones, as PNG bytes, made once per study and kept in memory (a study has ~130 of them, a few MB)."""

from __future__ import annotations

import functools
import io

from degusta_learn.collect.study import Study
from degusta_learn.render.sprites import sprite
from degusta_learn.render.tables import table_image

OBJECT_UNIT = 640
"""Pixels per normalized table unit of an object's picture (a plate ~109 px): the page scales it to the table."""
TABLE_SIDE = 1024
"""Longest side of a table's picture in pixels."""
ICON_UNIT = 360


def _png(im) -> bytes:
    buf = io.BytesIO()
    im.save(buf, format="PNG", optimize=False)
    return buf.getvalue()


class StudyImages:
    """PNG pictures of one study's objects, tables and type icons."""

    def __init__(self, study: Study):
        self.study = study
        self.root = str(study.root)

    def object_png(self, object_id: int) -> bytes | None:
        return self._object(object_id, OBJECT_UNIT) if object_id in self.study.catalog else None

    def table_png(self, table_id: int) -> bytes | None:
        return self._table(table_id) if table_id in self.study.tables else None

    def type_png(self, type_: str) -> bytes | None:
        first = next((o for o in self.study.catalog.objects if o.type == type_), None)
        return self._object(first.id, ICON_UNIT) if first is not None else None

    def table_size(self, table_id: int) -> tuple[int, int]:
        t = self.study.tables[table_id]
        scale = TABLE_SIDE / max(t.width, t.height)
        return max(1, round(t.width * scale)), max(1, round(t.height * scale))

    @functools.lru_cache(maxsize=2048)  # noqa: B019 - one StudyImages per server, kept for its lifetime
    def _object(self, object_id: int, unit: int) -> bytes:
        return _png(sprite(self.study.catalog[object_id], unit, self.root))

    @functools.lru_cache(maxsize=256)  # noqa: B019
    def _table(self, table_id: int) -> bytes:
        return _png(table_image(self.study.tables[table_id], *self.table_size(table_id), self.root))


__all__ = ["StudyImages"]
