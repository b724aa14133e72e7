"""Screenshots of `degusta collect`'s participant page, one per stage, taken with the real interface.

    python benchmarks/collect_screenshots.py                    # docs/images/collect_*.png, 1280 x 800
    python benchmarks/collect_screenshots.py --out /tmp/shots --width 1440 --height 900

A fresh study folder (the embedded default's catalog and tables, in a temporary folder) is served on 127.0.0.1 and a
scripted participant, in headless Chromium (Playwright), sets one table the way a Western place setting goes (a blue
plate, fork, knife, spoon and cup) with the mouse, rates it, rates the jittered copy, puts the copy right by dragging
and rates it again. Written: collect_start.png (the instructions), collect_arrange.png (objects placed, the fork
palette open, the knife selected), collect_rate.png, collect_jitter.png, collect_correct.png (the cup dragged
back and turned straight), collect_done.png. Needs Chromium (apt-get install chromium) and Playwright (pip install playwright).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from degusta_learn.collect import load_study_config, new_study_folder, open_study  # noqa: E402
from degusta_learn.collect.server import create_app  # noqa: E402

# A Western place setting on table 0 (the oak rectangle): (type, x, y, rotation).
SETTING = [("plate", 0.5, 0.56, 0), ("fork", 0.37, 0.56, 0), ("knife", 0.63, 0.56, 0), ("spoon", 0.68, 0.56, 0),
           ("cup", 0.665, 0.37, 0)]
COLOUR = "blue"


def chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    if Path("/usr/bin/chromium").exists():
        return "/usr/bin/chromium"
    raise SystemExit("collect_screenshots: Chromium is not installed (apt-get install chromium)")


class Served:
    def __init__(self, root: Path, overrides: list[str]):
        import uvicorn

        self.server = uvicorn.Server(uvicorn.Config(create_app(open_study(root, load_study_config(None, overrides)),
                                                               "screenshots-key"),
                                                    host="127.0.0.1", port=0, log_level="warning"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise SystemExit("collect_screenshots: the study server did not start")
            time.sleep(0.02)
        self.url = f"http://127.0.0.1:{self.server.servers[0].sockets[0].getsockname()[1]}/"

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10)


def wait_stage(page, stage: str) -> None:
    page.wait_for_function("(s) => document.body.dataset.stage === s", arg=stage)


def settle(page) -> None:
    """Every picture loaded, the draft saved, no animation frame pending."""
    page.wait_for_load_state("networkidle")
    page.wait_for_function("() => Array.from(document.images).every(i => i.complete) && "
                           "Array.from(document.querySelectorAll('svg image')).length >= 1")
    page.wait_for_timeout(400)


def point(page, x: float, y: float) -> tuple[float, float]:
    box = page.locator("#table-svg").bounding_box()
    return box["x"] + x * box["width"], box["y"] + y * box["height"]


def pick(study: dict, type_: str) -> int:
    """The index in the palette of the first object of `type_` whose label names COLOUR (else the first)."""
    objs = [o for o in study["objects"] if o["type"] == type_]
    for i, o in enumerate(objs):
        if o["label"].startswith(COLOUR + " "):
            return i
    return 0


def placed(page) -> dict[int, tuple[float, float]]:
    return {int(k): (x, y) for k, x, y in page.evaluate(
        "Array.from(document.querySelectorAll('#objects-layer g.placed')).map(g => "
        "[g.dataset.object, +g.dataset.x, +g.dataset.y])")}


def drag(page, frm: tuple[float, float], to: tuple[float, float]) -> None:
    page.mouse.move(*point(page, *frm))
    page.mouse.down()
    page.mouse.move(*point(page, *to), steps=10)
    page.mouse.up()


def take(out: Path, width: int, height: int) -> list[Path]:
    from playwright.sync_api import sync_playwright

    out.mkdir(parents=True, exist_ok=True)
    written = []
    with tempfile.TemporaryDirectory() as tmp:
        root = new_study_folder(Path(tmp) / "study")
        served = Served(root, ["tables=[0]", "tables_per_participant=1", "table_order=fixed"])
        try:
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=chromium(), headless=True)
                page = browser.new_page(viewport={"width": width, "height": height}, device_scale_factor=1)
                page.set_default_timeout(15_000)

                def shot(name: str) -> None:
                    settle(page)
                    path = out / f"collect_{name}.png"
                    page.screenshot(path=str(path))
                    written.append(path)

                page.goto(served.url)
                wait_stage(page, "start")
                shot("start")
                page.click("#start-button")
                wait_stage(page, "arrange")
                study = page.evaluate("fetch('/api/study').then(r => r.json())")
                ids = []
                for i, (type_, x, y, r) in enumerate(SETTING):
                    page.click(f"#types [data-type='{type_}']")
                    button = page.locator("#objects .object-button").nth(pick(study, type_))
                    ids.append(int(button.get_attribute("data-object")))
                    if i % 2:  # every other one dragged from the palette
                        b = button.bounding_box()
                        page.mouse.move(b["x"] + b["width"] / 2, b["y"] + b["height"] / 2)
                        page.mouse.down()
                        page.mouse.move(*point(page, x, y), steps=10)
                        page.mouse.up()
                    else:
                        button.click()
                        page.mouse.click(*point(page, x, y))
                    page.wait_for_function("(n) => document.querySelectorAll('#objects-layer g.placed').length === n",
                                           arg=i + 1)
                    if r:
                        page.fill("#rotation-number", str(r))
                page.click("#types [data-type='fork']")
                page.mouse.click(*point(page, SETTING[2][1], SETTING[2][2]))  # select the knife
                page.mouse.move(*point(page, 0.9, 0.95))
                shot("arrange")
                page.click("#submit")
                wait_stage(page, "rate_initial")
                page.fill("#rating", "86")
                shot("rate")
                page.click("#submit")
                wait_stage(page, "rate_jitter")
                page.fill("#rating", "41")
                shot("jitter")
                page.click("#submit")
                wait_stage(page, "correct")
                cup = ids[4]  # the cup put back and turned straight; the rest still as jittered
                drag(page, placed(page)[cup], (SETTING[4][1], SETTING[4][2]))
                page.fill("#rotation-number", str(SETTING[4][3]))
                page.evaluate("document.activeElement.blur()")
                page.mouse.move(*point(page, 0.9, 0.95))
                shot("correct")
                for oid, (_, x, y, _r) in zip(ids[1:], SETTING[1:]):
                    drag(page, placed(page)[oid], (x, y))
                for oid, (_, _x, _y, r) in zip(ids, SETTING):
                    px, py = placed(page)[oid]
                    page.mouse.click(*point(page, px, py))
                    page.fill("#rotation-number", str(r))
                page.click("#submit")
                wait_stage(page, "rate_correct")
                page.fill("#rating", "80")
                page.click("#submit")
                wait_stage(page, "done")
                shot("done")
                other = browser.new_page(viewport={"width": width, "height": height})  # a second participant, halfway
                other.goto(served.url)
                other.click("#start-button")
                other.wait_for_function("document.body.dataset.stage === 'arrange'")
                other.goto(served.url + "research?key=screenshots-key")
                other.screenshot(path=str(out / "collect_progress.png"))  # a plain page: no app.js to settle
                written.append(out / "collect_progress.png")
                browser.close()
        finally:
            served.stop()
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "images")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=800)
    args = ap.parse_args(argv)
    for path in take(args.out, args.width, args.height):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
