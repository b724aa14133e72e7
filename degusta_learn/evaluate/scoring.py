"""Score predictions episode by episode: the rows of per_episode.csv.

Every method's predictions are scored the same way (degusta_learn.metrics.score_many, equal to
score_prediction on each, against the held-out target arrangement of the dataset and its table), so
zero-shot, baseline and fine-tuned methods are compared on equal terms.

A predictions file may lack a field a metric needs: placements without `rotation` (an older or hand-written
file; the reader takes 0 for it). `check_records`, which reads the file itself, marks such records
(`missing_fields`); `score_predictions` then leaves what needs the rotation unscored (rotation error and
the footprint overlap: nan, `missing` names the field) instead of scoring a 0 nobody predicted, and the
reports say how many records lack which field.

Each row also carries `answer_key`, a short fingerprint of the answer (its object ids at positions rounded
to 0.01, metrics.answer_key): the summary's "constant answer" test compares them (metrics/degenerate.py).
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import read_jsonl
from degusta_learn.metrics import answer_key, score_many
from degusta_learn.scene import Dataset, Episode, Prediction
from degusta_learn.task.aggregate import AGGREGATIONS

_CONTEXT_IN_ID = re.compile(r"/k(\d+)$")
EPISODE_ID = re.compile(r"(?P<participant>.+)/t(?P<target>\d{1,9})/k(?P<context>\d{1,9})")
"""The ids `make_episodes` gives: participant/tTARGET/kCONTEXT."""
METHOD_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,79}")
"""A method name is a safe slug (letters, digits, '.', '_', '-'; at most 80 characters): it names files under
compare's `<out>/predictions/` and rows of the reports, so a predictions file's `method` must be one too."""

CSV_COLUMNS = ("method", "episode", "participant", "target", "context", "task", "failed", "n_gt", "n_pred",
               "n_matched", "object_accuracy", "rmsd", "rmsd_unregistered", "count_error", "set_rmsd",
               "object_precision", "object_f1", "set_rmsd_unregistered", "order_tau", "rotation_error",
               "n_rotation_scored", "off_table_rate", "overlap_rate", "gt_off_table_rate", "gt_overlap_rate", "missing",
               "answer_key", "tokens", "cost_usd", "n_samples", "n_parsed", "aggregation", "constrained", "n_decoded",
               "forced_closes", "n_free_known", "n_free_parsed")
MISSING_ATTR = "missing_fields"
"""The attribute `check_records` sets on a Prediction whose file record lacks fields a metric needs: a tuple of
field names (e.g. ("rotation",)); `score_predictions` reads it."""


@dataclass
class EpisodeRow:
    """One method's scores on one episode (a row of per_episode.csv)."""

    method: str
    episode: str
    participant: str
    target: int
    context: int | None
    task: str
    failed: bool
    n_gt: int
    n_pred: int
    n_matched: int
    object_accuracy: float
    rmsd: float
    rmsd_unregistered: float
    count_error: float
    set_rmsd: float  # set-aware (OSPA) RMSD: c = SET_PENALTY per unmatched object; c for a failed prediction
    # The rest of the task plan (metrics/scores.py; nan where undefined, see docs/metrics.md):
    object_precision: float = math.nan  # same-id matches / predicted objects (0 for a failed prediction)
    object_f1: float = math.nan
    set_rmsd_unregistered: float = math.nan  # set RMSD without registration
    order_tau: float = math.nan  # Kendall's tau of the matched pairs' placement order; nan for < 2 pairs
    rotation_error: float = math.nan  # degrees modulo symmetry, mean over scored matched pairs
    n_rotation_scored: int = 0
    off_table_rate: float = math.nan  # predicted centroids off the table surface
    overlap_rate: float = math.nan  # pairs of predicted footprints that overlap
    gt_off_table_rate: float = math.nan  # the ground truth's own rates (reference)
    gt_overlap_rate: float = math.nan
    missing: str | None = None  # fields the record lacked, e.g. "rotation" (those metrics not scored)
    answer_key: str | None = None  # fingerprint of the answer (metrics.answer_key; None: failed or empty)
    tokens: float | None = None
    cost_usd: float | None = None
    # Answers of methods that parse model text (zero-shot, fine-tuned VLMs), from the prediction's diagnostics:
    n_samples: int | None = None  # answers sampled
    n_parsed: int | None = None  # of which parsed
    aggregation: str | None = None  # how they were combined (prompting.aggregate.AGGREGATIONS; None: not recorded)
    constrained: bool | None = None  # decoded inside the answer grammar (a local model; None: not reported)
    n_decoded: int | None = None  # answers whose decoding is known (a local model's, not read back from a cache)
    forced_closes: int | None = None  # answers the token budget closed early (grammar) or cut off (free)
    n_free_known: int | None = None  # grammar: answers whose free-decoding version is known ...
    n_free_parsed: int | None = None  # ... and of those, how many parse (what free decoding would score)

    def to_row(self) -> dict:
        return asdict(self)


