"""Planning latency and throughput: `Planner.plan` in-process and `POST /plan` over loopback HTTP, per method.

For each method: one planner (loaded once; its first plan, which loads models and warms caches, is timed apart), 200
requests built from the test episodes of the SYNTHETIC naturalistic default (context 4: a participant, their four
context trials, the target's table), timed one at a time in-process and over HTTP (uvicorn in a thread on
127.0.0.1, one httpx client), then the same 200 from 8 concurrent clients (throughput, and each request's latency
while the others wait for the planner's lock). Prints a markdown table (milliseconds).

Usage:
    python benchmarks/bench_planner.py                                    # copy_nearest, consensus, learned
    python benchmarks/bench_planner.py --methods consensus --n 50         # a quick look
    python benchmarks/bench_planner.py --checkpoint runs/learned_cpu      # the learned row's checkpoint (default)
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, set before numpy is imported

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ThreadPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from degusta_learn.planner import Planner  # noqa: E402
from degusta_learn.planner.server import create_app  # noqa: E402
from degusta_learn.scene import make_episodes  # noqa: E402
from degusta_learn.synth import generate_dataset  # noqa: E402

CONFIGS = {"copy_nearest": ("baseline_copy_nearest", []), "consensus": ("baseline_consensus", []),
           "population_mean": ("baseline_population_mean", []), "learned": ("learned_predict", [])}


def requests_of(planner: Planner, n: int) -> list[dict]:
    ds = planner.dataset
    episodes = make_episodes(ds, 4, "test", 0)
    return [{"participant": e.participant, "trials": list(e.context),
             "table": ds.arrangement(e.participant, e.target).table} for e in (episodes * n)[:n]]


def ms(values) -> tuple[float, float]:
    a = np.asarray(values) * 1000
    return float(np.percentile(a, 50)), float(np.percentile(a, 95))


class Served:
    """The planner's app on a free loopback port, in a thread."""

    def __init__(self, planner: Planner):
        import uvicorn

        self.server = uvicorn.Server(uvicorn.Config(create_app(planner), host="127.0.0.1", port=0,
                                                    log_level="warning"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        while not self.server.started:
            time.sleep(0.01)
        self.url = f"http://127.0.0.1:{self.server.servers[0].sockets[0].getsockname()[1]}"

    def close(self) -> None:
        self.server.should_exit = True
        self.thread.join(10)


def timed(fn, items) -> list[float]:
    out = []
    for item in items:
        t = time.perf_counter()
        fn(item)
        out.append(time.perf_counter() - t)
    return out


def bench(method: str, dataset: Path, n: int, clients: int, extra: list[str]) -> dict:
    import httpx

    config, sets = CONFIGS[method]
    t = time.perf_counter()
    planner = Planner.from_config(config, [f"dataset={dataset}", *sets, *extra], read_paths=False)
    reqs = requests_of(planner, n)
    load_s = time.perf_counter() - t
    t = time.perf_counter()
    planner.plan(reqs[0])
    first_s = time.perf_counter() - t
    local = timed(planner.plan, reqs)
    served = Served(planner)
    try:
        with httpx.Client(base_url=served.url, timeout=60) as client:
            def post(r):
                reply = client.post("/plan", content=json.dumps(r))
                assert reply.status_code == 200, reply.text
            post(reqs[0])
            remote = timed(post, reqs)

        def client_loop(share):  # one client (one keep-alive connection) per thread, its share of the requests
            with httpx.Client(base_url=served.url, timeout=120) as c:
                return timed(lambda r: c.post("/plan", content=json.dumps(r)).raise_for_status(), share)

        t = time.perf_counter()
        with ThreadPoolExecutor(clients) as pool:
            waits = [w for ws in pool.map(client_loop, [reqs[i::clients] for i in range(clients)]) for w in ws]
        wall = time.perf_counter() - t
    finally:
        served.close()
    return {"method": method, "load_s": load_s, "first_ms": first_s * 1000, "local": ms(local), "http": ms(remote),
            "throughput": len(reqs) / wall, "concurrent": ms(waits)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", nargs="+", default=["copy_nearest", "consensus", "learned"], choices=list(CONFIGS))
    parser.add_argument("--n", type=int, default=200, help="requests per method")
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--dataset", type=Path, default=Path("data/naturalistic"))
    parser.add_argument("--checkpoint", default="runs/learned_cpu", help="the learned row's checkpoint")
    args = parser.parse_args()
    if not (args.dataset / "catalog.json").is_file():
        generate_dataset("naturalistic", args.dataset, seed=0)
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"{args.n} requests per method (test participants, context 4), {args.clients} concurrent clients\n")
    print("| method | load (s) | first plan (ms) | in-process p50 / p95 (ms) | HTTP p50 / p95 (ms) | "
          f"{args.clients} clients: plans/s | {args.clients} clients: p50 / p95 (ms) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for method in args.methods:
        extra = [f"checkpoint={args.checkpoint}"] if method == "learned" else []
        r = bench(method, args.dataset, args.n, args.clients, extra)
        print(f"| {method} | {r['load_s']:.2f} | {r['first_ms']:.0f} | {r['local'][0]:.1f} / {r['local'][1]:.1f} | "
              f"{r['http'][0]:.1f} / {r['http'][1]:.1f} | {r['throughput']:.0f} | "
              f"{r['concurrent'][0]:.0f} / {r['concurrent'][1]:.0f} |", flush=True)


if __name__ == "__main__":
    main()
