"""Untrusted text never becomes live markup, a formula or a crash (docs/reliability.md, "Untrusted text").

Hostile strings go into every field a user, a dataset or a server controls: the compare config's title, the
dataset's name (meta.json, or its folder's name), participant and episode ids, the folder names `evaluate` labels
clashing methods with, the error messages of failed methods (a server's reply), plot labels and object words.
The real `degusta evaluate` and `degusta compare` then run, and:

- report.html holds only the tags of the report (no <script>, no on* attribute, no javascript: URL) and shows each
  string as the text it is;
- report.md has exactly the headings, table rows and table cells of the same report built from plain strings;
- per_episode.csv parses back with `csv`, no cell starts with = + - @ TAB CR unless neutralised (a leading ') or
  a number (-0.5 stays -0.5);
- control characters (newline, NUL, U+2028, bidi overrides ...) in any text field of a dataset file, an episodes
  file or a predictions file are refused with one line naming the file and the field;
- the renderers and plots draw any text that passes validation (and any label) without a traceback.
"""

from __future__ import annotations

import csv
import functools
import html.parser
import json
import re
import unicodedata
from pathlib import Path

import pytest

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.evaluate import compare as compare_module
from degusta_learn.evaluate.compare import CompareConfig, MethodEntry, compare
from degusta_learn.scene import (
    Arrangement,
    Dataset,
    Placement,
    Prediction,
    Rating,
    default_catalog,
    default_tables,
    load_dataset,
    make_episodes,
    read_episodes,
    read_predictions,
    save_dataset,
    write_episodes,
    write_predictions,
)

HOSTILE = [
    "<script>alert(1)</script>",
    "<img src=x onerror=alert(1)>",
    '"><svg onload=alert(1)>',
    "<a href=\"javascript:alert(1)\">x</a>",
    "[click](javascript:alert(1))",
    "![i](javascript:alert(1))",
    "<javascript:alert(1)>",
    "[r]: javascript:alert(1)",
    "<!-- comment",
    "a\n# Fake section",
    "a\n\n| x | y |\n|---|---|\n| 1 | 2 |",
    "a\r\n> quote",
    "| pipe | in | cell |",
    "back`tick`s and ``double``",
    "`unclosed",
    "&lt;b&gt;already escaped&lt;/b&gt; &amp; &#60;",
    "*star* _under_ **bold** __dunder__ ~~strike~~",
    "back\\slash\\",
    "# hash at start",
    "- dash at start",
    "1. numbered",
    "=HYPERLINK(\"http://evil\",\"x\")",
    "+1+2",
    "-cmd|' /C calc'!A0",
    "@SUM(1+1)",
    "\t=1+1",
    "\r=1+1",
    " =1+1",
    "=1+1",
    "line\u2028separator\u2029para",
    "next\u0085line",
    "nul\x00byte",
    "esc\x1b[31mred",
    "bidi\u202eevil\u202c",
    "zero\u200bwidth\ufeffbom",
    "$\\frac{$ math $x^$",
    "_leading underscore",
    "x" * 3000,
    "emoji 🍽️ 👩‍🍳 RTL עברית العربية e\u0301\u0301 漢字",
]
CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029\u200b-\u200f\u202a-\u202e\u2060-\u2064\u2066-\u2069\ufeff]")
PRINTABLE = [h for h in HOSTILE if not CONTROL.search(h)]
FORMULA_START = tuple("=+-@\t\r")
NUMBER = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?")
FOLDER_SAFE = [h for h in HOSTILE if "/" not in h and "\x00" not in h and len(h) < 200]


# -- a tiny dataset whose participant ids are the strings under test -----------------------------------------------

def tiny_dataset(participants: list[str], name: str | None = "tiny") -> Dataset:
    catalog, tables = default_catalog(), {t.id: t for t in default_tables()}
    arrangements = []
    for i, p in enumerate(participants):
        objs = [(i * 7 + k * 11) % len(catalog) for k in range(3)]
        for t in range(3):
            arrangements.append(Arrangement(p, t, t % len(tables), tuple(
                Placement(catalog.ids[o], 0.3 + 0.1 * k + 0.01 * t, 0.4 + 0.05 * k, 0.0) for k, o in enumerate(objs))))
    meta = {"synthetic": True} | ({"name": name} if name is not None else {})
    return Dataset(catalog, tables, arrangements, meta=meta)


