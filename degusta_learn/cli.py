"""The `degusta` command: one thin function per verb, no logic of its own.

Usage (CPU smoke run, a minute):
    degusta data generate naturalistic --out data/naturalistic
    degusta data episodes data/naturalistic --context 4 --split test --out data/naturalistic/episodes_k4.jsonl
    degusta data export-sft --config configs/finetune_tiny_cpu.yaml --out exports/tiny_sft   # TRL / LLaMA-Factory
    degusta predict --config configs/baseline_copy_nearest.yaml
    degusta evaluate --dataset data/naturalistic --predictions runs/baseline_copy_nearest/predictions.jsonl --out runs/eval
    degusta plan --config baseline_consensus --request request.json --out plan/   # a plan for a new table
    degusta collect --dataset studies/lab1 --new         # the browser study: your participants' own data
    degusta quickstart                                   # everything above and more, one report
    degusta configs list                                 # the shipped configs; --config takes their names

Every user mistake raises DegustaError: printed on one line as "degusta: error: ...", exit status 2.

Exit codes (`ExitCode`; docs/reliability.md, "Exit codes"):
    0    ok: everything ran and passed (also --help, --version)
    2    user error: a DegustaError or a bad flag, one "degusta: error: ..." line; nothing (new) written
    3    ran, but something it reports failed: the output is written and one "degusta: ..." line on stderr names
         what failed (compare, quickstart: one or more methods failed, the report lists them and scores the
         rest; train --dry-run: a check FAILS on this machine, the whole report is printed)
    130  interrupted by Ctrl-C: finished work is kept
    143  terminated by SIGTERM (a scheduler, `timeout`), handled as Ctrl-C is
A verb returns its message (a str) or a `Result` (message + what failed); main() turns that into the status.
"""

from __future__ import annotations

import argparse
import contextlib
import enum
import os
import re
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from degusta_learn.config import MAX_SEED
from degusta_learn.errors import DegustaError, Terminated
from degusta_learn.names import CONTEXT_LENGTHS, PROMPT_METHODS, SPLITS


class ExitCode(enum.IntEnum):
    """What `degusta` exits with (the module docstring and docs/reliability.md list which verbs use which)."""

    OK = 0
    """Everything ran and passed."""
    USER_ERROR = 2
    """A DegustaError or a bad flag: one `degusta: error: ...` line; nothing, or nothing new, written."""
    PARTIAL = 3
    """It ran and wrote its output, but something it reports failed (a method, a check on this machine)."""
    INTERRUPTED = 130
    """Ctrl-C (128 + SIGINT); finished work is kept."""
    TERMINATED = 143
    """SIGTERM (128 + its number), handled as Ctrl-C is; finished work is kept."""


@dataclass(frozen=True)
class Result:
    """What a verb reports when it can end in part failed: its message (stdout) and, when something failed, one
    line naming it (stderr, after "degusta: "), which makes the exit status `ExitCode.PARTIAL`."""

    message: str
    failed: str = ""
    """One line naming what failed; "" when nothing did (exit 0)."""


def cmd_data_generate(args) -> str:
    from degusta_learn.config.yaml_io import apply_overrides
    from degusta_learn.synth import generate_dataset

    out = generate_dataset(args.name, args.out, seed=args.seed, overwrite=args.overwrite, legacy=args.legacy,
                           options=apply_overrides({}, args.set))
    return f"wrote the {args.name} dataset (SYNTHETIC{', legacy tables' if args.legacy else ''}) to {out}"


def cmd_data_export_sft(args) -> str:
    from degusta_learn.finetune.export_sft import export_sft

    out, n, images = export_sft(args.config, args.out, split=args.split, overrides=args.set)
    return (f"wrote {n} {args.split} examples ({images} images) to {out}: {args.split}.jsonl (TRL messages + "
            f"images), {args.split}_sharegpt.jsonl + dataset_info.json (LLaMA-Factory); see {out}/README.md")


