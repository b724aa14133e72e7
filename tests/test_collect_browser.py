"""`degusta collect`'s participant page in a real browser: headless Chromium (Debian's) driven by Playwright against
the real server (uvicorn in a thread on 127.0.0.1) on a fresh study folder.

A scripted participant sets every table with the mouse (a click on a type icon, an object, the table; a drag from
the palette; a drag of a placed object), turns one, submits, rates, rates the jittered copy, corrects it by
dragging and rates again, and the folder then loads as a dataset and passes `degusta data validate`. A refresh and a
server restart resume the table in progress; two participants in two browser contexts never see each other's data;
markup in a participant id or in the instructions is shown as text and never runs; Submit stays disabled below the
minimum or with an object off the surface.

Needs Chromium and Playwright; without them these tests fail (they never skip) with how to install them."""

from __future__ import annotations

import json
import math
import shutil
import threading
import time
from pathlib import Path

import pytest

from degusta_learn.cli import main
from degusta_learn.collect import load_study_config, new_study_folder, open_study
from degusta_learn.collect.server import create_app
from degusta_learn.scene import load_dataset

TIMEOUT_MS = 10_000
CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome")
INSTALL = 'install them with: apt-get install chromium; pip install -e ".[dev]" (Playwright, the driver)'


def chromium_path() -> str:
    for name in CHROMIUM_CANDIDATES:
        found = shutil.which(name)
        if found:
            return found
    for path in ("/usr/bin/chromium", "/usr/lib/chromium/chromium"):
        if Path(path).exists():
            return path
    pytest.fail(f"the browser tests need Chromium, which is not installed: {INSTALL}", pytrace=False)


@pytest.fixture(scope="module")
def browser():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        sync_playwright = None
    if sync_playwright is None:  # (outside the except: one line, no chained traceback)
        pytest.fail(f"the browser tests need Playwright, which is not installed: {INSTALL}", pytrace=False)
    path = chromium_path()
    with sync_playwright() as pw:
        try:
            b = pw.chromium.launch(executable_path=path, headless=True, args=["--no-sandbox"])
        except Exception as e:  # noqa: BLE001 - one line: which browser, why
            problem = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
            b = None
        if b is None:
            pytest.fail(f"cannot start Chromium at {path} ({problem}): {INSTALL}", pytrace=False)
        yield b
        b.close()


class Served:
    """The study app of `root` served by uvicorn on 127.0.0.1 (a free port) in a background thread."""

    def __init__(self, root: Path, overrides: list[str]):
        import uvicorn

        study = open_study(root, load_study_config(None, overrides))
        self.app = create_app(study, "researcher-key-for-tests")
        self.server = uvicorn.Server(uvicorn.Config(self.app, host="127.0.0.1", port=0, log_level="warning"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 20
        while not self.server.started:
            assert time.monotonic() < deadline and self.thread.is_alive(), "the study server did not start"
            time.sleep(0.02)
        self.port = self.server.servers[0].sockets[0].getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}/"

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10)
        assert not self.thread.is_alive(), "the study server did not stop"


TWO_TABLES = ["tables_per_participant=2", "table_order=fixed", "tables=[1, 4]"]


@pytest.fixture
def study(tmp_path):
    """A fresh study folder (the embedded default's catalog and tables) and its server; stopped afterwards."""
    made = []

    def start(overrides=TWO_TABLES, root=None):
        root = root or new_study_folder(tmp_path / "study")
        s = Served(root, list(overrides))
        s.root = root
        made.append(s)
        return s

    yield start
    for s in made:
        if s.thread.is_alive():
            s.stop()