def usage_number(diagnostics, key: str) -> float | None:
    """diagnostics["usage"][key] as a finite number >= 0, or None (missing or malformed: never an error)."""
    usage = diagnostics.get("usage") if isinstance(diagnostics, dict) else None
    value = usage.get(key) if isinstance(usage, dict) else None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        value = float(value)
    except (OverflowError, ValueError):
        return None
    return value if math.isfinite(value) and value >= 0 else None


def _count(d, key: str) -> int | None:
    """d[key] as an int >= 0, else None (missing or malformed diagnostics are never an error)."""
    v = d.get(key) if isinstance(d, dict) else None
    return v if isinstance(v, int) and not isinstance(v, bool) and v >= 0 else None


def answer_counts(diagnostics) -> dict:
    """The answer fields of an EpisodeRow from a prediction's diagnostics (`prompting.aggregate`)."""
    decoding = diagnostics.get("decoding") if isinstance(diagnostics, dict) else None
    constrained = decoding.get("constrained") if isinstance(decoding, dict) else None
    aggregation = diagnostics.get("aggregation") if isinstance(diagnostics, dict) else None
    return {"n_samples": _count(diagnostics, "n_responses"), "n_parsed": _count(diagnostics, "n_parsed"),
            "aggregation": aggregation if aggregation in AGGREGATIONS else None,  # untrusted: a known name or None
            "constrained": constrained if isinstance(constrained, bool) else None,
            "n_decoded": _count(decoding, "known"), "forced_closes": _count(decoding, "forced_closes"),
            "n_free_known": _count(decoding, "free_known"), "n_free_parsed": _count(decoding, "free_parsed")}


def _malformed_usage(diagnostics) -> bool:
    usage = diagnostics.get("usage") if isinstance(diagnostics, dict) else None
    if usage is None:
        return False
    if not isinstance(usage, dict):
        return True
    return any(usage.get(k) is not None and usage_number(diagnostics, k) is None for k in ("tokens", "cost_usd"))


