"""`degusta collect`'s server and store (the browser side: test_collect_browser.py): the steps of a study, what is
written, resuming, idempotent submissions, concurrent participants, isolation and refused input."""

from __future__ import annotations

import json
import threading
import zipfile
from io import BytesIO
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from degusta_learn.cli import main
from degusta_learn.collect import load_study_config, new_study_folder, open_study
from degusta_learn.collect.selfeval import displacement_rmsd, jitter_rng, jittered
from degusta_learn.collect.server import COOKIE, create_app
from degusta_learn.collect.store import StudyStore
from degusta_learn.errors import DegustaError
from degusta_learn.scene import load_dataset
from degusta_learn.scene.types import Placement

KEY = "researcher-key-0123456789"


def _app(folder: Path, *overrides: str):
    study = open_study(folder, load_study_config(None, ["tables_per_participant=2", *overrides]))
    return create_app(study, KEY)


@pytest.fixture
def folder(tmp_path):
    return new_study_folder(tmp_path / "study")


@pytest.fixture
def client(folder):
    with TestClient(_app(folder)) as c:
        yield c


def _plates(client, n=3, x0=0.3):
    objects = client.get("/api/study").json()["objects"]
    ids = [o["id"] for o in objects if o["type"] in ("plate", "fork", "cup")][::7][:n]
    return [{"object": oid, "x": round(x0 + 0.1 * i, 3), "y": 0.5, "rotation": 15.0 * i} for i, oid in enumerate(ids)]


def _step(client, state, sid, **body):
    r = client.post("/api/submit", json={"submission": sid, "trial": state["trial"], "stage": state["stage"], **body})
    assert r.status_code == 200, r.text
    return r.json()


def _finish_table(client, state, placements, ratings=(80, 60, 75), tag=""):
    """arrange -> rate_initial -> rate_jitter -> correct (put back) -> rate_correct."""
    state = _step(client, state, f"{tag}a{state['trial']}", placements=placements)
    assert state["stage"] == "rate_initial" and state["scene"] == placements
    state = _step(client, state, f"{tag}ri{state['trial']}", rating=ratings[0])
    assert state["stage"] == "rate_jitter"
    jittered_scene = state["scene"]
    state = _step(client, state, f"{tag}rj{state['trial']}", rating=ratings[1])
    assert state["stage"] == "correct" and state["draft"] == jittered_scene
    state = _step(client, state, f"{tag}c{state['trial']}", placements=placements)  # put it right exactly
    assert state["stage"] == "rate_correct"
    return _step(client, state, f"{tag}rc{state['trial']}", rating=ratings[2])


def test_a_whole_session_writes_the_dataset_format_and_validates(client, folder, capsys):
    assert client.get("/api/state").status_code == 401
    state = client.post("/api/session", json={}).json()
    assert (state["participant"], state["trial"], state["stage"], state["trials"]) == ("c001", 0, "arrange", 2)
    tables = []
    for k in range(2):
        tables.append(state["table"])
        state = _finish_table(client, state, _plates(client, 3 + k), ratings=(80, 60 - k, 75))
    assert state["stage"] == "done" and len(set(tables)) == 2
    ds = load_dataset(folder)
    assert [(a.participant, a.trial, a.table, len(a.placements)) for a in ds.arrangements] == [
        ("c001", 0, tables[0], 3), ("c001", 1, tables[1], 4)]
    assert ds.arrangements[1].placements[3].rotation == 45.0  # as submitted, in placement order
    assert [(r.b_initial, r.b_jitter, r.b_correct, r.rmsd_correct) for r in ds.ratings] == [(80, 60, 75, 0.0),
                                                                                            (80, 59, 75, 0.0)]
    record = [json.loads(line) for line in (folder / "collect" / "self_evaluation.jsonl").read_text().splitlines()]
    for rating, rec in zip(ds.ratings, record):  # what was shown is kept, and its RMSD is the one rated
        shown = [Placement(**p) for p in rec["jittered"]]
        initial = [Placement(**p) for p in rec["initial"]]
        assert rating.rmsd_jitter == displacement_rmsd(shown, initial) > 0 and 0 <= rec["t"] <= 1
    capsys.readouterr()
    assert main(["data", "validate", str(folder)]) == 0
    assert "valid — 125 objects, 5 tables, 1 participants, 2 arrangements, 2 ratings" in capsys.readouterr().out


