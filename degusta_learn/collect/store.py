"""What a study session writes, and the state that lets every participant resume where they were.

Files in the study folder (the dataset format, DESIGN section 3, plus the study's own folder):

    arrangements.jsonl              one line per submitted table (participant, trial, table, placements)
    ratings.jsonl                   one line per finished self-evaluation (b_initial, b_jitter, rmsd_jitter,
                                    b_correct, rmsd_correct)
    collect/self_evaluation.jsonl   the same trial with what was shown: t, the jittered and the corrected copies
    collect/participants/ID.json    a participant's place in the study, their draft, the SHA-256 of their session
                                    token (never the token), the submission ids already taken

Every write replaces its file atomically (files/atomic.py: a reader never sees half a file, a crash never leaves
one), in the order dataset line first, state second; `StudyStore` reconciles the two when it opens, so a crash
between them neither loses the line nor writes it twice. One lock serializes every change, so two participants'
submissions never interleave; each participant is reached only through their own session token.
Every submission is checked by the rules of `degusta data validate` (scene/dataset.py) before anything is written.
"""

from __future__ import annotations

import hashlib
import json
import re
import secrets
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from degusta_learn.collect.selfeval import displacement_rmsd, jitter_rng, jittered
from degusta_learn.collect.study import MAX_OBJECTS, Study
from degusta_learn.errors import DegustaError
from degusta_learn.files.atomic import atomic_write_bytes
from degusta_learn.files.jsonio import atomic_write_json, read_json
from degusta_learn.scene.dataset import check_arrangements, check_ratings, parse_placements
from degusta_learn.scene.types import Placement
from degusta_learn.scene.validate import Where, get, require_mapping

STAGES = ("arrange", "rate_initial", "rate_jitter", "correct", "rate_correct", "done")
EDITABLE = ("arrange", "correct")
RATING_STAGES = ("rate_initial", "rate_jitter", "rate_correct")
ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
MAX_SUBMISSION_IDS = 200
"""Submission ids remembered per participant (a replay of any of them is answered, not written again)."""


class Conflict(DegustaError):
    """A request that does not fit the participant's current step (409): another tab moved on, an id in use."""


class NoSession(DegustaError):
    """No valid session (401)."""


def token_digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@dataclass
class ParticipantState:
    """One participant's place in the study (collect/participants/ID.json)."""

    participant: str
    token_sha256: str
    tables: list[int]
    trial: int = 0
    stage: str = "arrange"
    draft: list[dict] = field(default_factory=list)
    initial: list[dict] = field(default_factory=list)
    jitter: dict | None = None
    corrected: list[dict] | None = None
    b_initial: float | None = None
    b_jitter: float | None = None
    submissions: list[str] = field(default_factory=list)
    created: float = 0.0
    updated: float = 0.0

    @property
    def table(self) -> int | None:
        return self.tables[self.trial] if self.trial < len(self.tables) else None

    @property
    def scene(self) -> list[dict]:
        """The scene a rating stage shows."""
        if self.stage == "rate_initial":
            return self.initial
        if self.stage == "rate_jitter":
            return self.jitter["placements"] if self.jitter else []
        if self.stage == "rate_correct":
            return self.corrected or []
        return []

    def public(self, min_objects: int, replayed: bool = False) -> dict:
        """What the participant's page is told (docs/collect_api.md "The state")."""
        return {"participant": self.participant, "trial": self.trial, "trials": len(self.tables),
                "table": self.table, "stage": self.stage, "draft": self.draft if self.stage in EDITABLE else [],
                "scene": self.scene, "min_objects": min_objects, "replayed": replayed}


def _placements_json(placements: list[Placement]) -> list[dict]:
    return [p.to_json() for p in placements]


def _as_placements(rows: list[dict]) -> list[Placement]:
    return [Placement(r["object"], r["x"], r["y"], r["rotation"]) for r in rows]


class JsonlLog:
    """A JSON-lines file of the study folder, keyed by (participant, trial): each key written once, atomically."""

    def __init__(self, path: Path):
        self.path = path
        self.keys: set[tuple[str, int]] = set()
        if path.exists():
            for line in path.read_text(encoding="utf-8").splitlines():
                if line.strip():
                    row = json.loads(line)
                    self.keys.add((str(row["participant"]), row["trial"]))

    def append(self, row: dict) -> bool:
        """Write `row` unless its key is there already (then False: a recovered or replayed write)."""
        key = (row["participant"], row["trial"])
        if key in self.keys:
            return False
        old = self.path.read_bytes() if self.path.exists() else b""
        if old and not old.endswith(b"\n"):
            old += b"\n"
        atomic_write_bytes(self.path, old + json.dumps(row, ensure_ascii=False).encode() + b"\n")
        self.keys.add(key)
        return True


