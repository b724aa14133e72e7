"""Untrusted text into Markdown, HTML, CSV and pictures: the one place where text becomes markup.

Dataset names, config titles, participant and episode ids, folder names and the error messages of failed
methods (a server's reply among them) are untrusted: a report must show them as the text they are, never
run them (a `<script>` in a dataset's name), never let them change the report's structure (a newline and
`# Fake section` in a name) and never let a spreadsheet evaluate them (`=HYPERLINK(...)` as a participant id).
Every writer of report.md / report.html / per_episode.csv (evaluate/report.py, evaluate/compare_report.py)
goes through these functions; the planner's and the study's pages should too.

- `one_line(text, limit)`: the text on one line: every run of whitespace (newline, CR, tab, U+0085, U+2028,
  U+2029 ...) becomes one space; other invisible or control characters (NUL, ESC, bidi overrides, zero-width
  spaces, lone surrogates: Unicode categories Cc, Cf, Cs, Zl, Zp, except the joiners U+200C/U+200D inside
  emoji and scripts) are shown as `\\xNN` / `\\uNNNN`; longer than `limit` characters: cut, with the length said.
- `md_text(text)`: inline Markdown (a table cell, a heading, a list item, bold text) that renders as exactly
  `one_line(text)`: `\\ ` * _ [ ] # |` are backslash-escaped, `& < > ~` written as character references, a
  leading list marker escaped; only escapes both Python-Markdown (what report.html is rendered with, tested)
  and CommonMark/GFM (a report.md opened on GitHub) understand.
- `md_prose(text)`: a sentence of ours with untrusted parts (a note naming a file): its `...` pairs become
  code spans (`md_code`), the rest is escaped as by `md_text`.
- `md_code(text)`: an inline code span (a fence longer than any backtick run inside); not for table cells
  (Python-Markdown and GFM disagree on `|` inside code spans there): use `md_text` in cells.
- `markdown_to_html(text)`: Python-Markdown (tables) with raw HTML off (a tag in the source is shown as text,
  never passed through), character references kept, and every link/image URL checked: only relative paths and
  http(s) URLs survive, others (javascript:, data:, vbscript:, file:, //host) are dropped.
- `html_text(text)`: `one_line` + HTML escaping, for text put straight into a page (the <title>).
- `csv_cell(value)` / `write_csv(f, fieldnames, rows)`: the OWASP rule for CSV injection: a text cell whose
  first non-blank character is = + - @ TAB CR LF (or their full-width forms) gets a leading `'`, unless the
  whole cell is a plain number (-0.5 stays -0.5); numbers, booleans and None are written as they are.
- `plot_text(text)`: `one_line` for a matplotlib label, with `$` escaped (no mathtext parse error) and a
  leading `_` kept visible (matplotlib hides legend labels starting with `_`).
- `unprintable(text)`: what the dataset validators refuse (scene/validate.py): a description of the first
  character of category Cc, Cf, Cs, Zl or Zp ("a newline (U+000A) at character 3"), or None.

Example:
    >>> md_text("<b>x</b> | *y*")
    '&lt;b&gt;x&lt;/b&gt; \\\\| \\\\*y\\\\*'
    >>> csv_cell("=1+1"), csv_cell("-0.5"), csv_cell(-0.5)
    ("'=1+1", '-0.5', -0.5)
"""

from __future__ import annotations

import csv
import html
import re
import unicodedata
import xml.etree.ElementTree as ET
from collections.abc import Iterable

import markdown
from markdown.treeprocessors import Treeprocessor

_UNSAFE_CATEGORIES = frozenset({"Cc", "Cf", "Cs", "Zl", "Zp"})
_JOINERS = frozenset("\u200c\u200d")  # ZWNJ / ZWJ: part of emoji sequences and of several scripts
_NAMES = {"\n": "a newline", "\r": "a carriage return", "\t": "a tab", "\x00": "a NUL byte", "\x1b": "an escape",
          "\x7f": "a delete", "\x85": "a next-line character", "\u2028": "a line separator",
          "\u2029": "a paragraph separator", "\ufeff": "a byte-order mark"}

