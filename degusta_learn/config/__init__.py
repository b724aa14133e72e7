"""Typed configs from YAML: dataclasses, `--set key=value` overrides and errors that name the key.

Only this package (and the CLI) reads YAML. A config class is a dataclass whose fields carry a one-line
docstring-like comment; nested sections are nested dataclasses. `load_config` checks every key and
type and raises `DegustaError` with messages such as
``configs/x.yaml: backend.n: expected int, got 'five'`` or ``configs/x.yaml: unknown key 'lr'``.

Hostile or oversized input is refused with one line, never loaded: YAML whose aliases expand past
`MAX_YAML_NODES` values (a "billion laughs" bomb) or refer to themselves, files over `MAX_CONFIG_BYTES`,
non-UTF-8, too-deep nesting, non-finite floats, and numbers outside the range a field declares with
`bounded(default, lo, hi)` (e.g. ``x.yaml: model.image_size: expected a value from 16 to 4,096, got 60000``).

Numbers and booleans are read as YAML 1.2 (its core schema), in files and in `--set` values alike, never as
PyYAML's YAML 1.1: `010` is 10 (not octal 8), `0o10` 8, `0x10` 16, `1e3` and `6e-3` are floats; `1:30` (not 90),
`1_000`, `0b10`, `yes`, `no`, `on`, `off` and `2024-01-05` are text, so a number or boolean key given one of them
is refused with one line naming the key. Only `true` / `false` are booleans; `.inf` / `.nan` are refused by every
number key (non-finite). Path keys (`PATH_KEYS`: `dataset`, `out`, `episodes`, ...) have `~` expanded and are
checked by `files.paths.check_path` (NUL bytes, names too long, non-UTF-8, a parent that is a file ...), naming the key.

Example:
    cfg = load_config(MyConfig, "configs/learned_cpu.yaml", overrides=["trainer.max_epochs=3"])

Modules: fields.py (`bounded`, `seed_field`, `check_choices`, `show_value`), yaml_io.py (`read_yaml`, `dump_yaml`,
`apply_overrides`), loading.py (`from_dict`, `load_config`, `to_dict`, `PATH_KEYS`); every name is importable from
`degusta_learn.config` itself.
"""

from degusta_learn.config.fields import (
    MAX_SEED,
    bounded,
    check_bounds,
    check_choices,
    check_seed,
    seed_field,
    show_value,
)
from degusta_learn.config.loading import PATH_KEYS, from_dict, load_config, path_key, to_dict
from degusta_learn.config.yaml_io import (
    MAX_CONFIG_BYTES,
    MAX_YAML_NODES,
    apply_overrides,
    dump_yaml,
    read_yaml,
)

__all__ = ["MAX_CONFIG_BYTES", "MAX_SEED", "MAX_YAML_NODES", "PATH_KEYS", "apply_overrides", "bounded", "check_bounds",
           "check_choices", "check_seed", "dump_yaml", "from_dict", "load_config", "path_key", "read_yaml", "seed_field",
           "show_value", "to_dict"]