class Participant:
    """One browser page of the study, with the moves a participant makes."""

    def __init__(self, page, url: str):
        self.page = page
        self.url = url
        self.dialogs: list[str] = []
        self.errors: list[str] = []
        page.set_default_timeout(TIMEOUT_MS)
        page.on("dialog", lambda d: (self.dialogs.append(d.message), d.dismiss()))
        page.on("pageerror", lambda e: self.errors.append(str(e)))
        # a script, style or picture the Content-Security-Policy refused is a console error too
        page.on("console", lambda m: self.errors.append(m.text) if "Content Security Policy" in m.text else None)

    def open(self) -> None:
        self.page.goto(self.url)
        # (a function, not an expression string: the page's Content-Security-Policy forbids eval)
        self.page.wait_for_function("() => ['start', 'arrange', 'rate_initial', 'rate_jitter', 'correct',"
                                    " 'rate_correct', 'done'].includes(document.body.dataset.stage)")

    def start(self, participant: str | None = None) -> None:
        self.open()
        assert self.stage() == "start"
        if participant is not None:
            self.page.fill("#pid", participant)
        self.page.click("#start-button")
        self.wait_stage("arrange")

    def stage(self) -> str:
        return self.page.evaluate("document.body.dataset.stage")

    def wait_stage(self, stage: str, trial: int | None = None) -> None:
        self.page.wait_for_function("([stage, trial]) => document.body.dataset.stage === stage && (trial === null"
                                    " || document.body.dataset.trial === String(trial))", arg=[stage, trial])

    def table_point(self, x: float, y: float) -> tuple[float, float]:
        box = self.page.locator("#table-svg").bounding_box()
        return box["x"] + x * box["width"], box["y"] + y * box["height"]

    def choose(self, type_: str, index: int = 0) -> int:
        """Click a type icon, then its `index`-th object; returns the object id."""
        self.page.click(f"#types [data-type='{type_}']")
        button = self.page.locator("#objects .object-button").nth(index)
        object_id = int(button.get_attribute("data-object"))
        button.click()
        assert button.get_attribute("aria-pressed") == "true"
        return object_id

    def placed(self) -> dict[int, tuple[float, float, float]]:
        """{object: (x, y, rotation)} of what the table shows, in drawing order (= placement order)."""
        return {int(k): tuple(v) for k, v in self.page.evaluate(
            "Array.from(document.querySelectorAll('#objects-layer g.placed')).map(g =>"
            " [g.dataset.object, [+g.dataset.x, +g.dataset.y, +g.dataset.rotation]])")}

    def count(self) -> int:
        return len(self.placed())

    def wait_count(self, n: int) -> None:
        self.page.wait_for_function("(n) => document.querySelectorAll('#objects-layer g.placed').length === n", arg=n)

    def click_place(self, type_: str, x: float, y: float, index: int = 0) -> int:
        n = self.count()
        object_id = self.choose(type_, index)
        self.page.mouse.click(*self.table_point(x, y))
        self.wait_count(n + 1)
        return object_id

    def drag_place(self, type_: str, x: float, y: float, index: int = 0) -> int:
        """Drag an object from the palette onto the table (without clicking it first)."""
        n = self.count()
        self.page.click(f"#types [data-type='{type_}']")
        button = self.page.locator("#objects .object-button").nth(index)
        object_id = int(button.get_attribute("data-object"))
        b = button.bounding_box()
        self.page.mouse.move(b["x"] + b["width"] / 2, b["y"] + b["height"] / 2)
        self.page.mouse.down()
        tx, ty = self.table_point(x, y)
        self.page.mouse.move(tx, ty, steps=12)
        assert self.page.locator("#drag-ghost").is_visible()
        self.page.mouse.up()
        self.wait_count(n + 1)
        assert not self.page.locator("#drag-ghost").is_visible()
        return object_id

    def grabbed_at(self, x: float, y: float) -> int | None:
        px, py = self.table_point(x, y)
        got = self.page.evaluate("([x, y]) => { const e = document.elementFromPoint(x, y);"
                                 " const g = e && e.closest('g.placed'); return g ? +g.dataset.object : null; }",
                                 [px, py])
        return got

    def drag_to(self, object_id: int, x: float, y: float) -> None:
        """Press on a placed object's centre and drag it to (x, y)."""
        ox, oy, _ = self.placed()[object_id]
        assert self.grabbed_at(ox, oy) == object_id
        self.page.mouse.move(*self.table_point(ox, oy))
        self.page.mouse.down()
        self.page.mouse.move(*self.table_point(x, y), steps=8)
        self.page.mouse.up()
        nx, ny, _ = self.placed()[object_id]
        assert abs(nx - x) < 0.006 and abs(ny - y) < 0.006, (object_id, (nx, ny), (x, y))

    def select(self, object_id: int) -> None:
        x, y, _ = self.placed()[object_id]
        self.page.mouse.click(*self.table_point(x, y))
        assert self.page.locator(f"g.placed[data-object='{object_id}']").get_attribute("class").count("selected")

    def submit(self, stage_after: str, trial_after: int | None = None) -> None:
        submit = self.page.locator("#submit")
        assert submit.is_enabled()
        submit.click()
        self.wait_stage(stage_after, trial_after)

    def rate(self, value: int, stage_after: str, trial_after: int | None = None) -> None:
        assert self.page.locator("#submit").is_disabled()  # the slider must be moved first
        assert "not set" in self.page.inner_text("#rating-value")
        self.page.fill("#rating", str(value))
        assert self.page.inner_text("#rating-value").startswith(str(value))
        self.submit(stage_after, trial_after)

    def wait_saved(self) -> None:
        self.page.wait_for_function("() => document.getElementById('save-status').textContent === 'Draft saved'")