def cmd_data_validate(args) -> str:
    from degusta_learn.scene import load_dataset
    from degusta_learn.scene.dataset import off_surface
    from degusta_learn.synth.oracle import dataset_styles

    ds = load_dataset(args.dir)
    ratings = f", {len(ds.ratings)} ratings" if ds.ratings is not None else ""
    styles = dataset_styles(ds)
    styles = f", {len(styles)} latent styles" if styles is not None else ""
    report = (f"{args.dir}: valid — {len(ds.catalog)} objects, {len(ds.tables)} tables, "
              f"{len(ds.participants)} participants, {len(ds.arrangements)} arrangements{ratings}{styles}")
    off = off_surface(ds)
    if off:
        shown = "; ".join(f"participant {a.participant} trial {a.trial} object {p.object} at ({p.x:.3f}, {p.y:.3f}) "
                          f"on table {a.table}" for a, p in off[:3])
        total = sum(len(a.placements) for a in ds.arrangements)
        report += (f"\nnote: {len(off)} of {total} placements have their centre off the table's surface polygon "
                   f"(tables.json 'surface'), e.g. {shown}{'; ...' if len(off) > 3 else ''}. A plate may hang "
                   f"over an edge; many such placements usually mean x, y are not fractions of the table's "
                   f"width and height")
    return report


def cmd_data_episodes(args) -> str:
    from degusta_learn.scene import load_dataset, make_episodes, write_episodes

    episodes = make_episodes(load_dataset(args.dir), args.context, args.split, args.seed)
    write_episodes(args.out, episodes)
    return f"wrote {len(episodes)} episodes (context {args.context}, split {args.split}) to {args.out}"


def cmd_predict(args) -> str:
    from degusta_learn.methods import run_predict

    out = run_predict(args.config, args.set, dry_run=args.dry_run)
    return f"wrote predictions to {out}" if out else "dry run: nothing written"


def cmd_train(args) -> str | Result:
    from degusta_learn.dryrun import DryRunReport
    from degusta_learn.methods import run_train
    from degusta_learn.training import global_rank

    out = run_train(args.config, args.set, dry_run=args.dry_run)
    if global_rank() != 0:  # the other processes of a multi-process run say nothing (rank 0 reports)
        return ""
    if isinstance(out, DryRunReport):  # the report is printed; a check that FAILS here makes it exit 3
        return Result("dry run: nothing loaded, trained or written",
                      failed=f"dry run: {out.failure_summary()}" if out.failures else "")
    return f"training finished; outputs in {out}"


def cmd_evaluate(args) -> str:
    from degusta_learn.evaluate import evaluate_files
    from degusta_learn.evaluate.compare import RESAMPLE_CLUSTER

    out = evaluate_files(args.dataset, args.predictions, args.out, episodes=args.episodes,
                         n_bootstrap=args.bootstrap, seed=args.seed, matching=args.matching,
                         cluster=RESAMPLE_CLUSTER[args.resample])
    from degusta_learn.evaluate.console import summary_text
    from degusta_learn.files.jsonio import read_json

    table = summary_text(read_json(out / "metrics.json"))
    return f"{table}\nwrote metrics.json, per_episode.csv and report.md to {out}"


def cmd_compare(args) -> Result:
    from degusta_learn.evaluate.compare import run_compare

    from degusta_learn.evaluate.console import summary_text
    from degusta_learn.files.jsonio import read_json

    result = run_compare(args.config, args.set)
    table = summary_text(read_json(result.out / "metrics.json").get("methods") or {})
    return Result(f"{table}\nwrote the comparison report to {result.out / 'report.md'} (and report.html)",
                  failed=result.failure_summary())


def cmd_render_episode(args) -> str:
    from degusta_learn.render.commands import render_episode

    files = render_episode(args.dataset, args.participant, args.target, args.context, args.method, args.out,
                           size=args.size, grid=args.grid, seed=args.seed)
    return f"wrote {len(files)} files ({', '.join(f.name for f in files)}) to {args.out}"


def cmd_render_catalog(args) -> str:
    from degusta_learn.render.commands import render_catalog

    return f"wrote the catalog contact sheet to {render_catalog(args.dataset, args.out, size=args.size)}"


