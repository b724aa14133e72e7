"""The object catalog: what can be placed on a table.

An object has an integer id, a type (JSON key ``class``: cup, fork, knife, plate, spoon), up to two
colours and two materials from the paper's vocabulary, and free-text shape, pattern and texture. The
default catalog has 25 objects of each type (125 in all), built deterministically so that objects of one
type really differ (no two share colour, material, shape and pattern) and every type offers several red,
blue and yellow objects (the simulated benchmark's colour preferences need them).

Ids are assigned type by type: cups 0-24, forks 25-49, knives 50-74, plates 75-99, spoons 100-124.

Physical scale: `object_size` gives each object's footprint (width, length) in normalized table-image
units, so a plate is larger than a cup and a knife longer than a spoon. Rotation 0 means the object's
long axis points to image north (a fork's tines, a knife's blade tip, a spoon's bowl at the top).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

TYPES = ("cup", "fork", "knife", "plate", "spoon")
COLORS = ("beige", "black", "blue", "brown", "gold", "gray", "green", "pink", "purple", "red", "silver",
          "white", "yellow")
MATERIALS = ("ceramic", "glass", "metal", "plastic", "wood")

# Footprint (width, length) in normalized table-image units. Round objects are width == length.
TYPE_SIZE = {
    "plate": (0.17, 0.17),
    "cup": (0.08, 0.08),
    "fork": (0.034, 0.15),
    "knife": (0.03, 0.18),
    "spoon": (0.038, 0.135),
}

# The discrete features that matching compares (Hamming distance), in this order.
MATCH_FEATURES = ("type", "color1", "color2", "material1", "material2", "shape", "pattern")
# Feature pairs compared as unordered pairs (the paper's multi-label colours and materials): a red/blue
# object and a blue/red one have the same colours. Both features of a pair share one code space.
UNORDERED_PAIRS = (("color1", "color2"), ("material1", "material2"))
_CODE_SPACE = {second: first for first, second in UNORDERED_PAIRS}

# Per-type vocabulary of the default catalog: materials that make sense and the shapes on offer.
_TYPE_MATERIALS = {
    "cup": ("ceramic", "glass", "plastic", "metal"),
    "plate": ("ceramic", "glass", "plastic", "wood", "metal"),
    "fork": ("metal", "plastic", "wood"),
    "knife": ("metal", "plastic", "wood"),
    "spoon": ("metal", "plastic", "wood"),
}
_TYPE_SHAPES = {
    "cup": ("round", "mug", "tall", "tapered"),
    "plate": ("round", "square", "oval", "octagonal"),
    "fork": ("straight", "curved", "slim"),
    "knife": ("straight", "serrated", "rounded"),
    "spoon": ("round", "oval", "deep"),
}
_PATTERNS = ("solid", "striped", "dotted", "rimmed", "floral", "checkered")
_MATERIAL_COLORS = {
    "metal": ("silver", "gold", "gray", "black"),
    "wood": ("brown", "beige", "black"),
    "glass": ("white", "blue", "green", "pink", "purple", "red", "yellow", "gray"),
}
_TEXTURE = {"ceramic": "glossy", "glass": "smooth", "metal": "polished", "plastic": "matte", "wood": "grained"}
# Every type gets these (color, material) objects first, so colour preferences can always be served.
_ANCHORS = (("red", "plastic"), ("blue", "plastic"), ("yellow", "plastic"), ("red", "ceramic"),
            ("blue", "ceramic"), ("yellow", "ceramic"), ("red", "glass"), ("blue", "glass"),
            ("yellow", "glass"))


@dataclass(frozen=True)
class CatalogObject:
    """One object of the catalog (the paper's "objects as language" entry, plus an optional picture)."""

    id: int
    type: str
    color1: str
    color2: str
    material1: str
    material2: str
    shape: str = "round"
    pattern: str = "solid"
    texture: str = "smooth"
    image: str | None = None  # path relative to the dataset folder of an RGBA picture, if any

    def to_json(self, with_image: bool = True) -> dict:
        d = {"id": self.id, "class": self.type, "color1": self.color1, "color2": self.color2,
             "material1": self.material1, "material2": self.material2, "shape": self.shape,
             "pattern": self.pattern, "texture": self.texture}
        if with_image and self.image is not None:
            d["image"] = self.image
        return d

    @property
    def colors(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys((self.color1, self.color2)))


@dataclass(frozen=True)
class Catalog:
    """An ordered collection of objects with fast lookup by id and a feature matrix for matching."""

    objects: tuple[CatalogObject, ...]
    _by_id: dict[int, CatalogObject] = field(init=False, repr=False, compare=False)
    _features: np.ndarray = field(init=False, repr=False, compare=False)
    _row: np.ndarray | None = field(init=False, repr=False, compare=False)
    _sorted: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        by_id = {o.id: o for o in self.objects}
        object.__setattr__(self, "_by_id", by_id)
        # Integer codes of MATCH_FEATURES, one row per object; rows addressed through _row[id].
        codes = {}
        feats = np.array([[codes.setdefault((_CODE_SPACE.get(f, f), getattr(o, f)), len(codes)) for f in MATCH_FEATURES]
                          for o in self.objects], dtype=np.int32).reshape(len(self.objects), len(MATCH_FEATURES))
        # Rows by id: a dense id -> row table when ids are compact (the usual 0..124), else a sorted-id
        # search, so that a large id never sizes an allocation (an id of 1e11 once asked for 745 GiB).
        ids = np.array([o.id for o in self.objects], dtype=np.int64)
        if len(ids) and ids.min() >= 0 and ids.max() < 4 * len(ids) + 1024:
            row = np.full(int(ids.max()) + 1, -1, dtype=np.int64)
            row[ids] = np.arange(len(ids))
        else:
            row = None
        order = np.argsort(ids, kind="stable")
        object.__setattr__(self, "_features", feats)
        object.__setattr__(self, "_row", row)
        object.__setattr__(self, "_sorted", (ids[order], order))

    def __len__(self) -> int:
        return len(self.objects)

    def __iter__(self):
        return iter(self.objects)

    def __contains__(self, object_id: int) -> bool:
        return object_id in self._by_id

    def __getitem__(self, object_id: int) -> CatalogObject:
        return self._by_id[object_id]

    @property
    def ids(self) -> list[int]:
        return [o.id for o in self.objects]

    @property
    def types(self) -> list[str]:
        """The object types present, in TYPES order first, then any others sorted."""
        present = {o.type for o in self.objects}
        return [t for t in TYPES if t in present] + sorted(present - set(TYPES))

    def of_type(self, type_: str) -> list[CatalogObject]:
        return [o for o in self.objects if o.type == type_]

    def features(self, ids) -> np.ndarray:
        """Integer feature codes (len(ids), len(MATCH_FEATURES)) for Hamming-distance matching (the two
        features of an UNORDERED_PAIRS pair share codes: `metrics.matching.hamming` compares them as pairs)."""
        ids = np.asarray(ids, dtype=np.int64)
        if self._row is not None and (ids.size == 0 or (ids.min() >= 0 and ids.max() < len(self._row))):
            rows = self._row[ids]
        else:
            keys, order = self._sorted
            pos = np.clip(np.searchsorted(keys, ids), 0, max(len(keys) - 1, 0))
            rows = np.where(keys[pos] == ids, order[pos], -1) if len(keys) else np.full(ids.shape, -1)
        if rows.size and rows.min() < 0:
            raise KeyError(f"object id {int(ids.flat[int(np.argmin(rows))])} is not in the catalog")
        return self._features[rows]

    def to_json(self) -> list[dict]:
        return [o.to_json() for o in self.objects]


def object_size(obj: CatalogObject) -> tuple[float, float]:
    """Footprint (width, length) in normalized table units; unknown types get a cup-sized square."""
    return TYPE_SIZE.get(obj.type, TYPE_SIZE["cup"])


def default_catalog(per_type: int = 25, seed: int = 0) -> Catalog:
    """The default catalog: `per_type` objects of each of the five types, deterministic from `seed`."""
    rng = np.random.default_rng(seed)
    objects = []
    for t_index, type_ in enumerate(TYPES):
        seen = set()
        for k in range(per_type):
            for _attempt in itertools.count():
                obj = _make_object(t_index * per_type + k, type_, k, rng)
                key = (obj.color1, obj.color2, obj.material1, obj.material2, obj.shape, obj.pattern)
                if key not in seen or _attempt > 50:
                    seen.add(key)
                    break
            objects.append(obj)
    return Catalog(tuple(objects))


def _make_object(object_id: int, type_: str, k: int, rng: np.random.Generator) -> CatalogObject:
    materials = _TYPE_MATERIALS[type_]
    if k < len(_ANCHORS):
        color1, material1 = _ANCHORS[k]
        if material1 not in materials:  # cutlery has no ceramic/glass: plastic handle in that colour
            material1 = "plastic"
    else:
        material1 = str(rng.choice(materials))
        color1 = str(rng.choice(_MATERIAL_COLORS.get(material1, COLORS)))
    # About a third of the objects combine two colours or two materials (e.g. a metal fork, wood handle).
    two_tone = rng.random() < 0.35
    material2 = str(rng.choice(materials)) if two_tone and rng.random() < 0.5 else material1
    color2 = str(rng.choice(_MATERIAL_COLORS.get(material2, COLORS))) if two_tone else color1
    shape = str(rng.choice(_TYPE_SHAPES[type_]))
    pattern = "solid" if material1 == "metal" or rng.random() < 0.4 else str(rng.choice(_PATTERNS[1:]))
    return CatalogObject(id=object_id, type=type_, color1=color1, color2=color2, material1=material1,
                         material2=material2, shape=shape, pattern=pattern, texture=_TEXTURE[material1])