class StudyStore:
    """Sessions, steps and writes of one study folder (module docstring). Thread-safe."""

    def __init__(self, study: Study):
        self.study, self.root = study, study.root
        self.folder = self.root / "collect"
        self.people = self.folder / "participants"
        self.people.mkdir(parents=True, exist_ok=True)
        self.arrangements = JsonlLog(self.root / "arrangements.jsonl")
        self.ratings = JsonlLog(self.root / "ratings.jsonl")
        self.selfeval = JsonlLog(self.folder / "self_evaluation.jsonl")
        self._lock = threading.Lock()
        self._states: dict[str, ParticipantState] = {}
        for file in sorted(self.people.glob("*.json")):
            try:
                st = ParticipantState(**read_json(file))
            except TypeError as e:
                raise DegustaError(f"{file}: not a participant state of this version of degusta collect ({e})") from None
            self._states[st.participant] = st
        self._by_token = {st.token_sha256: st.participant for st in self._states.values()}
        self._known = {a.participant for a in study.arrangements} | set(self._states)
        for st in self._states.values():
            self._reconcile(st)

    # -- sessions ---------------------------------------------------------------------------------------------
    def start(self, participant: str | None) -> tuple[str, ParticipantState]:
        """A new session: (its token, the new participant's state). `participant` only when ids are entered."""
        cfg = self.study.config
        with self._lock:
            if cfg.participant_ids == "enter":
                if not isinstance(participant, str) or not ID_PATTERN.fullmatch(participant):
                    raise DegustaError("participant: expected 1-64 letters, digits, '_', '-' or '.' (starting with a "
                                       "letter or digit)")
                if participant in self._known:
                    raise Conflict(f"participant {participant!r} is already in use: ask the researcher")
            else:
                if participant is not None:
                    raise DegustaError("participant: this study assigns participant ids (participant_ids: assign); "
                                       "send {}")
                participant = self._next_id()
            token = secrets.token_urlsafe(32)
            now = time.time()
            st = ParticipantState(participant, token_digest(token), self._tables_for(participant),
                                  created=now, updated=now)
            self._save(st)
            self._states[participant] = st
            self._by_token[st.token_sha256] = participant
            self._known.add(participant)
            return token, st

    def session(self, token: str | None) -> ParticipantState:
        if not token:
            raise NoSession("no session: start one")
        with self._lock:
            pid = self._by_token.get(token_digest(token))
            if pid is None:
                raise NoSession("this session is not known to the study (start a new one)")
            return self._states[pid]

    def _next_id(self) -> str:
        n = 1
        while f"c{n:03d}" in self._known:
            n += 1
        return f"c{n:03d}"

    def _tables_for(self, participant: str) -> list[int]:
        cfg, shown = self.study.config, list(self.study.shown_tables)
        if cfg.table_order == "random":
            digest = hashlib.sha256(f"{cfg.seed}\0{participant}\0tables".encode()).digest()
            rng = np.random.default_rng(int.from_bytes(digest[:8], "little"))
            shown = [shown[i] for i in rng.permutation(len(shown))]
        return shown[:cfg.tables_per_participant]

    # -- steps ------------------------------------------------------------------------------------------------
    def save_draft(self, st: ParticipantState, body: dict) -> None:
        w = Where("draft")
        require_mapping(body, w)
        with self._lock:
            self._expect(st, body, w, EDITABLE)
            st.draft = _placements_json(self._placements(body, w, st, draft=True))
            st.updated = time.time()
            self._save(st)

    def submit(self, st: ParticipantState, body: dict) -> tuple[ParticipantState, bool]:
        """Take one step (docs/collect_api.md); returns (state, replayed)."""
        w = Where("submission")
        require_mapping(body, w)
        sid = get(body, "submission", "str", w)
        if len(sid) > 100:
            raise w.fail("submission", "expected an id of at most 100 characters")
        with self._lock:
            if sid in st.submissions:
                return st, True
            self._expect(st, body, w, STAGES[:-1])
            if st.stage in EDITABLE:
                placements = self._placements(body, w, st, draft=False)
                self._take_placements(st, placements)
            else:
                rating = get(body, "rating", "number", w, lo=0, hi=100)
                self._take_rating(st, rating)
            st.submissions = [*st.submissions, sid][-MAX_SUBMISSION_IDS:]
            st.updated = time.time()
            self._save(st)
            return st, False

    def _expect(self, st: ParticipantState, body: dict, w: Where, stages) -> None:
        trial = get(body, "trial", "int", w, lo=0, hi=10**6)
        stage = get(body, "stage", "str", w)
        if stage not in STAGES:
            raise w.fail("stage", f"unknown stage {stage[:40]!r} (expected one of {', '.join(STAGES)})")
        if st.stage not in stages:
            raise Conflict(f"nothing to {'save' if stages is EDITABLE else 'submit'} at this step ({st.stage}): reload "
                           "the page")
        if (trial, stage) != (st.trial, st.stage):
            raise Conflict(f"this is table {st.trial + 1}, step {st.stage}, not table {trial + 1}, step {stage} "
                           "(another tab moved on): reload the page")

    def _placements(self, body: dict, w: Where, st: ParticipantState, draft: bool) -> list[Placement]:
        items = get(body, "placements", "list", w)
        if len(items) > MAX_OBJECTS:
            raise w.fail("placements", f"{len(items)} objects, more than {MAX_OBJECTS}")
        placements = parse_placements(items, self.study.catalog, w)
        if st.stage == "correct":
            want = {r["object"] for r in st.jitter["placements"]}
            got = {p.object for p in placements}
            if got != want:
                raise w.fail("placements", "a correction moves and turns the jittered objects; it does not add or "
                                           f"remove any (objects {sorted(want)} expected, got {sorted(got)})")
        if draft:
            return placements
        table = self.study.tables[st.table]
        inside = table.contains([p.x for p in placements], [p.y for p in placements])
        for j, (p, ok) in enumerate(zip(placements, inside)):
            if not ok:
                raise w.fail(f"placements[{j}]", f"object {p.object} at ({p.x:.3f}, {p.y:.3f}) is off the surface "
                                                 f"of table {table.id}")
        return placements

    def _take_placements(self, st: ParticipantState, placements: list[Placement]) -> None:
        if st.stage == "arrange":
            row = {"participant": st.participant, "trial": st.trial, "table": st.table,
                   "placements": _placements_json(placements)}
            check_arrangements([(None, row)], Path("submission"), self.study.catalog, self.study.tables,
                                self.study.min_objects)  # the dataset's rules, the study's minimum
            self.arrangements.append(row)
            self._after_arrangement(st, row["placements"])
        else:  # correct
            st.corrected = _placements_json(placements)
            st.jitter = dict(st.jitter, rmsd_correct=displacement_rmsd(placements, _as_placements(st.initial)))
            st.stage, st.draft = "rate_correct", []

    def _after_arrangement(self, st: ParticipantState, placements: list[dict]) -> None:
        st.initial, st.draft = placements, []
        if self.study.config.self_evaluation:
            st.stage = "rate_initial"
        else:
            self._next_trial(st)

    def _take_rating(self, st: ParticipantState, rating: float) -> None:
        cfg = self.study.config
        if st.stage == "rate_initial":
            st.b_initial = rating
            initial = _as_placements(st.initial)
            t, shaken = jittered(initial, cfg.jitter.shift, cfg.jitter.turn, jitter_rng(cfg.seed, st.participant,
                                                                                        st.trial))
            st.jitter = {"t": round(t, 6), "placements": _placements_json(shaken),
                         "rmsd_jitter": displacement_rmsd(shaken, initial)}
            st.stage = "rate_jitter"
        elif st.stage == "rate_jitter":
            st.b_jitter = rating
            st.stage, st.draft = "correct", list(st.jitter["placements"])
        else:  # rate_correct
            row = {"participant": st.participant, "trial": st.trial, "b_initial": st.b_initial,
                   "b_jitter": st.b_jitter, "rmsd_jitter": st.jitter["rmsd_jitter"], "b_correct": rating,
                   "rmsd_correct": st.jitter["rmsd_correct"]}
            check_ratings([(None, row)], Path("submission"))
            self.selfeval.append({**row, "table": st.table, "t": st.jitter["t"], "shift": cfg.jitter.shift,
                                  "turn": cfg.jitter.turn, "initial": st.initial,
                                  "jittered": st.jitter["placements"], "corrected": st.corrected})
            self.ratings.append(row)
            self._next_trial(st)

    @staticmethod
    def _next_trial(st: ParticipantState) -> None:
        st.trial += 1
        st.stage = "arrange" if st.trial < len(st.tables) else "done"
        st.draft, st.initial, st.jitter, st.corrected, st.b_initial, st.b_jitter = [], [], None, None, None, None

    def _reconcile(self, st: ParticipantState) -> None:
        """After a crash between a dataset line and the state: take the step the line records."""
        key = (st.participant, st.trial)
        changed = False
        if st.stage == "arrange" and key in self.arrangements.keys:
            row = next(a for a in self._read_arrangements() if (a["participant"], a["trial"]) == key)
            self._after_arrangement(st, row["placements"])
            changed = True
        if st.stage == "rate_correct" and key in self.ratings.keys:
            self._next_trial(st)
            changed = True
        if changed:
            self._save(st)

    def _read_arrangements(self) -> list[dict]:
        text = self.arrangements.path.read_text(encoding="utf-8")
        return [json.loads(line) for line in text.splitlines() if line.strip()]

    def _save(self, st: ParticipantState) -> None:
        atomic_write_json(self.people / f"{st.participant}.json", asdict(st))

    # -- the researcher's view --------------------------------------------------------------------------------
    def progress(self) -> list[dict]:
        with self._lock:
            return [{"participant": st.participant, "tables_done": min(st.trial, len(st.tables)),
                     "tables": len(st.tables), "stage": st.stage, "finished": st.stage == "done",
                     "started": st.created, "updated": st.updated}
                    for st in sorted(self._states.values(), key=lambda s: s.created)]

    def writing(self):
        """The lock every change holds (an export reads the logs under it: no half-taken step)."""
        return self._lock

    def finished(self) -> set[str]:
        with self._lock:
            return {st.participant for st in self._states.values() if st.stage == "done"}


__all__ = ["EDITABLE", "ID_PATTERN", "STAGES", "Conflict", "JsonlLog", "NoSession", "ParticipantState",
           "StudyStore", "token_digest"]