def check_records(path: str | Path, predictions: list[Prediction], ds: Dataset,
                  episodes: dict[str, Episode] | None = None, one_method: bool = True) -> list[str]:
    """Refuse predictions that contradict their episode; returns notes for the report (never silent).

    Every record must agree with its episode: with `episodes`, the episode's participant and target;
    without, the participant and target its id names (ids of `make_episodes`: participant/tT/kK; any
    other id needs the episode set). The target must be a trial of the participant in the dataset and
    not one of the episode's context trials. With `one_method`, a file holds one method: a second name
    (a misspelt line) is refused. Errors name file, line and field; malformed `diagnostics.usage` is
    ignored (counted in a note), never an error. A record lacking a field a metric needs (placements without
    `rotation`) is marked on its Prediction (`MISSING_ATTR`, read by `score_predictions`) and counted in a note.
    """
    path = Path(path)
    try:
        records = list(read_jsonl(path))
    except DegustaError:
        records = []
    if len(records) != len(predictions):  # the file changed under us: fall back to record numbers
        records = [(n, None) for n in range(1, len(predictions) + 1)]
    first_method: tuple[str, int] | None = None
    bad_usage, missing = 0, {}
    for (lineno, record), pred in zip(records, predictions):
        lacks = record_missing_fields(record, pred)
        setattr(pred, MISSING_ATTR, lacks)
        for name in lacks:
            missing[name] = missing.get(name, 0) + 1
        where = f"{path}:{lineno}"
        if not isinstance(pred.method, str) or not METHOD_NAME.fullmatch(pred.method):
            raise DegustaError(f"{where}: field 'method': {pred.method!r:.100} is not a safe method name (letters, "
                               "digits, '.', '_', '-'; starting with a letter or digit; at most 80 characters)")
        if one_method:
            if first_method is None:
                first_method = (pred.method, lineno)
            elif pred.method != first_method[0]:
                raise DegustaError(
                    f"{where}: field 'method': {pred.method!r} differs from {first_method[0]!r} on line "
                    f"{first_method[1]}; a predictions file holds one method (fix the misspelt name, or split "
                    "the file and pass both)")
        ep = episodes.get(pred.episode) if episodes is not None else None
        if ep is not None:
            participant, target, context = ep.participant, ep.target, ep.context
            source = f"the episode set says episode {pred.episode!r} is"
        else:
            m = EPISODE_ID.fullmatch(pred.episode)
            if m is None:
                raise DegustaError(
                    f"{where}: field 'episode': {pred.episode!r} is not an id of the form participant/tT/kK, so "
                    "its participant and target cannot be checked; pass the episode set with --episodes")
            participant, target, context = m.group("participant"), int(m.group("target")), None
            source = f"episode id {pred.episode!r} names"
        if pred.participant != participant:
            raise DegustaError(f"{where}: field 'participant': {source} participant {participant!r}, "
                               f"but the record says {pred.participant!r}")
        if pred.target != target:
            raise DegustaError(f"{where}: field 'target': {source} target trial {target}, "
                               f"but the record says {pred.target}")
        claimed = pred.diagnostics.get("context") if isinstance(pred.diagnostics, dict) else None
        for ctx in (context, claimed if isinstance(claimed, list) else None):
            if ctx is not None and pred.target in ctx:
                raise DegustaError(f"{where}: field 'target': trial {pred.target} is one of the episode's "
                                   f"context trials {list(ctx)}; a method must not be scored on what it was shown")
        if (pred.participant, pred.target) not in ds._by_key:
            raise DegustaError(f"{where}: field 'target': participant {pred.participant!r} has no trial "
                               f"{pred.target} in the dataset")
        if ep is None:
            k = int(m.group("context"))
            if isinstance(claimed, list) and len(claimed) != k:
                raise DegustaError(f"{where}: field 'episode': {pred.episode!r} names context length {k}, but the "
                                   f"record's diagnostics.context holds {len(claimed)} trials {claimed!r}"[:400]
                                   + "; fix the id or pass the episode set with --episodes")
            n_trials = len(ds.trials_of(pred.participant))
            if k >= n_trials:
                raise DegustaError(f"{where}: field 'episode': {pred.episode!r} asks for {k} context trials, but "
                                   f"participant {pred.participant!r} has only {n_trials} trials")
        bad_usage += _malformed_usage(pred.diagnostics)
    notes = [f"{path}: {count} record(s) have placements without `{name}`: {_MISSING_EFFECT.get(name, name)}."
             for name, count in missing.items()]
    if bad_usage:
        notes.append(f"{path}: {bad_usage} record(s) have a malformed `diagnostics.usage` (tokens/cost ignored there).")
    return notes


_MISSING_EFFECT = {"rotation": "their rotation error and overlapping footprints (which need the rotation) are not "
                               "scored (left out of those means), every other metric is"}
NEEDS = {"rotation": ("rotation_error", "overlap_rate")}
"""The metrics a missing field leaves unscored."""


def record_missing_fields(record, pred: Prediction) -> tuple[str, ...]:
    """Fields a metric needs that the file record of a scored (not failed) prediction lacks: ("rotation",) when
    one of its placements has no `rotation` (the reader takes 0 for it, which must not be scored as an answer)."""
    if pred.failed or not isinstance(record, dict) or not isinstance(record.get("placements"), list):
        return ()
    if any(isinstance(p, dict) and "rotation" not in p for p in record["placements"]):
        return ("rotation",)
    return ()