NAME_LIMIT = 300
"""Characters of a name (dataset, title, id, folder) a report shows before cutting it."""
MESSAGE_LIMIT = 2000
"""Characters of an error message (a failed method's, which may quote a server's reply) a report shows."""


def _unsafe(ch: str) -> bool:
    return ch not in _JOINERS and unicodedata.category(ch) in _UNSAFE_CATEGORIES


def unprintable(text: str, allow: str = "") -> str | None:
    """A description of the first control or invisible character in `text` (Unicode categories Cc, Cf, Cs,
    Zl, Zp: newline, tab, NUL, U+2028, bidi overrides, zero-width characters, lone surrogates) that is not in
    `allow`, or None."""
    for i, ch in enumerate(text):
        category = unicodedata.category(ch)
        if category in _UNSAFE_CATEGORIES and ch not in allow:
            name = _NAMES.get(ch) or {"Cc": "a control character", "Cs": "a lone surrogate"}.get(category) \
                or f"a {unicodedata.name(ch, 'format character').lower()}"
            return f"{name} (U+{ord(ch):04X}) at character {i + 1}"
    return None


def _visible_escape(ch: str) -> str:
    code = ord(ch)
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def one_line(text, limit: int | None = NAME_LIMIT) -> str:
    """`text` (any value: str() of it) on one line with control characters made visible; see the module doc."""
    text = str(text)
    if limit is not None and len(text) > limit:
        text = f"{text[:limit]}… ({len(text):,} characters)"
    out, space = [], False
    for ch in text:
        if ch.isspace() or unicodedata.category(ch) in ("Zl", "Zp"):
            space = True
            continue
        if space and out:
            out.append(" ")
        space = False
        out.append(_visible_escape(ch) if _unsafe(ch) else ch)
    return "".join(out)


_MD_ESCAPE = {"\\": "\\\\", "`": "\\`", "*": "\\*", "[": "\\[", "]": "\\]", "#": "\\#", "|": "\\|",
              "&": "&amp;", "<": "&lt;", ">": "&gt;", "~": "&#126;"}
_LEADING_MARKER = re.compile(r"([-+]|\d+(?=[.)]))")


def md_text(text, limit: int | None = NAME_LIMIT) -> str:
    """`text` as inline Markdown that renders as `one_line(text)`, safe in a table cell (see the module doc)."""
    return _md_escape(one_line(text, limit))


def _md_escape(line: str, at_start: bool = True) -> str:
    out = []
    for i, ch in enumerate(line):
        if ch == "_":  # inside a word (snake_case) an underscore is text in CommonMark and Python-Markdown alike
            inside = 0 < i < len(line) - 1 and line[i - 1].isalnum() and line[i + 1].isalnum()
            out.append("_" if inside else "\\_")
        else:
            out.append(_MD_ESCAPE.get(ch, ch))
    escaped = "".join(out)
    m = _LEADING_MARKER.match(escaped) if at_start else None
    if m:  # "- x", "+ x", "1. x" at the start of a list item or a quote would nest a list
        end = m.end()
        escaped = f"\\{escaped}" if m.group(1) in "-+" else f"{escaped[:end]}\\{escaped[end:]}"
    return escaped


def md_code(text, limit: int | None = NAME_LIMIT) -> str:
    """`text` as an inline code span (shown verbatim, monospace); not for table cells (use md_text there)."""
    return _md_code(one_line(text, limit))


def md_prose(text, limit: int | None = MESSAGE_LIMIT) -> str:
    """A sentence of ours with untrusted parts (a report's note naming a file): `one_line(text)` where each
    `...` pair becomes a code span and everything else is escaped as by `md_text`. Text that is all untrusted
    (an error message quoting a server) goes through `md_text`, which shows its backticks as they are."""
    parts = re.split(r"`([^`]+)`", one_line(text, limit))
    return "".join(_md_code(part) if i % 2 else _md_escape(part, at_start=i == 0) for i, part in enumerate(parts))


def _md_code(line: str) -> str:
    longest = max((len(run) for run in re.findall(r"`+", line)), default=0)
    fence = "`" * (longest + 1)
    pad = " " if line.startswith("`") or line.endswith("`") or not line else ""
    return f"{fence}{pad}{line}{pad}{fence}"


