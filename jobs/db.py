"""The job database through SQLAlchemy Core 2.x: SQLite (WAL) by default, PostgreSQL via psycopg 3.

:class:`Database` owns one engine (a connection pool) and hands out transactions with
:meth:`Database.tx`; the statements themselves live in :mod:`jobs.store` as Core
expressions, so no SQL text is rewritten per dialect.

Write transactions serialise where the job layer needs it:

* SQLite: a write transaction starts with ``BEGIN IMMEDIATE`` (the write lock up front), so
  read-then-write sequences cannot interleave between processes; WAL readers never wait.
* PostgreSQL: READ COMMITTED; the few read-then-write sequences whose outcome depends on
  other rows (the queue limit, schema upgrades) take a transaction-scoped advisory lock
  (:meth:`Tx.lock`), single-row transitions are one conditional ``UPDATE``.
"""

from __future__ import annotations

import sqlite3
import time
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy import exc as sa_exc
from sqlalchemy.engine import make_url

BUSY_TIMEOUT_S = 30.0
"""How long a SQLite connection waits for another's lock (busy_timeout, and the WAL switch's retries)."""


class DatabaseError(RuntimeError):
    """The job database cannot be opened or reached."""


class IntegrityConflict(Exception):
    """A unique constraint refused a write (an active job exists, a key is taken ...)."""


def _engine_url(url: str) -> tuple[str, sa.URL]:
    """``sqlite:///abs/path.db`` or ``postgresql://...`` (also ``postgres://`` and
    ``postgresql+psycopg://``) -> (kind, SQLAlchemy URL with the psycopg 3 driver)."""
    try:
        parsed = make_url(url)
    except sa_exc.ArgumentError as exc:
        raise DatabaseError(f"database_url {url!r} is not a database URL: {exc}") from None
    backend, _, driver = parsed.drivername.partition("+")
    if backend == "sqlite":
        if driver:
            raise DatabaseError(f"database_url: use plain sqlite:///PATH, got {parsed.drivername!r}")
        if not parsed.database or parsed.database in ("/", ":memory:"):
            raise DatabaseError(f"database_url {url!r} names no file (expected sqlite:///path.db)")
        return "sqlite", parsed
    if backend in ("postgresql", "postgres"):
        if driver not in ("", "psycopg"):
            raise DatabaseError(f"database_url: only the psycopg (3) driver is supported, got {driver!r}")
        return "postgresql", parsed.set(drivername="postgresql+psycopg")
    raise DatabaseError(
        f"database_url: expected sqlite:///PATH or postgresql://..., got scheme {parsed.drivername!r}"
    )


class Tx:
    """An open transaction: a SQLAlchemy Connection plus helpers that return plain dicts."""

    def __init__(self, conn: sa.Connection, kind: str):
        self.conn, self.kind = conn, kind

    def execute(self, statement, params: dict | None = None) -> sa.CursorResult:
        return self.conn.execute(statement, params or {})

    def one(self, statement, params: dict | None = None) -> dict | None:
        row = self.conn.execute(statement, params or {}).mappings().first()
        return None if row is None else dict(row)

    def all(self, statement, params: dict | None = None) -> list[dict]:
        return [dict(r) for r in self.conn.execute(statement, params or {}).mappings()]

    def scalar(self, statement, params: dict | None = None) -> Any:
        return self.conn.execute(statement, params or {}).scalar()

    def lock(self, name: str) -> None:
        """Serialise this transaction with every other one that locks ``name`` (until it ends).

        PostgreSQL: ``pg_advisory_xact_lock``. SQLite: a write transaction already holds
        the database's only write lock (``BEGIN IMMEDIATE``), so nothing more is needed.
        """
        if self.kind == "postgresql":
            key = zlib.crc32(f"roguenerf:{name}".encode()) - (1 << 31)
            self.conn.execute(sa.select(sa.func.pg_advisory_xact_lock(key)))


class Database:
    """``sqlite:///abs/path.db`` or ``postgresql://...``; :meth:`tx` opens a transaction."""

    def __init__(self, url: str):
        self.url = url
        self.kind, engine_url = _engine_url(url)
        self.path: Path | None = None
        if self.kind == "sqlite":
            self.path = Path(engine_url.database)
            self.engine = sa.create_engine(engine_url, connect_args={"timeout": 30.0},
                                           pool_size=8, max_overflow=32)
            self._sqlite_events()
        else:
            try:
                import psycopg  # noqa: F401
            except ImportError as exc:  # pragma: no cover - depends on the environment
                raise DatabaseError(
                    "database_url is postgresql:// but psycopg is not installed "
                    "(pip install 'roguenerf[postgresql]' or 'psycopg[binary]')"
                ) from exc
            # pre_ping: a restarted PostgreSQL must not leave dead pooled connections behind.
            self.engine = sa.create_engine(engine_url, pool_pre_ping=True, pool_size=8,
                                           max_overflow=32, pool_timeout=60)

    def _sqlite_events(self) -> None:
        @event.listens_for(self.engine, "connect")
        def _connect(dbapi_conn, record):
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # The driver must not open transactions on its own: we emit BEGIN ourselves.
            dbapi_conn.isolation_level = None
            cur = dbapi_conn.cursor()
            cur.execute(f"PRAGMA busy_timeout={int(BUSY_TIMEOUT_S * 1000)}")  # first: the pragmas below may wait
            # Switching a new database to WAL needs it to itself, and SQLite answers "database is
            # locked" at once, without the busy timeout, when processes starting together collide
            # here: retry for as long as the busy timeout would have waited.
            deadline, pause = time.monotonic() + BUSY_TIMEOUT_S, 0.01
            while True:
                try:
                    cur.execute("PRAGMA journal_mode=WAL")
                    break
                except sqlite3.OperationalError as exc:
                    if "locked" not in str(exc) or time.monotonic() > deadline:
                        raise
                    time.sleep(pause)
                    pause = min(pause * 2, 0.25)
            cur.execute("PRAGMA synchronous=NORMAL")
            cur.close()

        @event.listens_for(self.engine, "begin")
        def _begin(conn):
            write = conn.get_execution_options().get("roguenerf_write", True)
            conn.exec_driver_sql("BEGIN IMMEDIATE" if write else "BEGIN")

    def close(self) -> None:
        """Close the pooled connections (the engine stays usable; it reconnects on demand)."""
        self.engine.dispose()

    @contextmanager
    def tx(self, *, write: bool = True) -> Iterator[Tx]:
        """One transaction; commits on success, rolls back on any exception.

        A unique-constraint violation surfaces as :class:`IntegrityConflict`, an unreachable
        or locked database as :class:`DatabaseError`. ``write=False`` marks a read-only
        transaction (on SQLite it takes no write lock).
        """
        try:
            with self.engine.connect() as conn:
                conn = conn.execution_options(roguenerf_write=write)
                with conn.begin():
                    yield Tx(conn, self.kind)
        except sa_exc.IntegrityError as exc:
            raise IntegrityConflict(str(exc.orig)) from exc
        except (sa_exc.OperationalError, sa_exc.InterfaceError) as exc:
            raise DatabaseError(f"job database {self._safe_url()}: {exc.orig}") from exc
        except sa_exc.TimeoutError as exc:
            raise DatabaseError(f"job database {self._safe_url()}: {exc}") from exc

    def _safe_url(self) -> str:
        return make_url(self.url).render_as_string(hide_password=True)

    def ping(self) -> None:
        with self.tx(write=False) as tx:
            tx.scalar(sa.select(sa.literal(1)))