def test_the_jitter_is_the_simulated_studys(folder):
    """A rigid move of the whole scene by shift*t and a turn of turn*t degrees about the centroid (synth/ratings.py),
    objects turning with it; reproducible from the seed, participant and trial."""
    pts = [Placement(1, 0.3, 0.4, 0.0), Placement(2, 0.6, 0.4, 90.0), Placement(3, 0.45, 0.7, 10.0)]
    t, moved = jittered(pts, 0.15, 30.0, jitter_rng(0, "c001", 0))
    assert (t, moved) == jittered(pts, 0.15, 30.0, jitter_rng(0, "c001", 0))
    assert jittered(pts, 0.15, 30.0, jitter_rng(0, "c001", 1)) != (t, moved)
    a, b = np.array([[p.x, p.y] for p in pts]), np.array([[p.x, p.y] for p in moved])
    turn = [(m.rotation - p.rotation) % 360 for p, m in zip(pts, moved)]
    assert max(turn) - min(turn) < 1e-6  # one turn for every object
    degrees = turn[0] if turn[0] < 180 else turn[0] - 360
    assert abs(abs(degrees) - 30.0 * t) < 1e-3
    shift = np.linalg.norm(b.mean(0) - a.mean(0))
    assert abs(shift - 0.15 * t) < 1e-5
    # the pairwise distances are kept (rigid), and the RMSD is the displacement
    assert np.allclose(np.linalg.norm(a[:, None] - a[None], axis=-1), np.linalg.norm(b[:, None] - b[None], axis=-1),
                       atol=1e-5)
    assert displacement_rmsd(moved, pts) == pytest.approx(np.sqrt(((a - b) ** 2).sum(1).mean()), abs=1e-6)


def test_a_replayed_submission_is_written_once_and_a_stale_one_is_refused(client, folder):
    state = client.post("/api/session", json={}).json()
    body = {"submission": "s-1", "trial": 0, "stage": "arrange", "placements": _plates(client)}
    first = client.post("/api/submit", json=body).json()
    again = client.post("/api/submit", json=body)
    assert again.status_code == 200 and again.json()["replayed"] and again.json()["stage"] == first["stage"]
    stale = client.post("/api/submit", json={**body, "submission": "s-2"})  # a second tab still on the old step
    assert stale.status_code == 409 and "reload" in stale.json()["detail"]
    assert (folder / "arrangements.jsonl").read_text().count("\n") == 1
    assert state["stage"] == "arrange" and first["stage"] == "rate_initial"


@pytest.mark.parametrize("placements, message", [
    ([{"object": 999, "x": 0.5, "y": 0.5}], "unknown object id 999"),
    ([{"object": 1, "x": 1.3, "y": 0.5}], "1.3 is outside [0, 1]"),
    ([{"object": 1, "x": 0.5, "y": 0.5}, {"object": 1, "x": 0.6, "y": 0.5}], "object 1 is placed twice"),
    ([{"object": 1, "x": "0.5", "y": 0.5}], "expected a number"),
    ([{"object": 1, "x": 0.5, "y": 0.5}, {"object": 2, "x": 0.6, "y": 0.5}], "fewer than the minimum of 3"),
    ("plates", "expected a list"),
])
def test_an_invalid_arrangement_is_400_naming_it_and_writes_nothing(client, folder, placements, message):
    client.post("/api/session", json={})
    r = client.post("/api/submit", json={"submission": "x", "trial": 0, "stage": "arrange", "placements": placements})
    assert r.status_code == 400 and message in r.json()["detail"], r.json()
    assert r.json()["detail"].count("\n") == 0
    assert not (folder / "arrangements.jsonl").exists()
    assert client.get("/api/state").json()["stage"] == "arrange"  # the server goes on serving, nothing moved


