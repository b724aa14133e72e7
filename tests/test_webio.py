"""The web servers' shared request reading (webio.py): strict JSON and an address checked before serving."""

from __future__ import annotations

import socket

import pytest

from degusta_learn.cli import main
from degusta_learn.errors import DegustaError
from degusta_learn.webio import check_bindable, strict_json


@pytest.mark.parametrize("body, message", [
    (b'{"x": NaN}', "NaN is not a number JSON allows"),
    (b'{"x": 1e999}', "overflows to infinity"),
    (b'{"x": 1, "x": 2}', "given twice"),
    (b'{"x": ' + b"1" * 30 + b"}", "30 digits is out of range"),
    (b"\xff{}", "not UTF-8"),
    (b"[" * 100_000, "nested too deeply"),
    (b'{"x": ', "invalid JSON at line 1"),
])
def test_strict_json_refuses_in_one_line_naming_what(body, message):
    with pytest.raises(DegustaError, match=message) as e:
        strict_json(body, "draft")
    assert str(e.value).startswith("draft: ") and "\n" not in str(e.value)


def test_a_port_in_use_is_refused_before_anything_is_made(tmp_path, capsys):
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        with pytest.raises(DegustaError, match=f"cannot serve on 127.0.0.1:{port}: .*choose another with --port"):
            check_bindable("127.0.0.1", port)
        assert main(["collect", "--dataset", str(tmp_path / "study"), "--new", "--port", str(port)]) == 2
    assert "choose another with --port" in capsys.readouterr().err
    assert not (tmp_path / "study").exists()  # --new made nothing
    check_bindable("127.0.0.1", port)  # free again
