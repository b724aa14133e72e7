"""Bad dataset files, numbers, paths, pictures and tables: one clear error naming file/line/field, never a
traceback or a silently wrong result (issue 12, items 5, 6 and 11).

Each case runs `degusta data validate` in-process (`cli.main`: exit 2 and one line "degusta: error: ...")
or calls the loader/renderer and checks the exact message. Counted in docs/reliability.md.
"""

from __future__ import annotations

import json
import os
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from degusta_learn import cli
from degusta_learn.baselines.transfer import place_on, table_distance
from degusta_learn.errors import DegustaError
from degusta_learn.files import jsonio as fileio
from degusta_learn.render.sprites import open_picture, sprite
from degusta_learn.scene import (
    Catalog,
    CatalogObject,
    Table,
    default_catalog,
    default_tables,
    load_dataset,
    validate_dataset,
)
from degusta_learn.scene.validate import MAX_IMAGE_PIXELS


def validate(root, capsys) -> tuple[int, str]:
    """Run `degusta data validate root`: (exit code, stderr)."""
    rc = cli.main(["data", "validate", str(root)])
    err = capsys.readouterr().err
    return rc, err


def assert_refused(root, capsys, *parts: str) -> str:
    """Exit 2, one line "degusta: error: ...", naming the file and containing every part, no traceback."""
    rc, err = validate(root, capsys)
    assert rc == 2, err
    assert err.startswith("degusta: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for part in parts:
        assert part in err, f"{part!r} not in {err!r}"
    return err


def edit_json(path, mutate):
    data = json.loads(path.read_text())
    mutate(data)
    path.write_text(json.dumps(data))


def edit_line(path, line_no, mutate):
    lines = path.read_text().splitlines()
    obj = json.loads(lines[line_no - 1])
    mutate(obj)
    lines[line_no - 1] = json.dumps(obj)
    path.write_text("\n".join(lines) + "\n")


def replace_line(path, line_no, text: bytes):
    lines = path.read_bytes().splitlines()
    lines[line_no - 1] = text
    path.write_bytes(b"\n".join(lines) + b"\n")


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_header(width: int, height: int) -> bytes:
    """A well-formed PNG file that claims width x height pixels but holds 1 KB of data (a bomb's shape)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(b"\0" * 1000))
            + _chunk(b"IEND", b""))


# --- 1. the readers: bytes, files and numbers ------------------------------------------------------------

READER_CASES = [
    # (file, how to spoil it, expected parts of the message)
    ("arrangements.jsonl", lambda p: replace_line(p, 2, b'{"participant": "p\xff\xfe"}'),
     ["arrangements.jsonl:2: not UTF-8 text"]),
    ("catalog.json", lambda p: p.write_bytes(b"\xef\xbb\xbf[\xc3\x28]"), ["catalog.json:1: not UTF-8 text"]),
    ("meta.json", lambda p: p.write_bytes(b'{"name": "\x80"}'), ["meta.json:1: not UTF-8 text"]),
    ("catalog.json", lambda p: (p.unlink(), p.mkdir()), ["catalog.json: is a folder, expected a file"]),
    ("arrangements.jsonl", lambda p: (p.unlink(), p.mkdir()), ["arrangements.jsonl: is a folder"]),
    ("tables.json", lambda p: (p.unlink(), os.symlink(p.name, p)), ["tables.json: cannot read"]),
    ("arrangements.jsonl", lambda p: (p.unlink(), os.symlink("/dev/null", p)), ["arrangements.jsonl: not a regular file"]),
    ("ratings.jsonl", lambda p: os.symlink("no-such-file", p), ["ratings.jsonl: broken symbolic link"]),
    ("arrangements.jsonl", lambda p: edit_line(p, 3, lambda a: a.update(trial=int("9" * 400))),
     ["arrangements.jsonl:3: field 'trial': integer with 400 digits is out of range"]),
    ("catalog.json", lambda p: p.write_text(p.read_text().replace('"id": 0,', '"id": ' + "1" * 5000 + ",", 1)),
     ["catalog.json:", "entry 0: field 'id': integer with 5000 digits is out of range"]),
    ("arrangements.jsonl", lambda p: replace_line(p, 4, p.read_bytes().splitlines()[3].replace(b'"x": ', b'"x": 1' + b"0" * 400 + b".5, "
                                                                                                 b'"was_x": ', 1)),
     ["arrangements.jsonl:4: field 'placements[0].x': expected a finite number", "(it overflows to infinity)"]),
    ("arrangements.jsonl", lambda p: replace_line(p, 5, p.read_bytes().splitlines()[4].replace(b'"y": ', b'"y": -Infinity, "was_y": ', 1)),
     ["arrangements.jsonl:5: field 'placements[0].y': expected a finite number, got -Infinity"]),
    ("tables.json", lambda p: p.write_text(p.read_text().replace("0.04", "NaN", 1)),
     ["tables.json:", "entry 0: field 'surface[0][0]': expected a finite number, got NaN"]),
    ("ratings.jsonl", lambda p: p.write_text('{"participant": "p000", "trial": 0, "b_initial": Infinity}\n'),
     ["ratings.jsonl:1: field 'b_initial': expected a finite number, got Infinity"]),
    ("arrangements.jsonl", lambda p: replace_line(p, 1, b"[" * 50_000 + b"]" * 50_000),
     ["arrangements.jsonl:1: invalid JSON (nested too deeply)"]),
    ("meta.json", lambda p: p.write_text('{"name": ' + "[" * 100_000 + "]" * 100_000 + "}"),
     ["meta.json: invalid JSON (nested too deeply)"]),
    ("arrangements.jsonl", lambda p: edit_line(p, 1, lambda a: a.update(participant="\ud800")),
     ["arrangements.jsonl:1: invalid JSON (a string holds an invalid \\u escape (a lone surrogate))"]),
    ("arrangements.jsonl", lambda p: replace_line(p, 7, b'{"participant": "p001", "trial": 2,'),
     ["arrangements.jsonl:7: invalid JSON"]),
    ("arrangements.jsonl", lambda p: replace_line(p, 6, p.read_bytes().splitlines()[5].replace(b'"trial": ', b'"trial": 9, "trial": ', 1)),
     ["arrangements.jsonl:6: invalid JSON (duplicate key 'trial' in one object)"]),
    ("catalog.json", lambda p: p.write_text("[]"), ["catalog.json: expected a non-empty JSON list of objects"]),
    ("tables.json", lambda p: p.write_text('{"id": 0}'), ["tables.json: expected a non-empty JSON list of tables"]),
    ("arrangements.jsonl", lambda p: p.write_text("\n\n"), ["arrangements.jsonl: no arrangements"]),
    ("meta.json", lambda p: p.write_text("[1, 2]"), ["meta.json: expected a JSON object, got list"]),
]


@pytest.mark.parametrize("name, spoil, parts", READER_CASES,
                         ids=[f"{i}-{c[0]}" for i, c in enumerate(READER_CASES)])
def test_bad_files_and_numbers_are_one_line_errors(small_dataset_dir, capsys, name, spoil, parts):
    (small_dataset_dir / "ratings.jsonl").unlink(missing_ok=True)
    spoil(small_dataset_dir / name)
    assert_refused(small_dataset_dir, capsys, name, *parts)


def test_huge_files_and_lines_are_refused(small_dataset_dir, capsys, monkeypatch):
    monkeypatch.setattr(fileio, "MAX_JSON_BYTES", 1000)
    assert_refused(small_dataset_dir, capsys, "catalog.json: file too large")
    monkeypatch.setattr(fileio, "MAX_JSON_BYTES", 256 * 2**20)
    monkeypatch.setattr(fileio, "MAX_LINE_BYTES", 100)
    assert_refused(small_dataset_dir, capsys, "arrangements.jsonl:1: line too long")
    monkeypatch.setattr(fileio, "MAX_LINE_BYTES", 64 * 2**20)
    monkeypatch.setattr(fileio, "MAX_JSONL_BYTES", 1000)
    assert_refused(small_dataset_dir, capsys, "arrangements.jsonl: file too large")


def test_the_dataset_folder_itself(tmp_path, capsys):
    os.symlink(tmp_path / "loop", tmp_path / "loop")
    assert_refused(tmp_path / "loop", capsys, "loop: goes through a symbolic-link loop")  # files.paths.check_path
    (tmp_path / "file").write_text("x")
    assert_refused(tmp_path / "file", capsys, "file: not a dataset folder")
    assert_refused(tmp_path / "none", capsys, "none: dataset folder not found")


def test_meta_symlink_loop_is_an_error_not_a_dropped_synthetic_label(small_dataset_dir, capsys):
    assert load_dataset(small_dataset_dir).synthetic
    meta = small_dataset_dir / "meta.json"
    meta.unlink()
    os.symlink("meta.json", meta)
    assert_refused(small_dataset_dir, capsys, "meta.json: cannot read")
    meta.unlink()
    meta.mkdir()
    assert_refused(small_dataset_dir, capsys, "meta.json: is a folder")


# --- 2. dataset validation: types, ranges, vocabulary ----------------------------------------------------

VALIDATION_CASES = [
    ("meta.json", lambda d: d.update(min_objects="3"), "meta.json: field 'min_objects': expected an integer, got '3'"),
    ("meta.json", lambda d: d.update(min_objects=0), "meta.json: field 'min_objects': 0 is out of range"),
    ("meta.json", lambda d: d.update(synthetic="yes"), "meta.json: field 'synthetic': expected true or false, got 'yes'"),
    ("meta.json", lambda d: d.update(name=5), "meta.json: field 'name': expected a non-empty string, got 5"),
    ("meta.json", lambda d: d.update(seed="0"), "meta.json: field 'seed': expected an integer"),
    ("meta.json", lambda d: d.update(vocabulary=["teal"]), "meta.json: field 'vocabulary': expected an object"),
    ("meta.json", lambda d: d.update(latent_styles="../../styles.json"), "field 'latent_styles': '../../styles.json' leaves the dataset folder"),
    ("catalog.json", lambda d: d[0].update(id=100_000_000_000), "catalog.json: entry 0: field 'id': 100000000000 is out of range"),
    ("catalog.json", lambda d: d[1].update(id=-1), "catalog.json: entry 1: field 'id': -1 is out of range"),
    ("catalog.json", lambda d: d[2].update(id="2"), "catalog.json: entry 2: field 'id': expected an integer, got '2'"),
    ("catalog.json", lambda d: d[3].update(id=3.0), "catalog.json: entry 3: field 'id': expected an integer, got 3.0"),
    ("catalog.json", lambda d: d[4].update({"class": "spork"}), "catalog.json: entry 4: field 'class': 'spork' is not in the vocabulary"),
    ("catalog.json", lambda d: d[5].update(color1="teal"), "catalog.json: entry 5: field 'color1': 'teal' is not in the vocabulary"),
    ("catalog.json", lambda d: d[6].update(color2="Red"), "catalog.json: entry 6: field 'color2': 'Red' is not in the vocabulary"),
    ("catalog.json", lambda d: d[7].update(material1="unobtainium"), "entry 7: field 'material1': 'unobtainium' is not in the vocabulary"),
    ("catalog.json", lambda d: d[8].update(material2=["metal"]), "entry 8: field 'material2': expected a non-empty string"),
    ("catalog.json", lambda d: d[9].update(color1=7), "entry 9: field 'color1': expected a non-empty string, got 7"),
    ("catalog.json", lambda d: d[10].update(shape="x" * 5000), "entry 10: field 'shape': string of 5000 characters is too long"),
    ("tables.json", lambda d: d[0].update(width="1024"), "tables.json: entry 0: field 'width': expected an integer, got '1024'"),
    ("tables.json", lambda d: d[0].update(height=10**12), "tables.json: entry 0: field 'height': 1000000000000 is out of range"),
    ("tables.json", lambda d: d[1].update(id=10**11), "tables.json: entry 1: field 'id': 100000000000 is out of range"),
    ("tables.json", lambda d: d[1].update(name={"a": 1}), "tables.json: entry 1: field 'name': expected a string, got dict"),
    ("tables.json", lambda d: d[2].update(surface="square"), "tables.json: entry 2: field 'surface': expected a list"),
    ("tables.json", lambda d: d[2].update(surface=[[0.1, 0.1], [0.9, "0.1"], [0.9, 0.9]]), "entry 2: field 'surface': point 1 must be [x, y]"),
    ("arrangements.jsonl", lambda a: a.update(trial=-1), "arrangements.jsonl:3: field 'trial': -1 is out of range"),
    ("arrangements.jsonl", lambda a: a.update(trial=10**15), "arrangements.jsonl:3: field 'trial': 1000000000000000 is out of range"),
    ("arrangements.jsonl", lambda a: a.update(table="0"), "arrangements.jsonl:3: field 'table': expected an integer, got '0'"),
    ("arrangements.jsonl", lambda a: a.update(table=10**18), "arrangements.jsonl:3: field 'table': table id 1000000000000000000 has no table"),
    ("arrangements.jsonl", lambda a: a.update(participant=["p"]), "arrangements.jsonl:3: field 'participant': expected a string id"),
    ("arrangements.jsonl", lambda a: a.update(participant="p" * 5000), "arrangements.jsonl:3: field 'participant': string of 5000"),
    ("arrangements.jsonl", lambda a: a.update(placements={"0": 1}), "arrangements.jsonl:3: field 'placements': expected a list, got dict"),
    ("arrangements.jsonl", lambda a: a["placements"][0].update(x="0.5"), "arrangements.jsonl:3: field 'placements[0].x': expected a number, got '0.5'"),
    ("arrangements.jsonl", lambda a: a["placements"][1].update(y=True), "arrangements.jsonl:3: field 'placements[1].y': expected a number, got True"),
    ("arrangements.jsonl", lambda a: a["placements"][0].update(rotation="north"), "field 'placements[0].rotation': expected a number, got 'north'"),
    ("arrangements.jsonl", lambda a: a["placements"][0].update(x=10**19), "field 'placements[0].x': 1e+19 is outside [0, 1]"),
    ("arrangements.jsonl", lambda a: a["placements"][0].update(object=10**11), "field 'placements[0].object': unknown object id 100000000000"),
    ("arrangements.jsonl", lambda a: a["placements"][0].update(object="17"), "field 'placements[0].object': expected an integer, got '17'"),
    ("arrangements.jsonl", lambda a: a["placements"].__setitem__(0, [0.5, 0.5]), "field 'placements[0]': expected an object"),
    ("ratings.jsonl", lambda r: r.update(b_initial="90"), "ratings.jsonl:3: field 'b_initial': expected a number, got '90'"),
    ("ratings.jsonl", lambda r: r.update(rmsd_jitter=-0.1), "ratings.jsonl:3: field 'rmsd_jitter': RMSD -0.1 is negative"),
    ("ratings.jsonl", lambda r: r.update(trial="0"), "ratings.jsonl:3: field 'trial': expected an integer"),
    # a rating of no arrangement, or one rated twice, were accepted and scored by evaluate
    ("ratings.jsonl", lambda r: r.update(participant="zzz"), "ratings.jsonl:3: field 'trial': participant 'zzz' has no trial 0"),
    ("ratings.jsonl", lambda r: r.update(trial=99), "ratings.jsonl:3: field 'trial': participant 'p002' has no trial 99"),
    ("ratings.jsonl", lambda r: r.update(participant="p001"), "ratings.jsonl:3: field 'trial': participant 'p001' trial 0 is rated twice"),
]


def _add_ratings(root):
    rows = [{"participant": f"p{i:03d}", "trial": 0, "b_initial": 90, "b_jitter": 70, "rmsd_jitter": 0.05}
            for i in range(5)]
    (root / "ratings.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))


@pytest.mark.parametrize("name, mutate, expected", VALIDATION_CASES,
                         ids=[f"{i}-{c[0]}" for i, c in enumerate(VALIDATION_CASES)])
def test_wrong_types_ranges_and_words_name_file_record_field(small_dataset_dir, capsys, name, mutate, expected):
    path = small_dataset_dir / name
    if name == "ratings.jsonl":
        _add_ratings(small_dataset_dir)
    if name.endswith(".jsonl"):
        edit_line(path, 3, mutate)
    else:
        edit_json(path, mutate)
    assert_refused(small_dataset_dir, capsys, expected)


def test_a_dataset_may_widen_its_vocabulary_in_meta(small_dataset_dir, capsys):
    edit_json(small_dataset_dir / "catalog.json", lambda d: d[5].update(color1="teal", material2="bamboo"))
    edit_json(small_dataset_dir / "meta.json", lambda d: d.update(vocabulary={"colors": ["teal"], "materials": ["bamboo"]}))
    rc, err = validate(small_dataset_dir, capsys)
    assert rc == 0, err
    assert load_dataset(small_dataset_dir).catalog[5].color1 == "teal"


def test_a_huge_object_id_never_sizes_an_allocation():
    objects = (CatalogObject(10**11, "cup", "red", "red", "glass", "glass"),
               CatalogObject(3, "plate", "blue", "blue", "ceramic", "ceramic"))
    cat = Catalog(objects)  # used to allocate 8 * 1e11 bytes for an id -> row table
    assert cat.features([10**11, 3]).shape == (2, 7)
    assert (cat.features([3]) != cat.features([10**11])).any()
    with pytest.raises(KeyError, match="object id 4 is not in the catalog"):
        cat.features([4])


# --- 3. paths that leave the dataset, and pictures -------------------------------------------------------

def _set_image(root, image, table=False):
    edit_json(root / ("tables.json" if table else "catalog.json"), lambda d: d[0].update(image=image))


def test_image_paths_must_stay_inside_the_dataset(small_dataset_dir, tmp_path, capsys):
    outside = tmp_path / "outside.png"
    Image.new("RGBA", (8, 8), (255, 0, 0, 255)).save(outside)
    Image.new("RGBA", (8, 8), (0, 0, 255, 255)).save(small_dataset_dir / "ok.png")
    (small_dataset_dir / "pics").mkdir()
    os.symlink(outside, small_dataset_dir / "pics" / "link.png")
    os.symlink("loop.png", small_dataset_dir / "loop.png")
    cases = [
        ("../outside.png", "catalog.json: entry 0: field 'image': '../outside.png' leaves the dataset folder"),
        ("../../x.png", "field 'image': '../../x.png' leaves the dataset folder"),
        ("pics/../../outside.png", "leaves the dataset folder"),
        (str(outside), "is an absolute path; paths must be relative to the dataset folder"),
        ("C:\\pictures\\x.png", "is an absolute path"),
        ("..\\outside.png", "leaves the dataset folder"),
        ("pics/link.png", "pics/link.png is a symbolic link to " + str(outside.resolve()) + ", outside the dataset folder"),
        ("loop.png", "field 'image': cannot read"),
        ("missing.png", "field 'image': file " + str(small_dataset_dir / "missing.png") + " not found"),
        ("pics", "pics is not a regular file"),
        ("", "field 'image': expected a relative path string, got ''"),
        (17, "field 'image': expected a relative path string, got 17"),
    ]
    for image, expected in cases:
        _set_image(small_dataset_dir, image)
        assert_refused(small_dataset_dir, capsys, expected)
    _set_image(small_dataset_dir, "ok.png")
    _set_image(small_dataset_dir, "../outside.png", table=True)
    assert_refused(small_dataset_dir, capsys, "tables.json: entry 0: field 'image': '../outside.png' leaves the dataset folder")
    _set_image(small_dataset_dir, "ok.png", table=True)
    rc, err = validate(small_dataset_dir, capsys)
    assert rc == 0, err


def test_decompression_bombs_and_corrupt_pictures(small_dataset_dir, capsys):
    root = small_dataset_dir
    (root / "bomb.png").write_bytes(png_header(100_000, 100_000))
    (root / "empty.png").write_bytes(b"")
    (root / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage")
    for image, expected in [("bomb.png", "bomb.png is 100000 x 100000 pixels, over the limit"),
                            ("empty.png", "empty.png is an empty file, not an image"),
                            ("broken.png", "broken.png is a broken PNG file")]:
        _set_image(root, image)
        assert_refused(root, capsys, "catalog.json: entry 0: field 'image': ", expected)
    # The renderer's own loader (catalogs built in code skip validation): every failure names the file.
    side = int(MAX_IMAGE_PIXELS ** 0.5) + 1  # over our limit, under Pillow's
    (root / "big.png").write_bytes(png_header(side, side))
    good = root / "good.png"
    Image.new("RGBA", (64, 64), (0, 200, 0, 255)).save(good)
    (root / "truncated.png").write_bytes(good.read_bytes()[:60])
    (root / "text.png").write_text("not a picture")
    (root / "eps.png").write_bytes(b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 10 10\n")
    for name, expected in [("bomb.png", "too large to decode"), ("big.png", f"{side} x {side} pixels, over the limit"),
                           ("truncated.png", "not a readable image"), ("text.png", "not a readable image"),
                           ("eps.png", "not a readable image"), ("empty.png", "not a readable image"),
                           ("nothing.png", "not found")]:
        with pytest.raises(DegustaError, match=rf"{name}: image of object 0 .*" if name != "nothing.png" else "nothing.png"):
            try:
                open_picture(root / name, "image of object 0")
            except DegustaError as e:
                assert expected in str(e), str(e)
                raise
    assert open_picture(good, "image of object 0").size == (64, 64)


def test_the_renderer_refuses_pictures_outside_its_root(tmp_path):
    Image.new("RGBA", (8, 8), (255, 0, 0, 255)).save(tmp_path / "outside.png")
    (tmp_path / "data").mkdir()
    obj = CatalogObject(0, "cup", "red", "red", "glass", "glass", image="../outside.png")
    with pytest.raises(DegustaError, match=r"image of object 0: '\.\./outside\.png' leaves the dataset folder"):
        sprite(obj, 448, root=tmp_path / "data")
    ok = CatalogObject(0, "cup", "red", "red", "glass", "glass", image="../data/../outside.png")
    with pytest.raises(DegustaError, match="leaves the dataset folder"):
        sprite(ok, 448, root=tmp_path / "data")


# --- 4. degenerate tables --------------------------------------------------------------------------------

@pytest.mark.parametrize("surface, expected", [
    ([[0.5, 0.5], [0.5, 0.5], [0.5, 0.5]], "degenerate polygon: only 1 distinct points"),
    ([[0.1, 0.1], [0.9, 0.9], [0.1, 0.1], [0.9, 0.9]], "degenerate polygon: only 2 distinct points"),
    ([[0.1, 0.1], [0.5, 0.5], [0.9, 0.9]], "degenerate polygon: area "),  # collinear (area ~1e-17)
    ([[0.1, 0.5], [0.9, 0.5], [0.5, 0.5], [0.2, 0.5]], "degenerate polygon: area 0 of the image"),
    ([[0.1, 0.1], [0.15, 0.1], [0.15, 0.15], [0.1, 0.15]], "degenerate polygon: area 0.0025"),
    ([[0.1, 0.1], [0.9, 0.9], [0.9, 0.1], [0.1, 0.9]], "degenerate polygon: area "),  # a bow tie
    ([[0.1, 0.1], [0.9, 0.1]], "expected a polygon of 3 to 10000 [x, y] points, got 2"),
])
def test_degenerate_tables_are_rejected(small_dataset_dir, capsys, surface, expected):
    edit_json(small_dataset_dir / "tables.json", lambda d: d[3].update(surface=surface))
    assert_refused(small_dataset_dir, capsys, "tables.json: entry 3: field 'surface': ", expected)


def test_transfer_is_robust_on_degenerate_tables():
    cat, good = default_catalog(), default_tables()[0]
    flat = Table(9, 1024, 1024, ((0.5, 0.5), (0.5, 0.5), (0.5, 0.5)))
    line = Table(8, 1024, 1024, ((0.1, 0.5), (0.9, 0.5), (0.5, 0.5)))
    for a, b in [(good, flat), (flat, good), (flat, flat), (line, good), (good, line)]:
        assert np.isfinite(table_distance(a, b))
    uv = np.array([[0.2, 0.3], [0.8, 0.7], [np.nan, 0.5]])
    for table in (flat, line, good):
        placements = place_on(table, cat, [0, 75, 30], uv, np.array([0.0, 90.0, np.inf]))
        xy = np.array([[p.x, p.y] for p in placements])
        assert np.isfinite(xy).all() and (xy >= 0).all() and (xy <= 1).all()
        assert all(0 <= p.rotation < 360 for p in placements)


# --- 5. the generator keeps the validator's rules ----------------------------------------------------------

def test_every_generated_style_can_set_the_minimum_number_of_objects():
    """The root of `data generate naturalistic --seed 3` writing a 2-object arrangement: a freeform style
    whose third object found no room. Styles are cheap, so check 30 seeds x 199 participants."""
    from degusta_learn.synth.realize import MIN_OBJECTS
    from degusta_learn.synth.templates import sample_style

    catalog = default_catalog()
    for seed in range(30):
        for i in range(199):
            rng = np.random.default_rng(np.random.SeedSequence([seed, i]).spawn(3)[0])
            style = sample_style(rng, f"p{i:03d}", catalog)
            assert len(style.slots) >= MIN_OBJECTS, (seed, i, style.template)
            assert len({s.object for s in style.slots}) == len(style.slots), (seed, i)


def test_generated_datasets_validate_for_many_seeds():
    from degusta_learn.synth.naturalistic import naturalistic_with_styles
    from degusta_learn.synth.simulated import simulated_with_styles

    for seed in range(12):  # participant i depends only on (seed, i): 40 per seed covers 480 of them
        ds, _ = naturalistic_with_styles(seed, n_participants=40)
        validate_dataset(ds)
        assert min(len(a.placements) for a in ds.arrangements) >= 3
    ds, _ = naturalistic_with_styles(3, n_participants=140)  # p138: the participant of the bug report
    assert min(len(a.placements) for a in ds.arrangements if a.participant == "p138") >= 3
    validate_dataset(simulated_with_styles(5)[0])


def test_generate_seed_3_then_validate_on_disk(tmp_path, capsys):
    out = tmp_path / "nat3"
    assert cli.main(["data", "generate", "naturalistic", "--seed", "3", "--out", str(out)]) == 0
    capsys.readouterr()
    rc, err = validate(out, capsys)
    assert rc == 0, err
    ds = load_dataset(out)
    assert ds.synthetic and "SYNTHETIC" in ds.label
    assert min(len(a.placements) for a in ds.arrangements) >= 3


# --- episode files (read beside a dataset by predict and evaluate) ----------------------------------------

@pytest.mark.parametrize("line, expected", [
    ('{"id": "e", "participant": "p000", "context": [1, 2], "target": "0"}', "episodes.jsonl:1: field 'target': expected an integer, got '0'"),
    ('{"id": "e", "participant": "p000", "context": [1, 2], "target": 1e400}', "episodes.jsonl:1: field 'target': expected a finite number"),
    ('{"id": "e", "participant": "p000", "context": [1, 2], "target": ' + "7" * 400 + "}", "field 'target': integer with 400 digits"),
    ('{"id": "e", "participant": "p000", "context": [1, 1], "target": 0}', "episodes.jsonl:1: field 'context': a trial appears twice"),
    ('{"id": "e", "participant": "p000", "context": [1, -2], "target": 0}', "episodes.jsonl:1: field 'context': expected a list of trial numbers"),
    ('{"id": "e", "participant": "p000", "context": [1, 2], "target": 10000000000}', "field 'target': 10000000000 is out of range"),
])
def test_bad_episode_files(small_dataset_dir, line, expected):
    from degusta_learn.scene import read_episodes

    path = small_dataset_dir / "episodes.jsonl"
    path.write_text(line + "\n")
    with pytest.raises(DegustaError) as err:
        read_episodes(path, load_dataset(small_dataset_dir))
    assert expected in str(err.value) and "episodes.jsonl:1" in str(err.value)