def test_off_the_surface_is_refused_on_submit_but_kept_in_a_draft(client, folder):
    state = client.post("/api/session", json={}).json()
    table = next(t for t in client.get("/api/study").json()["tables"] if t["id"] == state["table"])
    x0 = min(p[0] for p in table["surface"])
    off = [*_plates(client, 3), {"object": 100, "x": x0 / 2, "y": 0.5, "rotation": 0}]
    assert client.put("/api/draft", json={"trial": 0, "stage": "arrange", "placements": off}).json() == {"saved": True}
    r = client.post("/api/submit", json={"submission": "x", "trial": 0, "stage": "arrange", "placements": off})
    assert r.status_code == 400 and "placements[3]" in r.json()["detail"] and "off the surface" in r.json()["detail"]
    assert client.get("/api/state").json()["draft"] == off


@pytest.mark.parametrize("content, headers, status, message", [
    (b'{"submission": "x", "trial": 0, "stage": "arrange", "placements": [{"object": 1, "x": NaN, "y": 0.5}]}',
     {"content-type": "application/json"}, 400, "NaN is not a number JSON allows"),
    (b"{" + b'"a": 1, ' * 40000 + b"}", {"content-type": "application/json"}, 413, "over the limit"),
    (b"submission=x", {"content-type": "application/x-www-form-urlencoded"}, 415, "expected Content-Type"),
    (b'{"submission": "x", "submission": "y"}', {"content-type": "application/json"}, 400, "given twice"),
    (b"[1, 2]", {"content-type": "application/json"}, 400, "expected a JSON object"),
    (b'{"submission": "x", "trial": 0, "stage": "rate_initial", "rating": 50}', {"content-type": "application/json"},
     409, "step arrange"),
    (b'{"submission": "x", "trial": 0, "stage": "<script>", "rating": 50}', {"content-type": "application/json"},
     400, "unknown stage"),
])
def test_malformed_requests_get_one_line_and_the_server_goes_on(client, folder, content, headers, status, message):
    client.post("/api/session", json={})
    r = client.post("/api/submit", content=content, headers=headers)
    assert r.status_code == status and message in r.json()["detail"], r.text
    assert "Traceback" not in r.text and r.json()["detail"].count("\n") == 0
    assert not (folder / "arrangements.jsonl").exists()
    ok = client.post("/api/submit", json={"submission": "y", "trial": 0, "stage": "arrange",
                                          "placements": _plates(client)})
    assert ok.status_code == 200


def test_ratings_must_be_numbers_from_0_to_100(client):
    state = client.post("/api/session", json={}).json()
    state = _step(client, state, "a", placements=_plates(client))
    for bad in (101, -1, "50", None, True):
        r = client.post("/api/submit", json={"submission": f"r{bad}", "trial": 0, "stage": "rate_initial",
                                             "rating": bad})
        assert r.status_code == 400 and "rating" in r.json()["detail"]
    assert client.get("/api/state").json()["stage"] == "rate_initial"


def test_a_correction_moves_the_jittered_objects_and_adds_none(client):
    state = client.post("/api/session", json={}).json()
    mine = _plates(client)
    state = _step(client, state, "a", placements=mine)
    state = _step(client, state, "b", rating=70)
    state = _step(client, state, "c", rating=40)
    r = client.post("/api/submit", json={"submission": "d", "trial": 0, "stage": "correct",
                                         "placements": [*mine, {"object": 120, "x": 0.5, "y": 0.3, "rotation": 0}]})
    assert r.status_code == 400 and "does not add or remove" in r.json()["detail"]
    moved = [{**p, "x": round(p["x"] + 0.02, 6)} for p in mine]
    state = _step(client, state, "e", placements=moved)
    assert state["stage"] == "rate_correct" and state["scene"] == moved