def new_participant(browser, url: str):
    context = browser.new_context(viewport={"width": 1280, "height": 860})
    return context, Participant(context.new_page(), url)


# Where the scripted participant sets things: inside the surface of every default table.
PLATE, FORK, KNIFE, KNIFE_MOVED = (0.5, 0.5), (0.36, 0.5), (0.62, 0.47), (0.64, 0.5)


def test_a_participant_sets_rates_and_corrects_every_table_and_the_folder_validates(browser, study, capsys):
    s = study()
    context, p = new_participant(browser, s.url)
    try:
        p.start()
        want, ratings = [], []
        for trial in range(2):
            p.wait_stage("arrange", trial)
            assert p.count() == 0 and p.page.locator("#submit").is_disabled()
            plate = p.click_place("plate", *PLATE, index=trial)
            fork = p.drag_place("fork", *FORK, index=trial)
            knife = p.click_place("knife", *KNIFE, index=trial)
            p.drag_to(knife, *KNIFE_MOVED)
            p.select(knife)
            p.page.click("#rotate-right")
            p.page.click("#rotate-right")
            p.page.keyboard.press("r")  # the selected object has the focus: R turns it 15 degrees more
            assert p.placed()[knife][2] == 45
            p.page.click("#rotate-left")
            p.page.fill("#rotation-number", "40")
            assert p.placed()[knife][2] == 40
            assert p.page.inner_text("#count") == "3 objects placed (at least 3)"
            initial = {plate: (*PLATE, 0.0), fork: (*FORK, 0.0), knife: (*KNIFE_MOVED, 40.0)}
            assert list(p.placed()) == [plate, fork, knife]  # placement order
            for oid, (x, y, r) in p.placed().items():
                assert math.isclose(x, initial[oid][0], abs_tol=0.006) and math.isclose(y, initial[oid][1], abs_tol=0.006)
                assert r == initial[oid][2]
            # the palette shows what is on the table as used
            p.page.click("#types [data-type='plate']")
            assert p.page.locator(f"#objects [data-object='{plate}']").is_disabled()
            p.submit("rate_initial", trial)
            # rating the participant's own arrangement: read-only, the same objects
            assert set(p.placed()) == set(initial)
            assert p.page.locator("#objects-layer g.placed[tabindex]").count() == 0
            b = [81 - trial, 40 + trial, 90 - trial]
            p.rate(b[0], "rate_jitter", trial)
            jittered = p.placed()
            assert set(jittered) == set(initial)
            p.rate(b[1], "correct", trial)
            # correcting: the jittered scene, editable; nothing can be added or removed
            assert p.placed() == jittered
            assert p.page.locator("#palette").is_hidden() and p.page.locator("#remove").is_hidden()
            remaining = list(initial)
            while remaining:  # drag each object back (one not covered by another first)
                oid = next((o for o in remaining if p.grabbed_at(*p.placed()[o][:2]) == o), None)
                assert oid is not None, "every jittered object is covered by another"
                p.drag_to(oid, *initial[oid][:2])
                p.page.fill("#rotation-number", str(int(initial[oid][2])))
                remaining.remove(oid)
            assert {k: v[2] for k, v in p.placed().items()} == {k: v[2] for k, v in initial.items()}
            p.submit("rate_correct", trial)
            p.rate(b[2], "arrange" if trial == 0 else "done", trial + 1)
            want.append(initial)
            ratings.append(b)
        assert "Thank you" in p.page.inner_text("#screen-done")
        assert not p.errors and not p.dialogs
    finally:
        context.close()
    s.stop()

    ds = load_dataset(s.root)
    arrangements = sorted(ds.arrangements, key=lambda a: a.trial)
    assert [(a.participant, a.trial, a.table) for a in arrangements] == [("c001", 0, 1), ("c001", 1, 4)]
    for a, initial in zip(arrangements, want):
        assert [q.object for q in a.placements] == list(initial)
        for q in a.placements:
            x, y, r = initial[q.object]
            assert abs(q.x - x) < 0.01 and abs(q.y - y) < 0.01 and q.rotation == r
    rows = sorted(ds.ratings, key=lambda r: r.trial)
    assert [(r.b_initial, r.b_jitter, r.b_correct) for r in rows] == [tuple(map(float, b)) for b in ratings]
    for r in rows:
        assert r.rmsd_jitter > r.rmsd_correct and r.rmsd_correct < 0.01  # put back where it was, within a pixel or so
    assert main(["data", "validate", str(s.root)]) == 0
    assert "valid" in capsys.readouterr().out