def cmd_quickstart(args) -> Result:
    from degusta_learn.quickstart import run_quickstart

    result = run_quickstart(args.out, small=args.small, with_api=args.with_api)
    report = result.out
    return Result(f"quickstart finished: open {report / 'report.md'} (or {report / 'report.html'} in a browser)",
                  failed=result.failure_summary())


def cmd_plan(args) -> str:
    from degusta_learn.planner import Planner, read_request
    from degusta_learn.planner.write import write_plan

    @contextlib.contextmanager
    def naming_the_file():  # a request's error ("request...: ...", as POST /plan answers) names the file first
        try:
            yield
        except DegustaError as e:
            if str(e).startswith("request"):
                raise DegustaError(f"{args.request}: {e}") from None
            raise

    with naming_the_file():
        request = read_request(args.request)  # a bad request fails before the method loads
    planner = Planner.from_config(args.config, args.set)
    if args.dry_run:
        planner.dry_run(request)
        return "dry run: nothing planned or written"
    with naming_the_file():
        plan = planner.plan(request)
    out = write_plan(planner, plan, args.out)
    note = f" ({plan.diagnostics['cost_usd']:.4f} USD)" if plan.diagnostics.get("cost_usd") else ""
    return f"{planner.method}: {len(plan.steps)} steps{' (FAILED)' if plan.failed else ''}{note}; wrote plan.json and plan.png to {out}"


def cmd_serve(args) -> str:
    from degusta_learn.planner import Planner
    from degusta_learn.planner.server import serve

    serve(Planner.from_config(args.config, args.set, read_paths=False), host=args.host, port=args.port)
    return "server stopped"


def cmd_collect(args) -> str:
    from degusta_learn.collect.run import collect

    return collect(args.dataset, args.config, args.set, new=args.new, host=args.host, port=args.port)


def cmd_configs_list(args) -> str:
    from degusta_learn.shipped import SHIPPED_DIR, list_configs

    rows = list_configs()
    width = max(len(name) for name, _ in rows)
    return "\n".join([f"{len(rows)} shipped configs in {SHIPPED_DIR}:",
                      *(f"  {name:<{width}}  {text}" for name, text in rows),
                      "run one by name (degusta train --config learned_cpu) or copy one out to edit "
                      "(degusta configs copy NAME [DIR])"])


def cmd_configs_copy(args) -> str:
    from degusta_learn.shipped import copy_config, run_command

    target = copy_config(args.name, args.dest)
    command = run_command(target, target)
    return f"wrote {target}" + (f"; run it with: {command}" if command else "")


def _config_arg(text: str) -> Path:
    """An argparse type: --config as a path (an existing one wins; `~` expanded, checked as every path flag is) or a
    shipped config name."""
    from degusta_learn.shipped import resolve_config

    try:
        return resolve_config(_checked(text))
    except DegustaError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


class _Parser(argparse.ArgumentParser):
    """argparse with the toolkit's error line: `degusta: error: ...` (one line, exit 2), not a usage dump."""

    def error(self, message: str):
        self.exit(2, f"degusta: error: {self.prog}: {message} (see {self.prog} --help)\n")


def _int_in(lo: int, hi: int) -> Callable[[str], int]:
    """An argparse type: an integer in [lo, hi] (a seed, a size, a count), checked before anything runs."""

    def parse(text: str) -> int:
        # decimal digits only, as a config reads them (YAML 1.2): Python's int() also takes 1_000 and other scripts' digits
        if not re.fullmatch(r"[-+]?[0-9]+", text.strip()):
            raise argparse.ArgumentTypeError(f"expected an integer (decimal digits), got {text[:40]!r}")
        value = int(text)
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"expected an integer from {lo} to {hi}, got {text[:40]}")
        return value

    parse.__name__ = "integer"
    return parse