def html_text(text, limit: int | None = NAME_LIMIT) -> str:
    """`text` on one line, HTML-escaped (quotes too): safe between tags and inside attribute values."""
    return html.escape(one_line(text, limit), quote=True)


# -- Markdown to HTML ------------------------------------------------------------------------------------------------

_SAFE_SCHEMES = frozenset({"http", "https"})
_URL_ATTRIBUTES = ("href", "src")


def safe_url(url: str) -> bool:
    """A relative path (no scheme, not //host) or an http(s) URL; what browsers ignore inside a scheme
    (tabs, newlines, leading blanks) and character references are undone first."""
    text = (url or "").replace(markdown.util.AMP_SUBSTITUTE, "&")  # Python-Markdown's stand-in for a literal &
    squeezed = re.sub(r"[\x00-\x20\x7f]", "", html.unescape(text))
    if squeezed.startswith(("//", "\\\\", "/\\", "\\/")):
        return False
    scheme = re.match(r"([A-Za-z][A-Za-z0-9+.\-]*):", squeezed)
    return scheme is None or scheme.group(1).lower() in _SAFE_SCHEMES


class _SafeLinks(Treeprocessor):
    """Drops unsafe URLs (safe_url) and any on* attribute from every element of the rendered tree."""

    def run(self, root: ET.Element) -> None:
        for element in root.iter():
            for key in list(element.attrib):
                if key.lower().startswith("on") or (key in _URL_ATTRIBUTES and not safe_url(element.attrib[key])):
                    del element.attrib[key]


def _markdown() -> markdown.Markdown:
    md = markdown.Markdown(extensions=["tables"], output_format="html")
    md.preprocessors.deregister("html_block")  # a raw HTML block is a paragraph of text, escaped
    md.inlinePatterns.deregister("html")  # inline tags and comments are text, escaped (entities are kept)
    md.treeprocessors.register(_SafeLinks(md), "degusta_safe_links", -1)  # last: after links and unescaping
    return md


def markdown_to_html(text: str) -> str:
    """Render Markdown to an HTML fragment in which no input can run anything (see the module doc)."""
    return _markdown().convert(text)


# -- CSV -------------------------------------------------------------------------------------------------------------

_FORMULA_START = frozenset("=+-@\t\r\n\uff1d\uff0b\uff0d\uff20")  # with the full-width = + - @
_SURROGATE = re.compile("[\ud800-\udfff]")
_PLAIN_NUMBER = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?")


def csv_cell(value):
    """`value` made safe for a spreadsheet: text starting (after blanks) with = + - @ TAB CR LF gets a leading
    `'` unless it is a plain number (a lone surrogate is written as `\\udcXX`); anything not a str (numbers,
    booleans, None) is returned unchanged."""
    if not isinstance(value, str) or not value:
        return value
    if _SURROGATE.search(value):  # a lone surrogate (an undecodable file name) cannot be written as UTF-8
        value = _SURROGATE.sub(lambda m: _visible_escape(m.group()), value)
    first = value.lstrip(" ")[:1] or value[:1]
    if (first in _FORMULA_START or value[0] in _FORMULA_START) and not _PLAIN_NUMBER.fullmatch(value):
        return "'" + value
    return value


def write_csv(f, fieldnames: Iterable[str], rows: Iterable[dict]) -> None:
    """Write a header and `rows` (dicts; None is an empty cell) to the open text file `f`, every cell through
    `csv_cell` (the csv module quotes commas, quotes and newlines, so every cell parses back as one cell)."""
    fieldnames = list(fieldnames)
    writer = csv.DictWriter(f, fieldnames=[csv_cell(k) for k in fieldnames], extrasaction="raise")
    writer.writeheader()
    for row in rows:
        writer.writerow({csv_cell(k): ("" if v is None else csv_cell(v)) for k, v in row.items()})


# -- pictures --------------------------------------------------------------------------------------------------------

def plot_text(text, limit: int | None = 80) -> str:
    """`one_line(text)` for a matplotlib label: `$` escaped (no mathtext), a leading `_` kept visible."""
    line = one_line(text, limit).replace("$", r"\$")
    return f" {line}" if line.startswith("_") else line
