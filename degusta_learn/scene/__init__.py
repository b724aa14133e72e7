"""The scene model (numpy only): catalog, tables, arrangements, episodes and the dataset format."""

from degusta_learn.names import CONTEXT_LENGTHS, SPLITS
from degusta_learn.scene.catalog import (
    COLORS,
    MATCH_FEATURES,
    MATERIALS,
    TYPE_SIZE,
    TYPES,
    Catalog,
    CatalogObject,
    default_catalog,
    object_size,
)
from degusta_learn.scene.dataset import (
    Dataset,
    load_dataset,
    parse_placements,
    save_dataset,
    validate_dataset,
)
from degusta_learn.scene.episodes import (
    make_episodes,
    participants_in,
    read_episodes,
    split_participants,
    write_episodes,
)
from degusta_learn.scene.predictions import read_predictions, write_predictions
from degusta_learn.scene.tables import Table, default_tables
from degusta_learn.scene.types import TASKS, Arrangement, Episode, Placement, Prediction, Rating

__all__ = [
    "COLORS", "CONTEXT_LENGTHS", "MATCH_FEATURES", "MATERIALS", "SPLITS", "TASKS", "TYPES", "TYPE_SIZE",
    "Arrangement", "Catalog", "CatalogObject", "Dataset", "Episode", "Placement", "Prediction", "Rating", "Table",
    "default_catalog", "default_tables", "load_dataset", "make_episodes", "object_size", "participants_in",
    "parse_placements", "read_episodes", "read_predictions", "save_dataset", "split_participants",
    "validate_dataset", "write_episodes", "write_predictions",
]
