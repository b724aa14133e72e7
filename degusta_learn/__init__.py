"""degusta_learn: personalized multi-object rearrangement (table setting).

Reproduces DegustaBot's zero-shot visual prompting and adds learned baselines, LoRA fine-tuning of
small open VLMs and one evaluation harness. See README.md for the tour.

`from degusta_learn import Planner` gives the planner (degusta_learn/planner: a plan for a new table by any method);
it is imported on first use, so `import degusta_learn` stays light.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_LAZY = {"Planner": "degusta_learn.planner"}
"""Names this package exports from a subpackage, imported when first asked for (PEP 562)."""


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'degusta_learn' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])


__all__ = ["Planner", "__version__"]
