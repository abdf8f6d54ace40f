"""Replay memory D_w of the online SINR map: the most recent measurements, kept in SQLite.

SQLite in WAL mode, so a restarted cloud finds its memory again and a reader never blocks the
writer. Rows are numbered in arrival order (``seq``); the memory keeps the ``capacity`` most
recent arrivals and drops older ones. The upload id is unique: an upload delivered twice is
stored once (as long as the first copy has not been dropped yet). Measurements that break the
scenario's rules are refused and counted per reason (see ``MeasurementSpec.screen``); the
counters persist with the data.

One connection, guarded by a lock, so the bus thread and the retraining worker can share it.

The rows stored most recently are also kept in memory (``RecentRows``): the mapper reads the
uploads since a change again at every job, which SQLite answers by scanning the whole memory
(BENCHMARKS.md, "The cloud's work in the compiled core").
"""

from __future__ import annotations

import math
import sqlite3
import threading
from collections import Counter, deque
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from shared.measurements import Measurement, MeasurementBatch, MeasurementSpec

DEFAULT_CAPACITY = 100_000  # the paper's replay capacity for more than two UAVs
RUN_DIR_FILE = Path("cloud") / "memory.sqlite"  # where the cloud process keeps it in a run dir

_SCHEMA = """
CREATE TABLE IF NOT EXISTS measurements (
    seq INTEGER PRIMARY KEY,
    id TEXT NOT NULL UNIQUE,
    source TEXT NOT NULL,
    step INTEGER NOT NULL,
    time REAL NOT NULL,
    level INTEGER NOT NULL,
    features BLOB NOT NULL,
    sinr_db REAL  -- NULL: the receiver reported the level only
);
CREATE INDEX IF NOT EXISTS measurements_time ON measurements(time);
CREATE TABLE IF NOT EXISTS rejected (reason TEXT PRIMARY KEY, count INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""
_COLUMNS = "id, source, step, time, level, features, sinr_db"
_LOOKUP_CHUNK = 900  # ids per query: below the 999 variables of SQLite builds before 3.32
# Rows per read of ``db_reports``: its reader finds each report's place from its features, whose
# working arrays over a whole memory outgrow the caches (BENCHMARKS.md, "A restarted cloud's
# reference").
_READ_CHUNK = 4096
# Rows kept in memory as well (``RecentRows``): far more than a change's handling reads (it
# settles after 4,000 uploads, RetrainConfig), a few megabytes of features.
RECENT_ROWS_KEPT = 20_000

Uploads = MeasurementBatch | Iterable[Measurement | Mapping]


class DbReports(NamedTuple):
    """Stored reports that carry the SINR: when each was taken, its features, its SINR."""

    times: np.ndarray
    features: np.ndarray
    sinr_db: np.ndarray


class SinrMemory:
    def __init__(self, path: str | Path, spec: MeasurementSpec, capacity: int = DEFAULT_CAPACITY):
        if capacity < 1:
            raise ValueError("capacity must be at least 1")
        self.path = Path(path)
        self.spec = spec
        self.capacity = capacity
        self._lock = threading.Lock()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(self.path, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        # A power cut may lose the last commits but never corrupts the file: fine for a memory
        # that the fleet refills within seconds, and it keeps commits off the disk's fsync.
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(_SCHEMA)
        self._add_reported_sinr()
        self._check_spec()
        self._recent = RecentRows(min(RECENT_ROWS_KEPT, capacity), self.newest_time())

    def _add_reported_sinr(self) -> None:
        """A memory written before reports carried the SINR gets the column, empty: its rows
        read back as level reports."""
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(measurements)")}
        if "sinr_db" not in columns:
            with self._db:
                self._db.execute("ALTER TABLE measurements ADD COLUMN sinr_db REAL")

    def _check_spec(self) -> None:
        want = {"feature_size": str(self.spec.feature_size),
                "level_count": str(self.spec.level_count)}
        with self._db:
            have = dict(self._db.execute("SELECT key, value FROM meta"))
            if have and have != want:
                raise ValueError(f"{self.path}: memory holds measurements of {have}, not {want}")
            self._db.executemany("INSERT OR IGNORE INTO meta VALUES (?, ?)", want.items())

    # -- writing --------------------------------------------------------------------------------
    def append(self, uploads: Uploads) -> tuple[int, int]:
        """Store a batch; returns (accepted, duplicates). Refused rows only bump counters."""
        stored, duplicates = self.store(uploads)
        return len(stored), duplicates

    def store(self, uploads: Uploads) -> tuple[MeasurementBatch, int]:
        """As ``append``, but returns the rows actually stored (new, valid), in order."""
        return self.store_each([uploads])[0]

    def store_each(self, uploads: Sequence[Uploads]) -> list[tuple[MeasurementBatch, int]]:
        """``store`` of each of several uploads, in order, in one transaction: a commit costs
        as much as storing 50 to 100 rows (BENCHMARKS.md, "Fleets of agent processes"), and a
        cloud taking many agents' uploads at once pays it once."""
        if not uploads:
            return []
        screened = [self.spec.screen(batch) if isinstance(batch, MeasurementBatch)
                    else self.spec.from_records(batch) for batch in uploads]
        rejected = sum((counts for _, counts in screened), Counter())
        with self._lock:
            with self._db:
                if rejected:
                    self._db.executemany(
                        "INSERT INTO rejected VALUES (?, ?) "
                        "ON CONFLICT(reason) DO UPDATE SET count = count + excluded.count",
                        rejected.items(),
                    )
                stored = [self._insert(batch) for batch, _ in screened]
                if any(len(new) for new, _ in stored):
                    self._db.execute(
                        "DELETE FROM measurements WHERE seq <= (SELECT MAX(seq) FROM "
                        "measurements) - ?", (self.capacity,))
            # Once committed: a transaction that fails leaves none of its rows here either.
            for new, _ in stored:
                self._recent.add(new)
        return stored

    def _insert(self, batch: MeasurementBatch) -> tuple[MeasurementBatch, int]:
        """Insert the rows of a screened batch the memory does not hold yet: those rows, and
        how many it held."""
        if not len(batch):
            return batch, 0
        fresh = self._fresh_rows(batch.ids)
        new = batch if len(fresh) == len(batch) else batch.take(fresh)
        self._db.executemany(
            f"INSERT INTO measurements ({_COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?)",
            zip(
                new.ids,
                new.sources,
                new.steps.tolist(),
                new.times.tolist(),
                new.levels.tolist(),
                [row.tobytes() for row in new.features],
                [None if math.isnan(db) else db for db in new.sinr_db.tolist()],
                strict=True,
            ),
        )
        return new, len(batch) - len(new)

    def _fresh_rows(self, ids: list[str]) -> np.ndarray:
        """Indices of rows whose id is neither stored yet nor repeated earlier in the batch."""
        seen: set[str] = set()
        for start in range(0, len(ids), _LOOKUP_CHUNK):
            chunk = ids[start : start + _LOOKUP_CHUNK]
            marks = ",".join("?" * len(chunk))
            seen.update(row[0] for row in self._db.execute(
                f"SELECT id FROM measurements WHERE id IN ({marks})", chunk))
        fresh = []
        for index, upload_id in enumerate(ids):
            if upload_id not in seen:
                seen.add(upload_id)
                fresh.append(index)
        return np.array(fresh, dtype=np.int64)

    # -- reading --------------------------------------------------------------------------------
    def count(self) -> int:
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM measurements").fetchone()[0]

    @property
    def rejected(self) -> Counter:
        """Refused measurements per reason, since the file was created."""
        with self._lock:
            return Counter(dict(self._db.execute("SELECT reason, count FROM rejected")))

    def newest_time(self) -> float | None:
        """When the newest stored measurement was taken; None when none is stored."""
        with self._lock:
            return self._db.execute("SELECT MAX(time) FROM measurements").fetchone()[0]

    def db_reports(self, before: float = math.inf,
                   chunk: int = _READ_CHUNK) -> Iterator[DbReports]:
        """The stored reports that carry the SINR, taken before ``before``, in arrival order,
        ``chunk`` at a time: only the columns a reader of the SINR needs, each chunk read
        under the lock, so writers wait for one chunk at most."""
        last_seq = -1
        while True:
            with self._lock:
                rows = self._db.execute(
                    "SELECT seq, time, features, sinr_db FROM measurements "
                    "WHERE seq > ? AND sinr_db IS NOT NULL AND time < ? ORDER BY seq LIMIT ?",
                    (last_seq, before, chunk)).fetchall()
            if not rows:
                return
            seqs, times, blobs, sinr_db = zip(*rows, strict=True)
            last_seq = seqs[-1]
            features = np.frombuffer(b"".join(blobs), dtype=np.float32)
            yield DbReports(np.array(times, dtype=np.float64),
                            features.reshape(len(rows), self.spec.feature_size),
                            np.array(sinr_db, dtype=np.float64))

    def since(self, time: float) -> MeasurementBatch:
        """Stored measurements taken at or after ``time``, in arrival order."""
        with self._lock:
            if self._recent.holds_since(time):
                return self._recent.since(time, self.spec.feature_size)
        return self._select("WHERE time >= ? ORDER BY seq", (time,))

    def recent(self, n: int) -> MeasurementBatch:
        """The ``n`` most recent arrivals, oldest first."""
        batch = self._select("ORDER BY seq DESC LIMIT ?", (max(0, n),))
        return batch.take(np.arange(len(batch))[::-1])

    def sample(self, rng: np.random.Generator, n: int) -> MeasurementBatch:
        """``n`` distinct stored measurements drawn uniformly (all of them if fewer)."""
        with self._lock:
            low, high = self._db.execute("SELECT MIN(seq), MAX(seq) FROM measurements").fetchone()
        if low is None:
            return MeasurementBatch.empty(self.spec.feature_size)
        # Rows are numbered consecutively (only the oldest are ever deleted), so drawing
        # numbers in [low, high] draws rows.
        picked = rng.choice(np.arange(low, high + 1), size=min(n, high - low + 1), replace=False)
        seqs = ",".join(str(int(s)) for s in picked)
        return self._select(f"WHERE seq IN ({seqs})", ())

    def _select(self, clause: str, params: tuple) -> MeasurementBatch:
        with self._lock:
            rows = self._db.execute(f"SELECT {_COLUMNS} FROM measurements {clause}",
                                    params).fetchall()
        if not rows:
            return MeasurementBatch.empty(self.spec.feature_size)
        ids, sources, steps, times, levels, blobs, sinr_db = zip(*rows, strict=True)
        features = np.frombuffer(b"".join(blobs), dtype=np.float32)
        return MeasurementBatch(
            ids=list(ids),
            sources=list(sources),
            steps=np.array(steps, dtype=np.int64),
            times=np.array(times, dtype=np.float64),
            features=features.reshape(len(rows), self.spec.feature_size).copy(),
            levels=np.array(levels, dtype=np.int64),
            sinr_db=np.array([np.nan if db is None else db for db in sinr_db], dtype=np.float64),
        )

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> SinrMemory:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RecentRows:
    """The rows a memory stored most recently, at most ``kept`` of them, in arrival order: all
    the rows taken at or after a time, as SQLite would give them back, when every row taken
    that late is among them. Every stored row not here was taken no later than
    ``older_taken_by``, the latest time of the rows that left and of the memory's rows when it
    opened: the rows taken later are all here. The memory deletes only rows beyond its
    capacity, and ``kept`` is at most that: every row here is stored."""

    def __init__(self, kept: int, older_taken_by: float | None):
        self.kept = kept
        self.older_taken_by = -math.inf if older_taken_by is None else older_taken_by
        # Each stored batch with the earliest and latest time it holds, so that a read looks
        # into only the batches that hold a row late enough.
        self._batches: deque[tuple[MeasurementBatch, float, float]] = deque()
        self._rows = 0

    def add(self, stored: MeasurementBatch) -> None:
        """Keep ``stored`` (rows just stored), in the dtypes SQLite gives back."""
        if not len(stored):
            return
        batch = MeasurementBatch.of_arrays(stored.ids, stored.sources, stored.steps,
                                           stored.times, stored.features, stored.levels,
                                           stored.sinr_db)
        self._batches.append((batch, float(batch.times.min()), float(batch.times.max())))
        self._rows += len(batch)
        while self._rows > self.kept:
            oldest, _, latest = self._batches.popleft()
            self._rows -= len(oldest)
            self.older_taken_by = max(self.older_taken_by, latest)

    def holds_since(self, time: float) -> bool:
        return time > self.older_taken_by

    def since(self, time: float, feature_size: int) -> MeasurementBatch:
        taken = [batch if earliest >= time else batch.take(batch.times >= time)
                 for batch, earliest, latest in self._batches if latest >= time]
        return (MeasurementBatch.concatenate(taken) if taken
                else MeasurementBatch.empty(feature_size))