def _checked(text: str) -> str:
    """`text` with `~` expanded, or ArgumentTypeError "PATH: why" (files.paths.check_path: a NUL byte, a name or path too
    long for the file system, non-UTF-8 bytes, a parent that is a file, a broken link, an unknown ~user ...); argparse
    names the flag."""
    from degusta_learn.files.paths import check_path, shown_path

    expanded, problem = check_path(text)
    if problem:
        raise argparse.ArgumentTypeError(f"{shown_path(text)}: {problem}")
    return expanded


def _out_arg(text: str) -> Path:
    """An argparse type: an output path, never empty (Path("") is the current folder, whose files it would
    replace), `~` expanded and checked (`_checked`)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; give the file or folder to write")
    return Path(_checked(text))


def _in_arg(text: str) -> Path:
    """An argparse type: a path to read (a dataset folder, a predictions or episodes file), `~` expanded and checked
    (`_checked`); whether it exists is for the command to say."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; give the file or folder to read")
    return Path(_checked(text))


SEED = _int_in(0, MAX_SEED)
CONFIG_HELP = "a YAML file, or the name of a shipped config (degusta configs list)"
IMAGE_SIZE = _int_in(64, 4096)
"""`degusta render --size`: render.lifting.MIN_IMAGE_SIZE .. MAX_IMAGE_SIZE (a Renderer draws nothing smaller; the
cost of an image set grows with the pixels, size^2: 4096 px takes ~1.2 min for an episode, benchmarks/RESULTS.md)."""


