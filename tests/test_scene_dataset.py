import json
import math

import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.scene import TYPES, default_catalog, default_tables, load_dataset, save_dataset


def test_default_catalog_has_25_distinct_objects_per_type():
    cat = default_catalog()
    assert len(cat) == 125 and cat.ids == list(range(125))
    for t in TYPES:
        objs = cat.of_type(t)
        assert len(objs) == 25
        keys = {(o.color1, o.color2, o.material1, o.material2, o.shape, o.pattern) for o in objs}
        assert len(keys) == 25, f"objects of type {t} repeat"
        for colour in ("red", "blue", "yellow"):
            assert sum(o.color1 == colour for o in objs) >= 2, (t, colour)
    assert cat[17].to_json()["class"] == "cup"
    assert default_catalog() == cat  # deterministic


def test_tables_contain_their_centre_not_the_corner():
    for t in default_tables():
        cx, cy = t.center
        assert t.contains(cx, cy)
        assert not t.contains(0.0, 0.0)


def test_round_trip(small_dataset, tmp_path):
    root = save_dataset(small_dataset, tmp_path / "d")
    ds = load_dataset(root)
    assert [a.to_json() for a in ds.arrangements] == [a.to_json() for a in small_dataset.arrangements]
    assert ds.catalog == small_dataset.catalog
    assert ds.synthetic and "SYNTHETIC" in ds.label


def test_loading_never_writes(small_dataset_dir):
    before = {p.name: p.stat().st_mtime_ns for p in small_dataset_dir.iterdir()}
    load_dataset(small_dataset_dir)
    after = {p.name: p.stat().st_mtime_ns for p in small_dataset_dir.iterdir()}
    assert before == after


def _rewrite_line(root, line_no, mutate):
    path = root / "arrangements.jsonl"
    lines = path.read_text().splitlines()
    obj = json.loads(lines[line_no - 1])
    mutate(obj)
    lines[line_no - 1] = json.dumps(obj)
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("mutate, expected", [
    (lambda a: a["placements"][0].update(object=999), "arrangements.jsonl:3: field 'placements[0].object': unknown object id 999"),
    (lambda a: a["placements"][1].update(x=1.5), "arrangements.jsonl:3: field 'placements[1].x': 1.5 is outside [0, 1]"),
    (lambda a: a.update(table=42), "arrangements.jsonl:3: field 'table': table id 42 has no table"),
    (lambda a: a.update(placements=a["placements"][:2]), "arrangements.jsonl:3: field 'placements': 2 objects, fewer than the minimum of 3"),
    (lambda a: a["placements"][0].update(y=math.nan), "arrangements.jsonl:3: field 'placements[0].y': expected a finite number"),
    (lambda a: a.update(trial=0), "arrangements.jsonl:3: field 'trial': duplicate trial 0"),
    (lambda a: a.update(trial="two"), "arrangements.jsonl:3: field 'trial': expected an integer"),
    (lambda a: a["placements"].append(dict(a["placements"][0])), "is placed twice"),
])
def test_bad_arrangements_name_file_line_field(small_dataset_dir, mutate, expected):
    _rewrite_line(small_dataset_dir, 3, mutate)
    with pytest.raises(DegustaError) as err:
        load_dataset(small_dataset_dir)
    assert expected in str(err.value)


def test_bad_json_line_and_catalog_and_tables(small_dataset_dir):
    path = small_dataset_dir / "arrangements.jsonl"
    path.write_text(path.read_text() + "{not json\n")
    with pytest.raises(DegustaError, match=r"arrangements.jsonl:51: invalid JSON"):
        load_dataset(small_dataset_dir)
    cat = json.loads((small_dataset_dir / "catalog.json").read_text())
    cat[4]["id"] = 3
    (small_dataset_dir / "catalog.json").write_text(json.dumps(cat))
    with pytest.raises(DegustaError, match=r"catalog.json: entry 4: field 'id': duplicate object id 3"):
        load_dataset(small_dataset_dir)
    cat[4]["id"], cat[5]["image"] = 4, "missing.png"
    (small_dataset_dir / "catalog.json").write_text(json.dumps(cat))
    with pytest.raises(DegustaError, match=r"entry 5: field 'image': file .*missing.png not found"):
        load_dataset(small_dataset_dir)


def test_missing_folder_and_ratings_range(small_dataset_dir, tmp_path):
    with pytest.raises(DegustaError, match="dataset folder not found"):
        load_dataset(tmp_path / "nope")
    row = {"participant": "p000", "trial": 0, "b_initial": 90, "b_jitter": 120, "rmsd_jitter": 0.1}
    (small_dataset_dir / "ratings.jsonl").write_text(json.dumps(row) + "\n")
    with pytest.raises(DegustaError, match=r"ratings.jsonl:1: field 'b_jitter': rating 120"):
        load_dataset(small_dataset_dir)