def _answer_key(pred: Prediction) -> str | None:
    """The answer's fingerprint (metrics.answer_key), for the "constant answer" test; None when it failed."""
    if pred.failed or not pred.placements:
        return None
    return answer_key([p.object for p in pred.placements], [(p.x, p.y) for p in pred.placements])


def score_predictions(ds: Dataset, predictions: list[Prediction],
                      episodes: dict[str, Episode] | None = None, matching: str = "hungarian") -> list[EpisodeRow]:
    """Score each prediction against the dataset's target arrangement.

    Args:
        ds: the dataset holding the ground truth.
        predictions: one method's (or several methods') predictions (check them with `check_records`).
        episodes: the episode set, if known; gives context length and task. Without it the context
            length is read from ids of the form ``.../kN`` and the task is "unknown".
        matching: how predicted objects are matched to true ones, "hungarian" (default) or "paper"
            (metrics.matching `MATCHINGS`; docs/metrics.md "Matching: ours and the paper's").

    Records `check_records` marked as lacking `rotation` get no rotation error and no overlap rate (nan;
    `missing` = "rotation").
    """
    for pred in predictions:
        ep = episodes.get(pred.episode) if episodes else None
        if ep is not None and (ep.participant, ep.target) != (pred.participant, pred.target):
            raise DegustaError(f"prediction for episode {pred.episode!r} names participant {pred.participant!r} "
                               f"trial {pred.target}, but the episode's target is {ep.participant!r} trial {ep.target}")
    gts = [ds.arrangement(pred.participant, pred.target) for pred in predictions]
    rows = []
    for pred, score in zip(predictions, score_many(ds.catalog, gts, predictions, tables=ds.tables,
                                                       matching=matching)):
        lacks = getattr(pred, MISSING_ATTR, ())
        if "rotation" in lacks:  # the reader's 0 is no answer: nothing that depends on it is scored
            score.rotation_error, score.n_rotation_scored, score.overlap_rate = math.nan, 0, math.nan
        ep = episodes.get(pred.episode) if episodes else None
        if ep is not None:
            context, task = len(ep.context), ep.task
        else:
            m = _CONTEXT_IN_ID.search(pred.episode)
            context, task = (int(m.group(1)) if m else None), "unknown"
        rows.append(EpisodeRow(
            method=pred.method, episode=pred.episode, participant=pred.participant, target=pred.target,
            context=context, task=task, failed=pred.failed or not pred.placements, n_gt=score.n_gt,
            n_pred=score.n_pred, n_matched=score.n_matched, object_accuracy=score.object_accuracy,
            rmsd=score.rmsd, rmsd_unregistered=score.rmsd_unregistered, count_error=score.count_error,
            set_rmsd=score.set_rmsd, object_precision=score.object_precision, object_f1=score.object_f1,
            set_rmsd_unregistered=score.set_rmsd_unregistered, order_tau=score.order_tau,
            rotation_error=score.rotation_error, n_rotation_scored=score.n_rotation_scored,
            off_table_rate=score.off_table_rate, overlap_rate=score.overlap_rate,
            gt_off_table_rate=score.gt_off_table_rate, gt_overlap_rate=score.gt_overlap_rate,
            missing=" ".join(lacks) or None, answer_key=_answer_key(pred),
            tokens=usage_number(pred.diagnostics, "tokens"), cost_usd=usage_number(pred.diagnostics, "cost_usd"),
            **answer_counts(pred.diagnostics)))
    return rows


def score_file(ds: Dataset, path: str | Path, episodes: dict[str, Episode], note=None) -> list[EpisodeRow]:
    """One predictions file scored on exactly `episodes` (as `degusta evaluate` scores it): every episode must have
    a prediction (one line names how many lack one). `note(text)` receives `check_records`' notes (default:
    dropped)."""
    from degusta_learn.scene import read_predictions

    preds = read_predictions(path, ds.catalog, episodes)
    for text in check_records(path, preds, ds, episodes):
        if note is not None:
            note(text)
    missing = set(episodes) - {p.episode for p in preds}
    if missing:
        raise DegustaError(f"{path}: {len(missing)} of the {len(episodes)} episodes have no prediction "
                           f"(e.g. {min(missing)})")
    return score_predictions(ds, preds, episodes)