def test_a_refresh_and_a_server_restart_resume_the_table_in_progress(browser, study):
    s = study()
    context, p = new_participant(browser, s.url)
    try:
        p.start()
        plate = p.click_place("plate", 0.45, 0.55)
        cup = p.drag_place("cup", 0.6, 0.4)
        p.select(cup)
        p.page.click("#rotate-left")
        p.wait_saved()
        before = p.placed()
        assert before[cup][2] == 345
        p.page.reload()
        p.wait_stage("arrange", 0)
        assert p.placed() == before and list(p.placed()) == [plate, cup]
        p.page.click("#types [data-type='cup']")
        assert p.page.locator(f"#objects [data-object='{cup}']").is_disabled()
        assert p.page.inner_text("#count") == "2 objects placed (at least 3)"

        s.stop()  # the same folder under a new server (and a new port: the cookie is the host's)
        s2 = study(root=s.root)
        p.url = s2.url
        p.open()
        assert p.stage() == "arrange" and p.placed() == before
        knife = p.click_place("knife", 0.7, 0.55)
        p.submit("rate_initial", 0)
        p.page.reload()
        p.wait_stage("rate_initial", 0)
        assert list(p.placed()) == [plate, cup, knife]
        assert not p.errors
    finally:
        context.close()


def test_two_participants_in_two_browsers_never_see_or_change_each_others_data(browser, study):
    s = study()
    (c1, p1), (c2, p2) = new_participant(browser, s.url), new_participant(browser, s.url)
    try:
        p1.start()
        p2.start()
        assert p1.page.evaluate("fetch('/api/state').then(r => r.json())")["participant"] == "c001"
        assert p2.page.evaluate("fetch('/api/state').then(r => r.json())")["participant"] == "c002"
        mine = [p1.click_place("plate", 0.5, 0.5), p1.click_place("fork", 0.38, 0.5), p1.click_place("cup", 0.6, 0.38)]
        theirs = [p2.click_place("spoon", 0.4, 0.6, index=3)]
        p1.wait_saved()
        p2.wait_saved()
        for p in (p1, p2):
            p.page.reload()
            p.wait_stage("arrange", 0)
        assert list(p1.placed()) == mine and list(p2.placed()) == theirs
        p1.submit("rate_initial", 0)
        p2.page.reload()
        p2.wait_stage("arrange", 0)
        assert list(p2.placed()) == theirs
        p2.click_place("plate", 0.5, 0.45, index=5)
        p2.wait_saved()
        p1.page.reload()
        p1.wait_stage("rate_initial", 0)
        assert list(p1.placed()) == mine
        people = s.root / "collect" / "participants"
        drafts = {f.stem: json.loads(f.read_text()) for f in people.glob("*.json")}
        assert [q["object"] for q in drafts["c001"]["initial"]] == mine
        assert [q["object"] for q in drafts["c002"]["draft"]] == [*theirs, p2.placed().popitem()[0]]
        lines = (s.root / "arrangements.jsonl").read_text().splitlines()
        assert len(lines) == 1 and json.loads(lines[0])["participant"] == "c001"
        assert not p1.errors and not p2.errors
    finally:
        c1.close()
        c2.close()