def perfect(ds: Dataset, episodes, method: str, shift: float = 0.0) -> list[Prediction]:
    out = []
    for e in episodes:
        gt = ds.arrangement(e.participant, e.target)
        out.append(Prediction(e.id, e.participant, e.target, method,
                              [Placement(p.object, min(p.x + shift, 0.9), p.y, p.rotation) for p in gt.placements]))
    return out


# -- what a report may contain ---------------------------------------------------------------------------------------

ALLOWED_TAGS = {"html", "head", "meta", "title", "style", "body", "h1", "h2", "h3", "h4", "p", "table", "thead",
                "tbody", "tr", "th", "td", "img", "a", "code", "strong", "em", "blockquote", "ul", "ol", "li", "hr",
                "br", "pre"}


class Page(html.parser.HTMLParser):
    """Every start tag with its attributes, and the text by innermost element (entities decoded)."""

    def __init__(self, text: str):
        super().__init__(convert_charrefs=True)
        self.tags: list[tuple[str, list]] = []
        self.stack: list[str] = []
        self.texts: list[tuple[str, str]] = []
        self.feed(text)
        self.close()

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, attrs))
        if tag not in ("img", "meta", "br", "hr"):
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if tag in self.stack:
            while self.stack.pop() != tag:
                pass

    def handle_data(self, data):
        self.texts.append((self.stack[-1] if self.stack else "", data))

    def handle_comment(self, data):
        self.tags.append(("<!--", []))

    def handle_pi(self, data):
        self.tags.append(("<?", []))

    def unknown_decl(self, data):
        self.tags.append(("<!", []))

    @property
    def text(self) -> str:
        return "".join(t for _, t in self.texts)

    def shape(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for tag, _ in self.tags:
            counts[tag] = counts.get(tag, 0) + 1
        return counts


def assert_inert_html(text: str) -> Page:
    page = Page(text)
    for tag, attrs in page.tags:
        assert tag in ALLOWED_TAGS, f"live markup from the input: <{tag}>"
        for key, value in attrs:
            assert not key.startswith("on"), f"event handler attribute {key}={value!r} on <{tag}>"
            assert key in {"charset", "href", "src", "alt", "title", "align", "style"} or tag == "meta", (tag, key)
            if key in ("href", "src"):
                squeezed = re.sub(r"[\x00-\x20]", "", value or "").lower()
                scheme = re.match(r"([a-z][a-z0-9+.-]*):", squeezed)
                assert scheme is None or scheme.group(1) in ("http", "https"), f"{key}={value!r}"
                assert not squeezed.startswith(("//", "\\\\")), f"{key}={value!r}"
    assert [tag for tag, _ in page.tags].count("style") == 1 and [tag for tag, _ in page.tags].count("script") == 0
    return page


def md_shape(text: str) -> list:
    """The report.md's structure: headings by level, table rows by their number of (unescaped) cells,
    blockquotes, list items, images; plain text lines counted as one kind."""
    shape = []
    for line in text.splitlines():
        if re.match(r"#{1,6} ", line):
            shape.append(("h", len(line.split(" ", 1)[0])))
        elif line.startswith("|"):
            shape.append(("row", len(re.findall(r"(?<!\\)\|", line))))
        elif line.startswith(">"):
            shape.append(("quote",))
        elif re.match(r"\s*([-*+]|\d+[.)]) ", line):
            shape.append(("li",))
        elif line.startswith("!["):
            shape.append(("img",))
        elif line.strip():
            shape.append(("text",))
        else:
            shape.append(("blank",))
    return shape


def assert_safe_csv(path: Path, participants: set[str] | None = None) -> list[dict]:
    with path.open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert rows
    for row in rows:
        for key, cell in row.items():
            assert cell is not None and key is not None, "a row with too many or too few cells"
            if cell.startswith(FORMULA_START) or cell.lstrip(" ").startswith(FORMULA_START):
                assert NUMBER.fullmatch(cell), f"{key}: {cell!r} would run as a formula"
        for key in ("target", "n_gt", "n_pred", "n_matched", "object_accuracy", "set_rmsd"):
            float(row[key])  # numbers stay numbers
    if participants is not None:
        shown = {r["participant"][1:] if r["participant"].startswith("'") and r["participant"][1:] in participants
                 else r["participant"] for r in rows}
        assert shown == participants
    return rows


def visible(text: str) -> str:
    """How a string may show in a one-line report: whitespace runs as one space (what HTML shows anyway)."""
    return " ".join(text.split())


# -- evaluate and compare on hostile participant ids, folder names, failure messages -----------------------------------

def _world(tmp_path: Path, participants: list[str], name: str | None = "tiny", folder: str = "ds"):
    ds = tiny_dataset(participants, name)
    root = save_dataset(ds, tmp_path / folder)
    ds = load_dataset(root)
    eps = make_episodes(ds, 2, "all")
    write_episodes(tmp_path / "eps.jsonl", eps)
    write_predictions(tmp_path / "a.jsonl", perfect(ds, eps, "a"))
    write_predictions(tmp_path / "b.jsonl", perfect(ds, eps, "b", shift=0.02))
    return ds, root, eps


def _no_pictures(monkeypatch) -> None:
    """Skip matplotlib and the qualitative images (their labels are tested on their own, below): seconds saved."""
    from degusta_learn.evaluate import compare_report, qualitative

    def stub(*args, **kwargs):
        path = next(a for a in args if isinstance(a, Path))
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")
        return path

    for name in ("plot_metric_bars", "plot_acceptability", "plot_context"):
        monkeypatch.setattr(compare_report, name, stub)
    monkeypatch.setattr(qualitative, "render_side_by_side", stub)


def _compare(tmp_path: Path, root: Path, title: str, failures: dict[str, str], monkeypatch, qualitative: int = 1):
    real = compare_module._collect

    def collect(entry, *args, **kwargs):
        if entry.name in failures:
            raise DegustaError(failures[entry.name])  # e.g. a server's reply, quoted in the method's error
        return real(entry, *args, **kwargs)

    monkeypatch.setattr(compare_module, "_collect", collect)
    methods = [MethodEntry("a", predictions=str(tmp_path / "a.jsonl")),
               MethodEntry("b", predictions=str(tmp_path / "b.jsonl"))]
    methods += [MethodEntry(m, predictions=str(tmp_path / "a.jsonl")) for m in failures]
    cfg = CompareConfig(dataset=str(root), out=str(tmp_path / "cmp"), episodes=str(tmp_path / "eps.jsonl"),
                        methods=methods, n_bootstrap=10, qualitative=qualitative, render_size=64, title=title)
    return compare(cfg, log=lambda m: None).out


def _evaluate(tmp_path: Path, root: Path, ds: Dataset, eps, folders: list[str], capsys) -> Path:
    files = []
    for i, folder in enumerate(folders):
        path = tmp_path / "runs" / folder / "predictions.jsonl"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_predictions(path, perfect(ds, eps[::9], "m", shift=0.001 * i))  # a few episodes: a fast test
        files.append(str(path))
    out = tmp_path / "ev"
    code = main(["evaluate", "--dataset", str(root), "--predictions", *files, "--out", str(out), "--bootstrap", "10"])
    assert code == 0, capsys.readouterr().err
    return out


def _run_all(tmp_path: Path, participants, folders, messages, monkeypatch, capsys, title="Comparison report"):
    ds, root, eps = _world(tmp_path, participants)
    failures = {f"broken{i}": f"server said: {m}" for i, m in enumerate(messages)}
    cmp = _compare(tmp_path, root, title, failures, monkeypatch)
    ev = _evaluate(tmp_path, root, ds, eps, folders, capsys)
    return cmp, ev


def test_hostile_ids_folders_and_server_messages_stay_text(tmp_path, monkeypatch, capsys):
    """One comparison and one evaluation holding every hostile string at once, against the same run on plain
    strings: same report structure, inert HTML that shows the strings, a CSV without live formulas."""
    n_folders = len(FOLDER_SAFE)
    participants = [h for h in PRINTABLE if len(h) <= 1000]  # longer ids are refused (MAX_STR)
    with monkeypatch.context() as m:  # the plain run only gives the structure: no pictures needed
        _no_pictures(m)
        plain = _run_all(tmp_path / "plain", [f"p{i:02d}" for i in range(len(participants))],
                         [f"run{i:02d}" for i in range(n_folders)], [f"message {i}" for i in range(len(HOSTILE))],
                         monkeypatch, capsys)
    hostile = _run_all(tmp_path / "hostile", participants, FOLDER_SAFE, HOSTILE, monkeypatch, capsys)
    for (p_cmp, p_ev), (h_cmp, h_ev) in [(plain, hostile)]:
        assert md_shape((h_cmp / "report.md").read_text(encoding="utf-8")) == \
            md_shape((p_cmp / "report.md").read_text(encoding="utf-8"))
        assert md_shape((h_ev / "report.md").read_text(encoding="utf-8")) == \
            md_shape((p_ev / "report.md").read_text(encoding="utf-8"))
        plain_page = assert_inert_html((p_cmp / "report.html").read_text(encoding="utf-8"))
        page = assert_inert_html((h_cmp / "report.html").read_text(encoding="utf-8"))
        assert page.shape() == plain_page.shape()
        shown = visible(page.text)
        for message in HOSTILE:
            if not CONTROL.search(message) and len(message) < 1000:
                assert visible(f"server said: {message}") in shown, message
        assert_safe_csv(h_cmp / "per_episode.csv", set(participants))
        assert_safe_csv(h_ev / "per_episode.csv")  # a few episodes only: some of the participants
        # every folder name labels its method in the evaluation report, as text
        report = (h_ev / "report.md").read_text(encoding="utf-8")
        assert report.count("\n| ") >= len(FOLDER_SAFE)
    metrics = json.loads((hostile[0] / "metrics.json").read_text(encoding="utf-8"))
    assert metrics["failed_methods"]["broken0"] == f"server said: {HOSTILE[0]}"  # the JSON keeps the exact text


@pytest.mark.parametrize("text", HOSTILE, ids=range(len(HOSTILE)))
def test_hostile_title_and_dataset_name(text, tmp_path, monkeypatch, capsys):
    """The compare config's title and the dataset's name (meta.json where printable, else the folder's name)."""
    in_meta = not CONTROL.search(text) and len(text) <= 1000
    folder = "ds" if in_meta or "/" in text or "\x00" in text or len(text) > 200 else text
    ds, root, eps = _world(tmp_path, ["p0", "p1", "p2"], name=text if in_meta else None, folder=folder)
    _no_pictures(monkeypatch)
    out = _compare(tmp_path, root, text, {}, monkeypatch, qualitative=0)
    report = (out / "report.md").read_text(encoding="utf-8")
    page = assert_inert_html((out / "report.html").read_text(encoding="utf-8"))
    assert sum(1 for line in report.splitlines() if line.startswith("#")) == \
        sum(1 for line in report.splitlines() if line.startswith("## ")) + 1
    assert report.splitlines()[0].startswith("# ")
    assert page.shape().get("h1") == 1 and page.shape().get("title") == 1
    title_text = [t for tag, t in page.texts if tag == "title"]
    h1 = [t for tag, t in page.texts if tag == "h1"]
    if not CONTROL.search(text) and len(text) < 300:
        assert visible("".join(h1)) == visible(text) and visible("".join(title_text)) == visible(text)
        if in_meta:
            assert visible(f"Dataset: {text} (SYNTHETIC data).") in visible(page.text)
    ev = tmp_path / "ev"
    assert main(["evaluate", "--dataset", str(root), "--predictions", str(tmp_path / "a.jsonl"), "--out", str(ev),
                 "--bootstrap", "10"]) == 0, capsys.readouterr().err
    ev_report = (ev / "report.md").read_text(encoding="utf-8")
    assert md_shape(ev_report)[:3] == [("h", 1), ("blank",), ("text",)]
    assert sum(1 for line in ev_report.splitlines() if re.match("#+ ", line)) == 4  # title + its three sections


def test_method_names_stay_safe_file_names(tmp_path):
    """compare and evaluate take only safe method names (letters, digits, . _ -): nothing to escape there."""
    for text in HOSTILE:
        with pytest.raises(DegustaError, match="safe name"):
            MethodEntry(text, predictions="x.jsonl")
    ds, root, eps = _world(tmp_path, ["p0", "p1", "p2"])
    for i, text in enumerate(HOSTILE[:8]):
        write_predictions(tmp_path / f"bad{i}.jsonl", perfect(ds, eps, text))
        with pytest.raises(DegustaError, match="field 'method'"):
            from degusta_learn.evaluate import evaluate_files
            evaluate_files(root, [tmp_path / f"bad{i}.jsonl"], tmp_path / "ev")


# -- control characters in dataset text are refused, one line naming file and field --------------------------------

BAD_CHARS = ["\n", "\r", "\t", "\x00", "\x1b", "\x7f", "\x85", "\u2028", "\u2029", "\u200b", "\u202e", "\u2066",
             "\ufeff", "\ud800"]


def _tiny_root(tmp_path: Path) -> Path:
    ds = tiny_dataset(["p0", "p1", "p2"])
    ds.ratings = [Rating("p0", 0, 80.0, 60.0, 0.05)]
    root = save_dataset(ds, tmp_path / "ds")
    (root / "pic.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00\x00\x00\rIHDR\x00\x00\x00\x01\x00\x00\x00\x01")
    return root


def _edit_json(path: Path, edit, *args) -> None:
    """Rewrite a JSON file after `edit(data, *args)`."""
    data = json.loads(path.read_text(encoding="utf-8"))
    edit(data, *args)
    path.write_text(json.dumps(data), encoding="utf-8")


def _edit_jsonl(path: Path, edit, *args) -> None:
    """Rewrite a JSONL file after `edit(first_record, *args)`."""
    lines = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
    edit(lines[0], *args)
    path.write_text("".join(json.dumps(x) + "\n" for x in lines), encoding="utf-8")


def _set(record: dict, key: str, value, prefix: str = "") -> None:
    record[key] = prefix + value if prefix else value


def _set_first(key: str, records: list, value) -> None:
    records[0][key] = value


def _meta(key, word=None):
    def edit(meta, bad):
        if key.startswith("vocabulary."):
            meta["vocabulary"] = {key.split(".")[1]: [bad]}
        else:
            meta[key] = bad
    return edit


DATASET_FIELDS = {  # (file, field): how to put the bad text there
    ("meta.json", "name"): _meta("name"),
    ("meta.json", "generator"): _meta("generator"),
    ("meta.json", "description"): _meta("description"),
    ("meta.json", "vocabulary.classes"): _meta("vocabulary.classes"),
    ("meta.json", "vocabulary.colors"): _meta("vocabulary.colors"),
    ("meta.json", "vocabulary.materials"): _meta("vocabulary.materials"),
    ("meta.json", "latent_styles"): _meta("latent_styles"),
    ("meta.json", "episodes"): _meta("episodes"),
    **{("catalog.json", key): functools.partial(_set_first, key)
       for key in ("class", "color1", "color2", "material1", "material2", "shape", "pattern", "texture", "image")},
    ("tables.json", "name"): functools.partial(_set_first, "name"),
    ("tables.json", "image"): functools.partial(_set_first, "image"),
    ("arrangements.jsonl", "participant"): lambda arr, bad: _set(arr, "participant", bad, "p0"),
    ("ratings.jsonl", "participant"): lambda rating, bad: _set(rating, "participant", bad, "p0"),
}


@pytest.mark.parametrize("where", list(DATASET_FIELDS), ids=lambda w: f"{w[0]}:{w[1]}")
def test_control_characters_in_dataset_text_are_refused(where, tmp_path):
    file, field = where
    root = _tiny_root(tmp_path)
    original = (root / file).read_bytes() if (root / file).exists() else b"{}"
    for char in BAD_CHARS:
        (root / file).write_bytes(original)
        bad = {"class": "cup", "color1": "red", "color2": "red", "material1": "glass", "material2": "glass",
               "image": "pic.png", "latent_styles": "pic.png", "episodes": "pic.png"}.get(field.split(".")[-1], "word")
        bad = bad + char
        if field == "class":  # the word is in the vocabulary too: only the character can refuse it
            _edit_json(root / "meta.json", _set, "vocabulary", {"classes": [bad]})
        (_edit_jsonl if file.endswith(".jsonl") else _edit_json)(root / file, DATASET_FIELDS[where], bad)
        if field == "description" and char in "\n\r\t":  # prose: a description may have lines and tabs
            assert load_dataset(root).meta["description"] == bad
            continue
        with pytest.raises(DegustaError) as err:
            load_dataset(root)
        message = str(err.value)
        assert "\n" not in message and "\r" not in message and not CONTROL.search(message), repr(message)
        named = "meta.json" if field == "class" else file
        assert named in message, (repr(char), message)
        if char != "\ud800":  # a lone surrogate may be refused by the JSON reader already (file and line, no field)
            assert f"'{field if field != 'class' else 'vocabulary.classes'}'" in message, (repr(char), message)
        if field == "class":
            (root / "meta.json").write_text(json.dumps({"synthetic": True, "name": "tiny"}), encoding="utf-8")


@pytest.mark.parametrize("field", ["id", "participant", "task"])
def test_control_characters_in_episode_files_are_refused(field, tmp_path):
    root = _tiny_root(tmp_path)
    ds = load_dataset(root)
    eps = make_episodes(ds, 2, "all")
    for char in BAD_CHARS:
        write_episodes(tmp_path / "eps.jsonl", eps)
        value = {"id": eps[0].id, "participant": eps[0].participant, "task": eps[0].task}[field] + char
        _edit_jsonl(tmp_path / "eps.jsonl", _set, field, value)
        with pytest.raises(DegustaError) as err:
            read_episodes(tmp_path / "eps.jsonl", ds)
        message = str(err.value)
        assert "\n" not in message and "eps.jsonl:1" in message, (repr(char), message)
        assert f"'{field}'" in message or char == "\ud800", (repr(char), message)  # JSON reader: file and line


@pytest.mark.parametrize("field", ["episode", "participant", "method"])
def test_control_characters_in_prediction_files_are_refused(field, tmp_path):
    root = _tiny_root(tmp_path)
    ds = load_dataset(root)
    eps = make_episodes(ds, 2, "all")
    for char in BAD_CHARS:
        write_predictions(tmp_path / "p.jsonl", perfect(ds, eps, "m"))
        value = {"episode": eps[0].id, "participant": eps[0].participant, "method": "m"}[field] + char
        _edit_jsonl(tmp_path / "p.jsonl", _set, field, value)
        with pytest.raises(DegustaError) as err:
            read_predictions(tmp_path / "p.jsonl", ds.catalog)
        message = str(err.value)
        assert "\n" not in message and "p.jsonl:1" in message, (repr(char), message)
        assert f"'{field}'" in message or char == "\ud800", (repr(char), message)  # JSON reader: file and line


def test_printable_unicode_in_dataset_text_loads(tmp_path):
    """Validation refuses control characters only: accents, RTL scripts, emoji, CJK and punctuation load."""
    root = _tiny_root(tmp_path)
    words = ["tasse à café", "כוס", "كوب", "🍵", "茶碗", "e\u0301", "<b>&amp;", "=1+1", "x" * 100]
    _edit_json(root / "meta.json", lambda m: m.update(name=" | ".join(words), vocabulary={"classes": words}))
    _edit_json(root / "catalog.json", lambda cat: [o.__setitem__("class", words[i % len(words)])
                                                   for i, o in enumerate(cat)])
    _edit_jsonl(root / "arrangements.jsonl", lambda a: a.__setitem__("participant", "=p0 עברית"))
    (root / "ratings.jsonl").unlink()
    ds = load_dataset(root)
    assert set(words) <= set(ds.catalog.types)


# -- renderers and plots never traceback on text ---------------------------------------------------------------------

RENDER_TEXT = ["x" * 100, "W" * 100, "🍽️👩‍🍳🥄", "עברית العربية", "e\u0301\u0301\u0301 z\u0336a\u0337", "漢字かな",
               "<b>&amp;</b>", "$\\frac{$", "\u0000nul", "a\nb\rc\td", "\u2028\u2029\u0085", "", " ", "\ud800",
               "\u202eevil", "\ufffd\uffff"]


def test_renderers_draw_any_text(tmp_path):
    from PIL import Image, ImageDraw

    from degusta_learn.render import text as text_module
    from degusta_learn.render.lifting import Renderer

    im = Image.new("RGB", (200, 60), "gray")
    draw = ImageDraw.Draw(im)
    for t in RENDER_TEXT:
        text_module.text_size(t, 14)
        text_module.mark_size(t, 14)
        text_module.draw_centered(draw, (100, 30), t, 14, halo=(255, 255, 255), halo_width=2)
        text_module.draw_mark(draw, (4, 4), t, 12)
    # class, shape and pattern words that pass validation, drawn on the sheets that name them
    root = _tiny_root(tmp_path)
    words = [w for w in RENDER_TEXT if w.strip() and not CONTROL.search(w) and "\ud800" not in w and w != "\ufffd\uffff"]
    _edit_json(root / "meta.json", lambda m: m.update(vocabulary={"classes": words}))
    _edit_json(root / "catalog.json", lambda cat: [o.update({"class": words[i % len(words)], "shape": words[-1 - i % 3],
                                                            "pattern": words[i % 2]}) for i, o in enumerate(cat)])
    ds = load_dataset(root)
    renderer = Renderer.for_dataset(ds, size=96)
    for type_ in ds.catalog.types[:len(words) + 1]:
        renderer.gomo(type_)
    arr = ds.arrangements[0]
    renderer.uma(arr.table, list(arr.placements))


@pytest.mark.filterwarnings("ignore:Tight layout not applied")  # a 3,000-character label: cut, still wide
def test_plots_and_qualitative_panels_take_any_label(tmp_path):
    import numpy as np

    from degusta_learn.evaluate.plots import plot_acceptability, plot_context, plot_metric_bars
    from degusta_learn.evaluate.qualitative import render_side_by_side
    from degusta_learn.render.lifting import Renderer

    stat = {"mean": 0.1, "ci_low": 0.05, "ci_high": 0.2}
    entry = {"set_rmsd": stat, "rmsd": stat, "object_accuracy": stat, "degenerate": False,
             "by_context": {"0": {"set_rmsd": stat, "object_accuracy": stat, "rmsd": stat},
                            "2": {"set_rmsd": stat, "object_accuracy": stat, "rmsd": stat}}}
    labels = ["<script>alert(1)</script>", "a\n# Fake section", "nul\x00byte", "$\\frac{$", "$x^$", "_hidden",
              "a$b$c", "\\", "\ud800", "x" * 3000]
    summary = {label: dict(entry, degenerate=i % 3 == 0) for i, label in enumerate(labels)}
    plot_metric_bars(summary, tmp_path / "bars.png", 0.01)
    plot_acceptability({0.05: 0.5, 0.1: 0.8}, {label: np.array([0.01, 0.2]) for label in labels},
                       tmp_path / "acc.png", {labels[0]})
    plot_context(summary, tmp_path / "ctx.png", 0.01)
    ds = tiny_dataset([PRINTABLE[0], "p1", "p2"])
    arr = ds.arrangements[0]
    panels = {label: (list(arr.placements), label) for label in labels}
    render_side_by_side(ds, Renderer.for_dataset(ds, size=64), arr.participant, arr.trial, panels, tmp_path / "q.png")
    assert all((tmp_path / n).is_file() for n in ("bars.png", "acc.png", "ctx.png", "q.png"))


# -- the mechanism itself: degusta_learn.textsafe ------------------------------------------------------------------

def _cells(html_text: str) -> list[str]:
    page = Page(html_text)
    return [t for tag, t in page.texts if tag in ("td", "code", "h1", "p", "li")]


@pytest.mark.parametrize("text", HOSTILE, ids=range(len(HOSTILE)))
def test_markdown_escapes_render_as_the_text(text):
    from degusta_learn.textsafe import markdown_to_html, md_code, md_prose, md_text, one_line

    shown = one_line(text, limit=5000)
    assert "\n" not in shown and "\r" not in shown and not CONTROL.search(re.sub("[\u200c\u200d]", "", shown))
    cell = md_text(text, limit=5000)
    doc = (f"# {cell}\n\n| a | b |\n|---|---|\n| {cell} | {cell} |\n\n- {cell}\n\n> {cell}\n\n"
           f"episode {md_code(text, limit=5000)}\n")
    page = assert_inert_html(f"<style></style>{markdown_to_html(doc)}")
    shape = page.shape()
    assert (shape.get("h1"), shape.get("tr"), shape.get("td"), shape.get("li"), shape.get("blockquote")) == \
        (1, 2, 2, 1, 1), (doc, shape)
    assert shape.get("a") is None and shape.get("img") is None and shape.get("em") is None
    h1 = "".join(t for tag, t in page.texts if tag == "h1")
    assert visible(h1) == visible(shown)
    code = "".join(t for tag, t in page.texts if tag == "code")
    assert visible(code) == visible(shown)
    # a sentence of ours quoting it (a note, an error message): `...` pairs become code, the rest stays text
    prose = markdown_to_html(f"- {md_prose(text, limit=5000)}\n\n- server said: {md_prose(text, limit=5000)}\n")
    page = assert_inert_html(f"<style></style>{prose}")
    assert page.shape().get("li") == 2 and set(page.shape()) <= {"style", "ul", "li", "p", "code"}, prose
    items = prose.split("</li>")[0]
    assert visible(Page(items).text) == visible(re.sub(r"`([^`]+)`", r"\1", shown)), prose


def test_markdown_to_html_neutralises_raw_html_and_unsafe_urls():
    from degusta_learn.textsafe import markdown_to_html

    doc = ("<script>alert(1)</script>\n\n<img src=x onerror=alert(1)>\n\n[a](javascript:alert(1)) "
           "[b](JAVAscript:alert(1)) [c](java\tscript:x) [d](data:text/html,x) [e](vbscript:x) "
           "![f](javascript:alert(1)) [g](https://example.org) [h](plots/metrics.png) [i](mailto:x@y.z) [k](//evil.example/x)\n\n"
           "[r]: javascript:alert(1)\n\n[j][r] &lt;kept&gt; &#60;b&#62;\n")
    out = markdown_to_html(doc)
    page = assert_inert_html(f"<style></style>{out}")
    hrefs = [dict(attrs).get("href") or dict(attrs).get("src") for tag, attrs in page.tags if tag in ("a", "img")]
    assert "https://example.org" in hrefs and "plots/metrics.png" in hrefs
    assert "<script>" in page.text and "<kept>" in page.text  # shown, not run


@pytest.mark.parametrize("value, expected", [
    ("=1+1", "'=1+1"), ("+1+2", "'+1+2"), ("+1", "+1"), ("-cmd", "'-cmd"), ("@SUM(A1)", "'@SUM(A1)"), ("\t=1", "'\t=1"),
    ("\r=1", "'\r=1"), (" =1", "' =1"), ("＝1+1", "'＝1+1"), ("-0.5", "-0.5"), ("+3", "+3"), ("-1e-3", "-1e-3"),
    ("p001", "p001"), ("a=b", "a=b"), ("", ""), (-0.5, -0.5), (3, 3), (None, None), (True, True),
])
def test_csv_cells(value, expected):
    from degusta_learn.textsafe import csv_cell

    assert csv_cell(value) == expected


def test_safe_csv_writer_round_trips(tmp_path):
    from degusta_learn.textsafe import write_csv

    rows = [{"name": h, "value": -0.5, "n": 3} for h in HOSTILE] + [{"name": "-2", "value": None, "n": -1}]
    path = tmp_path / "x.csv"
    with path.open("w", newline="", encoding="utf-8") as f:
        write_csv(f, ["name", "value", "n"], rows)
    back = assert_safe_csv_generic(path)
    assert len(back) == len(rows)
    assert [r["value"] for r in back[:-1]] == ["-0.5"] * len(HOSTILE) and back[-1] == {"name": "-2", "value": "",
                                                                                          "n": "-1"}


def assert_safe_csv_generic(path: Path) -> list[dict]:
    with path.open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        for cell in row.values():
            if cell.lstrip(" ").startswith(FORMULA_START):
                assert NUMBER.fullmatch(cell), cell
    return rows


def test_unprintable_names_the_character():
    from degusta_learn.textsafe import unprintable

    assert unprintable("plain words, ünïcödé, עברית, 🍽️") is None
    for char in BAD_CHARS:
        found = unprintable("ab" + char)
        assert found is not None and "U+" in found and "character 3" in found, (repr(char), found)
        assert unicodedata.category(char) in ("Cc", "Cf", "Cs", "Zl", "Zp")
