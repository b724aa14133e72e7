"""`degusta collect` speed and integrity: the page in a headless browser, the server over HTTP, 20 participants at once.

    python benchmarks/bench_collect.py                     # everything, printed as a markdown table
    python benchmarks/bench_collect.py --participants 50 --trials 5
    python benchmarks/bench_collect.py --no-browser        # the HTTP parts only (no Chromium needed)

The study server runs in a subprocess of this script (uvicorn, 127.0.0.1, a free port) on a fresh study folder in a
temporary directory (the embedded default's catalog and tables, `--trials` tables per participant, the
self-evaluation on), so the clients' threads and the browser driver do not share its interpreter.

- Page load (headless Chromium, Playwright): from navigation start to the participant's table drawn (the page's
  `degusta:ready` User Timing mark) and to every picture it asked for received (Resource Timing), median over
  `--repeats` loads in fresh browser contexts (no browser cache; the server's pictures already made) and over
  reloads (browser cache warm). The first load after the server starts (it draws its pictures then) is its own row.
- Interaction latency in the page: from the pointer event's timestamp to the frame after the object is drawn
  (requestAnimationFrame, then a task): a click on the table placing a chosen object, and one pointer move of a
  drag moving a placed object.
- Server latency (httpx, one client, sequential): POST /api/submit per kind of step and PUT /api/draft.
- Concurrency: `--participants` simulated participants (httpx clients in threads, each with its own session
  cookie) take a whole session at once: drafts, every submission, and every arrangement submitted twice with the
  same submission id (a double click: the second must be answered `replayed` and write nothing). Afterwards every
  line of arrangements.jsonl, ratings.jsonl and collect/self_evaluation.jsonl is counted against the submissions
  made: nothing lost, nothing doubled, and the folder loads with `degusta_learn.scene.load_dataset`. Bounded: every
  request has a timeout and the whole run `--deadline` seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from concurrent.futures import ThreadPoolExecutor, wait
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402

TIMEOUT = httpx.Timeout(30.0, connect=5.0)


# ------------------------------------------------------------------------------------------------ the server process

def serve_forever(folder: Path, trials: int, port_file: Path) -> None:
    """The subprocess: serve the study folder and write the port to `port_file`."""
    import uvicorn

    from degusta_learn.collect import load_study_config, open_study
    from degusta_learn.collect.server import create_app

    study = open_study(folder, load_study_config(None, [f"tables_per_participant={trials}"]))
    server = uvicorn.Server(uvicorn.Config(create_app(study, "bench-researcher-key"), host="127.0.0.1", port=0,
                                           log_level="warning", limit_concurrency=200))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        if not thread.is_alive():
            raise SystemExit("bench_collect: the server did not start")
        time.sleep(0.02)
    tmp = port_file.with_suffix(".tmp")
    tmp.write_text(str(server.servers[0].sockets[0].getsockname()[1]))
    tmp.replace(port_file)
    thread.join()


class ServerProcess:
    def __init__(self, folder: Path, trials: int):
        self.port_file = folder.parent / "port"
        self.proc = subprocess.Popen([sys.executable, __file__, "--serve", str(folder), "--trials", str(trials),
                                      "--port-file", str(self.port_file)], cwd=str(REPO))
        deadline = time.monotonic() + 60
        while not self.port_file.exists():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise SystemExit("bench_collect: the study server did not start")
            time.sleep(0.05)
        self.url = f"http://127.0.0.1:{int(self.port_file.read_text())}"

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)


# ------------------------------------------------------------------------------------------------ numbers

def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q * (len(s) - 1))))]


def ms(values: list[float]) -> str:
    if not values:
        return "-"
    return f"{statistics.median(values):.1f} / {pct(values, 0.95):.1f}"


# ------------------------------------------------------------------------------------------------ a participant over HTTP

def inside(poly: list[list[float]], x: float, y: float) -> bool:
    """Even-odd rule (scene.Table.contains)."""
    hit = False
    for (xa, ya), (xb, yb) in zip(poly, poly[1:] + poly[:1]):
        if (ya > y) != (yb > y) and x < xa + (y - ya) * (xb - xa) / (yb - ya):
            hit = not hit
    return hit


def a_setting(study: dict, table_id: int, k: int) -> list[dict]:
    """A plate, fork, knife (and spoon, cup) on the table's surface; objects chosen by `k`."""
    table = next(t for t in study["tables"] if t["id"] == table_id)
    xs, ys = [p[0] for p in table["surface"]], [p[1] for p in table["surface"]]
    cx, cy = (min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2
    by_type: dict[str, list[int]] = {}
    for o in study["objects"]:
        by_type.setdefault(o["type"], []).append(o["id"])
    layout = [("plate", 0, 0, 0), ("fork", -0.13, 0, 0), ("knife", 0.13, 0, 0), ("spoon", 0.17, 0, 0),
              ("cup", 0.15, -0.14, 0)][: 3 + k % 3]
    out = []
    for type_, dx, dy, r in layout:
        ids = by_type[type_]
        x, y = cx + dx, cy + dy
        if not inside(table["surface"], x, y):
            x, y = cx + dx / 3, cy
        out.append({"object": ids[k % len(ids)], "x": round(x, 4), "y": round(y, 4), "rotation": r})
    return out


class Participant:
    """One simulated participant: an httpx client holding its own session cookie."""

    def __init__(self, url: str, study: dict, k: int, timings: dict | None = None, replay: bool = False):
        self.client = httpx.Client(base_url=url, timeout=TIMEOUT)
        self.study, self.k, self.timings, self.replay = study, k, timings, replay
        self.made = Counter()       # submissions answered 200 and not replayed, by stage
        self.replays = 0            # second sends answered replayed
        self.wrong_replays = 0      # second sends not answered replayed

    def _timed(self, kind: str, method: str, path: str, body: dict) -> httpx.Response:
        t = time.perf_counter()
        r = self.client.request(method, path, json=body)
        if self.timings is not None:
            self.timings.setdefault(kind, []).append((time.perf_counter() - t) * 1000)
        if r.status_code != 200:
            raise RuntimeError(f"{method} {path} {json.dumps(body)[:200]} -> {r.status_code} {r.text[:300]}")
        return r

    def session(self) -> dict:
        r = self.client.post("/api/session", json={})
        r.raise_for_status()
        return r.json()

    def run(self) -> str:
        st = self.session()
        initial = None
        while st["stage"] != "done":
            stage, trial = st["stage"], st["trial"]
            if stage == "arrange":
                setting = a_setting(self.study, st["table"], self.k + trial)
                for n in range(1, len(setting) + 1):  # a draft after each object, as the page saves them
                    self._timed("draft", "PUT", "/api/draft", {"trial": trial, "stage": stage,
                                                                "placements": setting[:n]})
                initial = setting
                body = {"submission": str(uuid.uuid4()), "trial": trial, "stage": stage, "placements": setting}
            elif stage == "correct":
                corrected = [dict(p) for p in initial]  # put right: back where they were (all on the surface)
                self._timed("draft", "PUT", "/api/draft", {"trial": trial, "stage": stage, "placements": corrected})
                body = {"submission": str(uuid.uuid4()), "trial": trial, "stage": stage, "placements": corrected}
            else:
                body = {"submission": str(uuid.uuid4()), "trial": trial, "stage": stage,
                        "rating": float((self.k * 7 + trial * 13 + len(stage)) % 101)}
            kind = "rate" if stage.startswith("rate_") else stage
            r = self._timed(kind, "POST", "/api/submit", body)
            nxt = r.json()
            if nxt["replayed"]:
                raise RuntimeError(f"a fresh submission was answered replayed: {body}")
            self.made[stage] += 1
            if self.replay and stage == "arrange":  # the same click sent twice
                again = self.client.post("/api/submit", json=body)
                if again.status_code == 200 and again.json().get("replayed"):
                    self.replays += 1
                else:
                    self.wrong_replays += 1
            st = nxt
        self.client.close()
        return st["participant"]


# ------------------------------------------------------------------------------------------------ the browser parts

def chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return "/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None


LOAD_TIMES = """() => {
  const ready = performance.getEntriesByName('degusta:ready')[0];
  const pics = performance.getEntriesByType('resource').filter(e => e.name.includes('/img/'));
  return [ready ? ready.startTime : null, pics.length ? Math.max(...pics.map(e => e.responseEnd)) : null, pics.length];
}"""

PROBE = """() => {
  window.__lat = {place: [], move: []};
  let down = null, move = null;
  const svg = document.getElementById('table-svg');
  const after = (t0, list) => requestAnimationFrame(() => setTimeout(() => list.push(performance.now() - t0), 0));
  svg.addEventListener('pointerdown', e => { down = e.timeStamp; move = null; }, true);
  svg.addEventListener('pointermove', e => { move = e.timeStamp; }, true);
  new MutationObserver(records => {
    for (const r of records) {
      if (r.type === 'childList' && r.addedNodes.length && down !== null) { after(down, window.__lat.place); down = null; }
      if (r.type === 'attributes' && r.attributeName === 'transform' && move !== null) {
        after(move, window.__lat.move); move = null; }
    }
  }).observe(document.getElementById('objects-layer'), {childList: true, subtree: true, attributes: true,
                                                         attributeFilter: ['transform']});
}"""


def wait_ready(page) -> None:
    page.wait_for_function("() => performance.getEntriesByName('degusta:ready').length > 0")
    page.wait_for_load_state("networkidle")


def browser_part(url: str, repeats: int, placements: int) -> dict:
    from playwright.sync_api import sync_playwright

    exe = chromium()
    if exe is None:
        raise SystemExit("bench_collect: Chromium is not installed (apt-get install chromium), or pass --no-browser")
    # a session made over HTTP: the browser's first load is the server's first drawing of the table and palette
    r = httpx.post(url + "/api/session", json={}, timeout=TIMEOUT)
    r.raise_for_status()
    cookie = {"name": "degusta_session", "value": r.cookies["degusta_session"], "url": url}
    viewport = {"width": 1280, "height": 800}
    out: dict = {"fresh_ready": [], "fresh_pics": [], "reload_ready": [], "reload_pics": []}
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=exe, headless=True)

        def fresh_page():
            ctx = browser.new_context(viewport=viewport)
            ctx.add_cookies([cookie])
            page = ctx.new_page()
            page.set_default_timeout(30_000)
            page.goto(url + "/")
            wait_ready(page)
            assert page.evaluate("document.body.dataset.stage") == "arrange"
            return ctx, page

        ctx, page = fresh_page()
        out["first"] = page.evaluate(LOAD_TIMES)
        ctx.close()
        for _ in range(repeats):
            ctx, page = fresh_page()
            ready, pics, _n = page.evaluate(LOAD_TIMES)
            out["fresh_ready"].append(ready)
            out["fresh_pics"].append(pics)
            ctx.close()
        ctx, page = fresh_page()
        for _ in range(repeats):
            page.reload()
            wait_ready(page)
            ready, pics, _n = page.evaluate(LOAD_TIMES)
            out["reload_ready"].append(ready)
            out["reload_pics"].append(pics if pics is not None else ready)  # every picture from the memory cache
        # interaction latency: place (click), drag a little (one sample per pointer move), undo both
        page.evaluate(PROBE)
        box = page.locator("#table-svg").bounding_box()
        types = [b.get_attribute("data-type") for b in page.locator("#types .type-button").all()]
        for i in range(placements):
            page.click(f"#types [data-type='{types[i % len(types)]}']")
            page.locator("#objects .object-button").nth(i % 10).click()
            x = box["x"] + box["width"] * (0.35 + 0.3 * ((i * 7) % 10) / 10)
            y = box["y"] + box["height"] * (0.4 + 0.2 * ((i * 3) % 10) / 10)
            page.mouse.click(x, y)
            page.wait_for_function("(n) => window.__lat.place.length >= n", arg=i + 1)
            page.mouse.down()
            for step in range(1, 6):
                page.mouse.move(x + 4 * step, y + 3 * step)
            page.mouse.up()
            page.keyboard.press("Control+z")
            page.keyboard.press("Control+z")
            page.wait_for_function("() => document.querySelectorAll('#objects-layer g.placed').length === 0")
        page.wait_for_timeout(100)
        lat = page.evaluate("() => window.__lat")
        out["place"], out["move"] = lat["place"], lat["move"]
        ctx.close()
        browser.close()
    return out