def version() -> str:
    """The version of the running package (`degusta_learn.__version__`, the code imported: an installed
    distribution's metadata may describe another copy than the one on sys.path)."""
    from degusta_learn import __version__

    return __version__


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="degusta", description="Personalized table setting: data, "
                                     "zero-shot VLM prompting, learned baselines, fine-tuning, evaluation.",
                     epilog="exit status: 0 ok; 2 a user error (nothing new written); 3 it ran and wrote its "
                            "output, but something it reports failed (compare/quickstart: a method; "
                            "train --dry-run: a check FAILS on this machine); 130 interrupted (143: SIGTERM)")
    parser.add_argument("--version", action="version", version=f"degusta {version()}")
    verbs = parser.add_subparsers(dest="verb", required=True)

    data = verbs.add_parser("data", help="generate, validate and cut datasets").add_subparsers(dest="data_verb", required=True)
    p = data.add_parser("generate", help="write an embedded synthetic dataset")
    p.add_argument("name", choices=["naturalistic", "simulated", "relational"])
    p.add_argument("--out", required=True, type=_out_arg)
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing dataset folder that degusta generated (nothing else is ever deleted)")
    p.add_argument("--legacy", action="store_true",
                   help="naturalistic only: the tables made before every table kept the plausibility rules "
                        "(bounded duplicates per type, a utensil per plate; docs/data.md), byte for byte")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="relational only: a generator option (participants, noise, multi; docs/generators.md)")
    p.set_defaults(func=cmd_data_generate)
    p = data.add_parser("validate", help="check a dataset folder; exit 0 or name the file/line/field")
    p.add_argument("dir", type=_in_arg)
    p.set_defaults(func=cmd_data_validate)
    p = data.add_parser("episodes", help="write episodes.jsonl for a context length and split")
    p.add_argument("dir", type=_in_arg)
    p.add_argument("--context", type=int, choices=list(CONTEXT_LENGTHS), required=True)
    p.add_argument("--split", default="test", choices=list(SPLITS))
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--out", required=True, type=_out_arg)
    p.set_defaults(func=cmd_data_episodes)
    p = data.add_parser("export-sft", help="a finetune config's training examples as a messages + images "
                        "dataset (TRL, LLaMA-Factory)")
    p.add_argument("--config", required=True, type=_config_arg, help=CONFIG_HELP + " (kind: finetune)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--out", required=True, type=_out_arg)
    p.add_argument("--split", default="train", choices=["train", "val"])
    p.set_defaults(func=cmd_data_export_sft)

    p = verbs.add_parser("predict", help="run any method from a YAML config -> predictions.jsonl")
    p.add_argument("--config", required=True, type=_config_arg, help=CONFIG_HELP)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--dry-run", action="store_true", help="count requests and cost; call nothing")
    p.set_defaults(func=cmd_predict)

    p = verbs.add_parser("plan", help="a plan for a new table from a request (JSON) -> plan.json + plan.png")
    p.add_argument("--config", required=True, type=_config_arg, help=CONFIG_HELP + " (a predict config)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--request", required=True, type=_in_arg, help="the plan request, a JSON file (docs/planner.md)")
    p.add_argument("--out", required=True, type=_out_arg, help="the folder to write plan.json and plan.png into")
    p.add_argument("--dry-run", action="store_true", help="what the plan would call and cost; call nothing")
    p.set_defaults(func=cmd_plan)

    p = verbs.add_parser("serve", help="plans over HTTP: POST /plan, GET /health, /openapi.json (FastAPI)")
    p.add_argument("--config", required=True, type=_config_arg, help=CONFIG_HELP + " (a predict config)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--host", default="127.0.0.1", help="the address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=_int_in(0, 65535), default=8000, help="the port (default 8000)")
    p.set_defaults(func=cmd_serve)

    p = verbs.add_parser("collect", help="the browser study: participants set tables and rate them -> a dataset "
                                         "folder (docs/collect.md)")
    p.add_argument("--dataset", required=True, type=_out_arg, help="the study folder: its catalog and tables are "
                   "what participants set; arrangements.jsonl and ratings.jsonl are appended to it")
    p.add_argument("--new", action="store_true", help="make a new study folder with the embedded default's "
                   "catalog and tables")
    p.add_argument("--config", type=_config_arg, default=None, help=CONFIG_HELP + " (a study config; default: "
                   "collect_study)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--host", default="127.0.0.1", help="the address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=_int_in(0, 65535), default=8765, help="the port (default 8765)")
    p.set_defaults(func=cmd_collect)

    p = verbs.add_parser("train", help="train a learned baseline or fine-tune a VLM from a YAML config")
    p.add_argument("--config", required=True, type=_config_arg, help=CONFIG_HELP)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--dry-run", action="store_true", help="print model size, trainable parameters, tokens per "
                   "example vs data.max_length, steps per epoch and predicted memory; load and write nothing")
    p.set_defaults(func=cmd_train)

    p = verbs.add_parser("evaluate", help="predictions -> metrics.json, per_episode.csv, report.md")
    p.add_argument("--dataset", required=True, type=_in_arg)
    p.add_argument("--predictions", required=True, type=_in_arg, nargs="+")
    p.add_argument("--episodes", type=_in_arg, help="the episode set the predictions must cover (optional)")
    p.add_argument("--out", required=True, type=_out_arg)
    p.add_argument("--bootstrap", type=_int_in(1, 1_000_000), default=1000, help="bootstrap resamples for the intervals")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--resample", default="participants", choices=["participants", "episodes"],
                   help="what the bootstrap intervals resample: participants, each with all of its episodes (the "
                        "default), or episodes one by one")
    p.add_argument("--matching", default="hungarian", choices=["hungarian", "paper"],  # metrics.matching.MATCHINGS
                   help="how predicted objects are paired with true ones: hungarian (least total Hamming distance, "
                   "the default) or paper (the paper's greedy rule: each true object in placement order takes "
                   "its most similar remaining prediction)")
    p.set_defaults(func=cmd_evaluate)

    p = verbs.add_parser("compare", help="several methods on the same episodes -> one report folder")
    p.add_argument("--config", required=True, type=_config_arg, help=CONFIG_HELP)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.set_defaults(func=cmd_compare)

    render = verbs.add_parser("render", help="lifted images of an episode or of the catalog").add_subparsers(
        dest="render_verb", required=True)
    p = render.add_parser("episode", help="an episode's context/target images, object sheets and prompt texts")
    p.add_argument("dataset", type=_in_arg)
    p.add_argument("--participant", required=True)
    p.add_argument("--target", type=_int_in(0, 999_999_999), required=True, help="the target trial")
    p.add_argument("--context", type=_int_in(0, 1000), required=True, help="context length (e.g. 0, 2, 4)")
    p.add_argument("--method", required=True, choices=list(PROMPT_METHODS))
    p.add_argument("--out", required=True, type=_out_arg)
    p.add_argument("--size", type=IMAGE_SIZE, default=448, help="image size in pixels")
    p.add_argument("--grid", type=_int_in(1, 26), default=8, help="grid rows = columns for logma/mogma")
    p.add_argument("--seed", type=SEED, default=0, help="episode seed (as in degusta data episodes)")
    p.set_defaults(func=cmd_render_episode)
    p = render.add_parser("catalog", help="a contact sheet of the whole catalog")
    p.add_argument("dataset", type=_in_arg)
    p.add_argument("--out", required=True, type=_out_arg)
    p.add_argument("--size", type=IMAGE_SIZE, default=448, help="pixels per object-type sheet")
    p.set_defaults(func=cmd_render_catalog)

    p = verbs.add_parser("quickstart", help="the main job on the embedded default (CPU, about 5 minutes on 2 cores)")
    p.add_argument("--out", type=_out_arg, default=Path("quickstart"), help="where everything is written")
    p.add_argument("--small", action="store_true", help="a reduced size that finishes in a few minutes (CI)")
    p.add_argument("--with-api", action="store_true",
                   help="add a zero-shot GPT-4o MOGMA row (needs OPENAI_API_KEY; prints the cost first)")
    p.set_defaults(func=cmd_quickstart)

    configs = verbs.add_parser("configs", help="the configs shipped with the package: list them, copy one to edit"
                               ).add_subparsers(dest="configs_verb", required=True)
    p = configs.add_parser("list", help="every shipped config with its one-line purpose")
    p.set_defaults(func=cmd_configs_list)
    p = configs.add_parser("copy", help="write a shipped config out to edit (never overwrites)")
    p.add_argument("name", help="a shipped config name, with or without .yaml (degusta configs list)")
    p.add_argument("dest", nargs="?", type=_out_arg, default=Path("."),
                   help="the folder to write NAME.yaml into (default: here), or a .yaml file name")
    p.set_defaults(func=cmd_configs_copy)
    return parser


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """While a verb runs, SIGTERM raises `Terminated` (a KeyboardInterrupt) in the main thread, so a kill by a
    scheduler or `timeout` keeps finished work exactly as Ctrl-C does; the previous handler is restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    """Run one verb; returns its `ExitCode` (module docstring)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # a flag error (one line printed), --help or --version: the status, not an exception
        return e.code if isinstance(e.code, int) else ExitCode.USER_ERROR
    func: Callable = args.func
    try:
        with sigterm_as_interrupt():
            result = func(args)
    except DegustaError as e:
        from degusta_learn.prompting.backends.base import redact
        from degusta_learn.textsafe import one_line

        # one line, a key pasted into a config never echoed, a server's reply quoted without its control characters
        print(f"degusta: error: {one_line(redact(str(e)), limit=None)}", file=sys.stderr)
        return ExitCode.USER_ERROR
    except KeyboardInterrupt as e:
        if argv is None and threading.current_thread() is threading.main_thread():  # the `degusta` process itself:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM while it exits is not a kill (-15)
        name = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
        print(f"degusta: {name}; finished work is kept (re-run to resume)", file=sys.stderr)
        return ExitCode.TERMINATED if isinstance(e, Terminated) else ExitCode.INTERRUPTED
    if not isinstance(result, Result):
        result = Result(result or "")
    if result.message:
        try:
            print(result.message)
        except BrokenPipeError:  # e.g. `degusta configs list | head`: the reader took what it wanted
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
    if result.failed:  # one line on stderr; the report itself says more
        from degusta_learn.prompting.backends.base import redact

        print(f"degusta: {redact(' '.join(result.failed.split()))}", file=sys.stderr)
        return ExitCode.PARTIAL
    return ExitCode.OK


if __name__ == "__main__":
    sys.exit(main())