def test_sessions_resume_after_a_restart_and_no_one_reaches_anothers_data(folder):
    app = _app(folder)
    with TestClient(app) as a, TestClient(app) as b:
        sa = a.post("/api/session", json={}).json()
        sb = b.post("/api/session", json={}).json()
        assert sa["participant"] != sb["participant"]
        draft = _plates(a, 2)
        a.put("/api/draft", json={"trial": 0, "stage": "arrange", "placements": draft})
        # b cannot act for a: there is no participant id in any request, only b's own cookie
        assert b.get("/api/state").json()["participant"] == sb["participant"] and b.get("/api/state").json()["draft"] == []
        token = a.cookies.get(COOKIE)
    forged = TestClient(_app(folder))
    forged.cookies.set(COOKIE, "not-a-token")
    assert forged.get("/api/state").status_code == 401
    assert forged.post("/api/session", json={"participant": sa["participant"]}).status_code == 400  # ids are assigned
    # a restart (a new app on the same folder) with a's cookie: a is where they were, draft and all
    with TestClient(_app(folder)) as again:
        again.cookies.set(COOKIE, token)
        state = again.get("/api/state").json()
        assert (state["participant"], state["stage"], state["draft"]) == (sa["participant"], "arrange", draft)
        assert again.post("/api/session", json={}).json()["participant"] == sa["participant"]  # no second session
    stored = (folder / "collect" / "participants" / f"{sa['participant']}.json").read_text()
    assert token not in stored  # only its SHA-256 reaches the disk


def test_entered_ids_are_checked_and_never_taken_twice(folder):
    with TestClient(_app(folder, "participant_ids=enter")) as a:
        for bad in ("<img src=x onerror=alert(1)>", "", "a" * 65, "../etc", 7):
            r = a.post("/api/session", json={"participant": bad})
            assert r.status_code == 400 and "participant" in r.json()["detail"]
        assert a.post("/api/session", json={"participant": "P-07"}).status_code == 200
    with TestClient(_app(folder, "participant_ids=enter")) as b:  # after a restart, too
        r = b.post("/api/session", json={"participant": "P-07"})
        assert r.status_code == 409 and "already in use" in r.json()["detail"]


def test_a_crash_between_the_line_and_the_state_neither_loses_nor_doubles_it(folder, monkeypatch):
    study = open_study(folder, load_study_config(None, ["tables_per_participant=2", "self_evaluation=false"]))
    store = StudyStore(study)
    token, st = store.start(None)
    calls = []

    def crash(self, st):
        calls.append(st.stage)
        if len(calls) == 1:
            raise OSError("power cut")

    monkeypatch.setattr(StudyStore, "_save", crash)
    placements = [{"object": o, "x": 0.3 + 0.1 * i, "y": 0.5, "rotation": 0.0} for i, o in enumerate((0, 30, 80))]
    with pytest.raises(OSError):
        store.submit(st, {"submission": "a", "trial": 0, "stage": "arrange", "placements": placements})
    monkeypatch.undo()
    again = StudyStore(open_study(folder, study.config))  # the restart reconciles from the line
    st2 = again.session(token)
    assert (st2.trial, st2.stage) == (1, "arrange")
    assert (folder / "arrangements.jsonl").read_text().count("\n") == 1