# ------------------------------------------------------------------------------------------------ the whole run

def count_lines(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def run(args) -> int:
    rows: list[tuple[str, str]] = []
    with tempfile.TemporaryDirectory() as tmp:
        from degusta_learn.collect import new_study_folder

        folder = new_study_folder(Path(tmp) / "study")
        server = ServerProcess(folder, args.trials)
        try:
            study = httpx.get(server.url + "/api/study", timeout=TIMEOUT).json()
            if not args.no_browser:
                b = browser_part(server.url, args.repeats, args.placements)
                first_ready, first_pics, _n = b["first"]
                rows += [
                    ("page load, first after server start (drawn / all pictures), ms",
                     f"{first_ready:.0f} / {first_pics:.0f}"),
                    (f"page load, fresh browser context (drawn / all pictures), median of {args.repeats}, ms",
                     f"{statistics.median(b['fresh_ready']):.0f} / {statistics.median(b['fresh_pics']):.0f}"),
                    (f"page reload, browser cache warm (drawn / all pictures), median of {args.repeats}, ms",
                     f"{statistics.median(b['reload_ready']):.0f} / {statistics.median(b['reload_pics']):.0f}"),
                    (f"click on the table -> object drawn, median / p95 of {len(b['place'])}, ms", ms(b["place"])),
                    (f"drag: pointer move -> object drawn, median / p95 of {len(b['move'])}, ms", ms(b["move"])),
                ]
            # server latency, one client after the other
            timings: dict[str, list[float]] = {}
            for k in range(args.sequential):
                Participant(server.url, study, 1000 + k, timings).run()
            for kind in ("arrange", "rate", "correct", "draft"):
                what = "PUT /api/draft" if kind == "draft" else f"POST /api/submit ({kind})"
                rows.append((f"{what}, one client, median / p95 of {len(timings[kind])}, ms", ms(timings[kind])))
            before = {name: len(count_lines(p)) for name, p in (
                ("arrangements", folder / "arrangements.jsonl"), ("ratings", folder / "ratings.jsonl"),
                ("selfeval", folder / "collect" / "self_evaluation.jsonl"))}
            # many at once
            load: dict[str, list[float]] = {}
            people = [Participant(server.url, study, k, load, replay=True) for k in range(args.participants)]
            lock = threading.Lock()
            done_ids: list[str] = []

            def one(p: Participant) -> None:
                pid = p.run()
                with lock:
                    done_ids.append(pid)

            t = time.perf_counter()
            with ThreadPoolExecutor(args.participants) as pool:
                futures = [pool.submit(one, p) for p in people]
                finished, pending = wait(futures, timeout=args.deadline)
                wall = time.perf_counter() - t
                for f in pending:
                    f.cancel()
                failures = [f.exception() for f in finished if f.exception() is not None]
            if pending or failures:
                print(f"bench_collect: {len(pending)} participants unfinished after {args.deadline} s, "
                      f"{len(failures)} failed: {failures[:1]}", file=sys.stderr)
                return 1
            made = sum((p.made for p in people), Counter())
            replays = sum(p.replays for p in people)
            wrong = sum(p.wrong_replays for p in people)
            arrangements = count_lines(folder / "arrangements.jsonl")[before["arrangements"]:]
            ratings = count_lines(folder / "ratings.jsonl")[before["ratings"]:]
            selfeval = count_lines(folder / "collect" / "self_evaluation.jsonl")[before["selfeval"]:]
            keys = Counter((a["participant"], a["trial"]) for a in arrangements)
            rkeys = Counter((r["participant"], r["trial"]) for r in ratings)
            expected = args.participants * args.trials
            doubled = sum(n - 1 for n in keys.values() if n > 1) + sum(n - 1 for n in rkeys.values() if n > 1)
            lost = (expected - len(keys)) + (expected - len(rkeys))
            ok = (len(arrangements) == made["arrange"] == expected and len(ratings) == made["rate_correct"] == expected
                  and len(selfeval) == expected and doubled == 0 and lost == 0 and wrong == 0
                  and replays == made["arrange"] and set(done_ids) == {a["participant"] for a in arrangements})
            submissions = sum(made.values())
            requests = submissions + replays + sum(len(v) for k, v in load.items() if k == "draft") + len(people)
            rows += [
                (f"{args.participants} participants at once, {args.trials} tables each: wall time, s", f"{wall:.2f}"),
                ("  submissions made (+ replays sent) / requests in all", f"{submissions} (+{replays}) / {requests}"),
                ("  POST /api/submit under that load, median / p95, ms",
                 ms(load["arrange"] + load["rate"] + load["correct"])),
                ("  lines written: arrangements / ratings / self_evaluation (expected each)",
                 f"{len(arrangements)} / {len(ratings)} / {len(selfeval)} ({expected})"),
                ("  lost / doubled / replays not recognized", f"{lost} / {doubled} / {wrong}"),
            ]
        finally:
            server.stop()
        from degusta_learn.scene import load_dataset

        ds = load_dataset(folder)
        rows.append(("the folder loads as a dataset (arrangements / ratings)",
                     f"{len(ds.arrangements)} / {len(ds.ratings)}"))
    print(f"degusta collect ({platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"Python {platform.python_version()}; server in a subprocess)\n")
    print("| measure | value |")
    print("|---|---|")
    for name, value in rows:
        print(f"| {name} | {value} |")
    print(f"\nintegrity: {'OK' if ok else 'FAILED'}")
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--participants", type=int, default=20)
    ap.add_argument("--trials", type=int, default=5, help="tables per participant (at most 5: the default tables)")
    ap.add_argument("--sequential", type=int, default=6, help="participants run one after the other for latency")
    ap.add_argument("--repeats", type=int, default=5, help="page loads measured")
    ap.add_argument("--placements", type=int, default=20, help="placements (and drags) measured in the page")
    ap.add_argument("--deadline", type=float, default=300.0, help="seconds the concurrent run may take")
    ap.add_argument("--no-browser", action="store_true")
    ap.add_argument("--serve", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--port-file", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.serve:
        serve_forever(args.serve, args.trials, args.port_file)
        return 0
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