def test_markup_from_the_study_or_a_participant_is_shown_as_text_and_never_runs(browser, study):
    instructions = ("Welcome <script>window.__ran = 1; alert('script')</script>\n\n"
                    "Second <img src=x onerror=\"window.__ran = 2; alert('img')\"> paragraph & <b>bold</b>")
    s = study([*TWO_TABLES, "participant_ids=enter", f"instructions={json.dumps(instructions)}",
               "title=<i>Lab</i> study"])
    context, p = new_participant(browser, s.url)
    try:
        p.open()
        assert p.stage() == "start"
        assert p.page.inner_text("#title") == "<i>Lab</i> study"
        paragraphs = p.page.locator("#instructions p")
        assert paragraphs.count() == 2
        assert paragraphs.nth(0).inner_text() == "Welcome <script>window.__ran = 1; alert('script')</script>"
        assert "<img src=x onerror=" in paragraphs.nth(1).inner_text()
        assert p.page.locator("#instructions script, #instructions img, #instructions b").count() == 0
        evil = "<img src=x onerror=alert(1)>"
        p.page.fill("#pid", evil)
        with p.page.expect_response("**/api/session") as answer:
            p.page.click("#start-button")
        assert answer.value.status == 400
        detail = answer.value.json()["detail"]
        p.page.wait_for_selector("#alert:not([hidden])")
        assert p.page.inner_text("#alert-text") == detail
        assert p.page.locator("#alert img, #main img[src='x']").count() == 0
        assert p.stage() == "start"
        p.page.fill("#pid", "lab-01")
        p.page.click("#start-button")
        p.wait_stage("arrange", 0)
        assert p.page.is_hidden("#alert")
        p.page.wait_for_timeout(100)
        assert p.page.evaluate("window.__ran") is None
        assert not p.dialogs and not p.errors
    finally:
        context.close()


def test_submit_stays_disabled_below_the_minimum_and_with_an_object_off_the_surface(browser, study):
    s = study()
    context, p = new_participant(browser, s.url)
    try:
        p.start()
        submit = p.page.locator("#submit")
        p.click_place("plate", 0.5, 0.5)
        p.click_place("fork", 0.38, 0.5)
        assert submit.is_disabled() and p.page.inner_text("#count") == "2 objects placed (at least 3)"
        assert "1 more" in p.page.inner_text("#validity")
        cup = p.click_place("cup", 0.03, 0.03)  # table 1 is round: its corner is off the surface
        assert submit.is_disabled() and "off the table" in p.page.inner_text("#validity")
        assert "off" in p.page.locator(f"g.placed[data-object='{cup}']").get_attribute("class")
        p.drag_to(cup, 0.62, 0.4)
        assert submit.is_enabled() and p.page.inner_text("#count") == "3 objects placed (at least 3)"
        p.page.keyboard.press("Delete")  # the cup is selected and has the focus
        assert p.count() == 2 and submit.is_disabled()
        p.page.keyboard.press("Control+z")
        assert p.count() == 3 and submit.is_enabled()
        p.page.click("#undo")  # back before the drag: off the surface again
        assert max(abs(v - 0.03) for v in p.placed()[cup][:2]) < 0.006 and submit.is_disabled()
        # the keyboard alone: choose, put in the middle, nudge
        p.page.keyboard.press("Control+z")
        p.page.keyboard.press("Control+z")
        assert p.count() == 1 and submit.is_disabled()
        p.page.click("#types [data-type='knife']")
        p.page.locator("#objects .object-button").first.focus()
        p.page.keyboard.press("Enter")
        p.page.focus("#table-svg")
        p.page.keyboard.press("Enter")
        assert p.count() == 2
        x0, y0, _ = p.placed()[int(p.page.locator("#objects-layer g.placed").last.get_attribute("data-object"))]
        p.page.keyboard.press("Shift+ArrowRight")
        knife = int(p.page.locator("#objects-layer g.placed").last.get_attribute("data-object"))
        assert math.isclose(p.placed()[knife][0], x0 + 0.02, abs_tol=1e-3) and p.placed()[knife][1] == y0
        assert submit.is_disabled()
        assert not p.errors
    finally:
        context.close()