def test_twenty_participants_at_once_lose_and_double_nothing(folder):
    app = _app(folder, "self_evaluation=false")
    errors, made = [], []

    def participant(k: int):
        try:
            with TestClient(app) as c:
                state = c.post("/api/session", json={}).json()
                for trial in range(2):
                    body = {"submission": f"{k}-{trial}", "trial": trial, "stage": "arrange",
                            "placements": _plates(c, 3 + trial % 2, x0=0.3)}
                    assert c.post("/api/submit", json=body).status_code == 200
                    assert c.post("/api/submit", json=body).json()["replayed"]  # a double click
                    made.append((state["participant"], trial))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(repr(e))

    threads = [threading.Thread(target=participant, args=(k,)) for k in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors and not any(t.is_alive() for t in threads)
    ds = load_dataset(folder)
    assert sorted((a.participant, a.trial) for a in ds.arrangements) == sorted(made) and len(made) == 40


def test_the_researchers_pages_need_the_key_and_escape_what_they_show(folder):
    with TestClient(_app(folder, "title=<b>Lab</b> & co")) as c:
        c.post("/api/session", json={})
        assert c.get("/research").status_code == 403
        assert c.get("/research?key=wrong-key-000000").status_code == 403
        page = c.get(f"/research?key={KEY}")
        assert page.status_code == 200 and "&lt;b&gt;Lab&lt;/b&gt; &amp; co" in page.text and "<b>Lab" not in page.text
        assert "c001" in page.text and "script" not in page.text.lower()
        assert "default-src 'self'" in page.headers["content-security-policy"]
        import html
        import re

        links = [html.unescape(h) for h in re.findall(r'href="(/research/export[^"]*)"', page.text)]
        assert len(links) == 2 and all(c.get(link).status_code == 200 for link in links)  # the page's own links work
        state = c.get("/api/state").json()
        _finish_table(c, state, _plates(c))
        z = zipfile.ZipFile(BytesIO(c.get(f"/research/export?key={KEY}").content))
        assert {"catalog.json", "tables.json", "meta.json", "arrangements.jsonl", "ratings.jsonl",
                "collect/self_evaluation.jsonl"} == set(z.namelist())
        complete = zipfile.ZipFile(BytesIO(c.get("/research/export", params={"key": KEY, "complete": "1"}).content))
        assert "arrangements.jsonl" not in complete.namelist()  # c001 has not finished both tables
        assert c.get("/research/export", headers={"Authorization": f"Bearer {KEY}"}).status_code == 200


def test_a_study_config_that_cannot_run_is_one_line_naming_the_key(folder, tmp_path):
    cfg = load_study_config
    with pytest.raises(DegustaError, match=r"tables_per_participant: 9 tables.*only 5 tables"):
        open_study(folder, cfg(None, ["tables_per_participant=9"]))
    with pytest.raises(DegustaError, match=r"tables: \[7\] are not tables"):
        open_study(folder, cfg(None, ["tables=[0, 7]", "tables_per_participant=1"]))
    with pytest.raises(DegustaError, match="min_objects: 2 is below the dataset's minimum of 3"):
        open_study(folder, cfg(None, ["min_objects=2"]))
    with pytest.raises(DegustaError, match="table_order"):
        cfg(None, ["table_order=shuffled"])
    with pytest.raises(DegustaError, match="colour"):
        cfg(None, ["colour=red"])
    with pytest.raises(DegustaError, match="instructions_file: cannot read"):
        cfg(None, [f"instructions_file={tmp_path / 'missing.txt'}"])
    with pytest.raises(DegustaError, match="--new needs a new or empty folder"):
        new_study_folder(folder)
    with pytest.raises(DegustaError, match="study folder not found"):
        open_study(tmp_path / "nowhere", cfg())
    synthetic = tmp_path / "synthetic"
    new_study_folder(synthetic)
    (synthetic / "meta.json").write_text(json.dumps({"synthetic": True}))
    with pytest.raises(DegustaError, match="synthetic: true"):
        open_study(synthetic, cfg())


def test_the_cli_refuses_a_missing_folder_in_one_line(tmp_path, capsys):
    assert main(["collect", "--dataset", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "study folder not found" in err and "--new" in err


def test_collected_data_round_trips_through_predict_and_evaluate(folder, tmp_path, capsys):
    """Three participants, three tables each: consensus predicts them, evaluate scores them and its tolerance
    curve comes from the collected ratings, not the paper's."""
    app = _app(folder, "tables_per_participant=3")
    for k in range(3):
        with TestClient(app) as c:
            state = c.post("/api/session", json={}).json()
            while state["stage"] != "done":
                state = _finish_table(c, state, _plates(c, 3 + (state["trial"] + k) % 3, x0=0.25 + 0.05 * k),
                                      ratings=(90, 90 - 10 * k, 85), tag=str(k))
    preds = tmp_path / "consensus.jsonl"
    assert main(["predict", "--config", "baseline_consensus", "--set", f"dataset={folder}", "--set", "split=all",
                 "--set", "context=2", "--set", f"out={preds}"]) == 0
    assert main(["evaluate", "--dataset", str(folder), "--predictions", str(preds), "--out",
                 str(tmp_path / "eval")]) == 0
    report = (tmp_path / "eval" / "report.md").read_text()
    assert "from this dataset's ratings" in report and "SYNTHETIC" not in report
    assert len(load_dataset(folder).ratings) == 9
