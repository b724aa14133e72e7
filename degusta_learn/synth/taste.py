"""Object taste: how much a person's favourite colours and materials like each catalog object.

taste(object) = the share of the object's colours that are favourite colours
              + 0.25 x the number of its two material slots (material1, material2) that are favourite
so a one-colour object in a favourite colour and favourite material scores 1.5. Feature matrices are built
once per catalog (cached), so scoring a person is two small matrix products.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from degusta_learn.scene import Catalog


@dataclass(frozen=True)
class TypeFeatures:
    """The objects of one type: ids (n,), colour shares (n, C), material counts (n, M) and vocabularies."""

    ids: np.ndarray
    colors: np.ndarray
    materials: np.ndarray
    color_names: tuple[str, ...]
    material_names: tuple[str, ...]

    def taste(self, colors, materials) -> np.ndarray:
        """(n,) taste scores for favourite `colors` and `materials`."""
        c = np.array([name in colors for name in self.color_names], dtype=float)
        m = np.array([name in materials for name in self.material_names], dtype=float)
        return self.colors @ c + 0.25 * (self.materials @ m)


_CACHE: list[tuple[Catalog, dict]] = []  # (catalog, features) of recently used catalogs, by identity


def catalog_features(catalog: Catalog) -> dict[str, TypeFeatures]:
    """Per object type, the feature matrices used by `TypeFeatures.taste` (cached per catalog object)."""
    for cached, feats in _CACHE:
        if cached is catalog:
            return feats
    feats = _build(catalog)
    _CACHE[:] = [*_CACHE[-3:], (catalog, feats)]
    return feats


def _build(catalog: Catalog) -> dict[str, TypeFeatures]:
    color_names = tuple(sorted({c for o in catalog for c in (o.color1, o.color2)}))
    material_names = tuple(sorted({m for o in catalog for m in (o.material1, o.material2)}))
    out = {}
    for type_ in catalog.types:
        objs = catalog.of_type(type_)
        colors = np.zeros((len(objs), len(color_names)))
        materials = np.zeros((len(objs), len(material_names)))
        for i, o in enumerate(objs):
            for c in o.colors:
                colors[i, color_names.index(c)] = 1.0 / len(o.colors)
            materials[i, material_names.index(o.material1)] += 1
            materials[i, material_names.index(o.material2)] += 1
        out[type_] = TypeFeatures(np.array([o.id for o in objs], dtype=np.int64), colors, materials,
                                  color_names, material_names)
    return out
