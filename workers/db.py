"""A small portable SQL layer: SQLite (WAL mode) by default, PostgreSQL through psycopg.

Queries are written once with ``?`` placeholders and portable SQL (no RETURNING, no UPSERT);
the PostgreSQL connection rewrites placeholders to ``%s``. One connection per thread.
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlparse


class DatabaseError(RuntimeError):
    """The job database cannot be opened or reached."""


class IntegrityConflict(Exception):
    """A unique constraint refused a write (an active job exists, a key is taken ...)."""


class Tx:
    """An open transaction: run statements, read rows as dicts."""

    def __init__(self, cursor, paramstyle: str):
        self._cur = cursor
        self._pg = paramstyle == "pg"

    def _sql(self, sql: str) -> str:
        return sql.replace("?", "%s") if self._pg else sql

    def execute(self, sql: str, params: Sequence[Any] = ()) -> int:
        self._cur.execute(self._sql(sql), tuple(params))
        return self._cur.rowcount

    def one(self, sql: str, params: Sequence[Any] = ()) -> dict | None:
        self._cur.execute(self._sql(sql), tuple(params))
        row = self._cur.fetchone()
        if row is None:
            return None
        return dict(zip([d[0] for d in self._cur.description], row))

    def columns(self, table: str) -> list[str]:
        """Column names of ``table`` (portable: an empty SELECT's description)."""
        self._cur.execute(f"SELECT * FROM {table} WHERE 1 = 0")
        names = [d[0] for d in self._cur.description]
        self._cur.fetchall()
        return names

    def all(self, sql: str, params: Sequence[Any] = ()) -> list[dict]:
        self._cur.execute(self._sql(sql), tuple(params))
        names = [d[0] for d in self._cur.description]
        return [dict(zip(names, row)) for row in self._cur.fetchall()]


class Database:
    """``sqlite:///abs/path.db`` or ``postgresql://...``; :meth:`tx` opens a transaction."""

    def __init__(self, url: str):
        self.url = url
        parsed = urlparse(url)
        if parsed.scheme == "sqlite":
            # sqlite:///abs/path -> path "/abs/path"; sqlite:////abs also tolerated.
            self.kind = "sqlite"
            self.path = Path(parsed.path if parsed.netloc == "" else parsed.netloc + parsed.path)
            if str(self.path) in ("", "/"):
                raise DatabaseError(f"database_url {url!r} names no file (expected sqlite:///path.db)")
        elif parsed.scheme in ("postgresql", "postgres"):
            self.kind = "postgresql"
            self.path = None
        else:
            raise DatabaseError(
                f"database_url: expected sqlite:///PATH or postgresql://..., got scheme {parsed.scheme!r}"
            )
        self._local = threading.local()

    def _connect(self):
        if self.kind == "sqlite":
            self.path.parent.mkdir(parents=True, exist_ok=True)
            conn = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")
            conn.execute("PRAGMA busy_timeout=30000")
            return conn
        try:
            import psycopg
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise DatabaseError(
                "database_url is postgresql:// but psycopg is not installed (pip install 'psycopg[binary]')"
            ) from exc
        return psycopg.connect(self.url, autocommit=True)

    def _conn(self):
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._connect()
            self._local.conn = conn
        return conn

    def close(self) -> None:
        conn = getattr(self._local, "conn", None)
        if conn is not None:
            conn.close()
            self._local.conn = None

    @contextmanager
    def tx(self, *, write: bool = True) -> Iterator[Tx]:
        """One transaction; commits on success, rolls back on any exception.

        A unique-constraint violation surfaces as :class:`IntegrityConflict`.
        ``write=False`` marks a read-only transaction (on SQLite it takes no write lock).
        """
        conn = self._conn()
        try:
            if self.kind == "sqlite":
                # IMMEDIATE takes the write lock up front, so read-then-write sequences
                # (sweeper, claims) cannot interleave between processes; WAL readers never wait.
                conn.execute("BEGIN IMMEDIATE" if write else "BEGIN")
                cur = conn.cursor()
                try:
                    yield Tx(cur, "qmark")
                except BaseException:
                    conn.execute("ROLLBACK")
                    raise
                conn.execute("COMMIT")
            else:
                with conn.transaction():
                    yield Tx(conn.cursor(), "pg")
        except sqlite3.IntegrityError as exc:
            raise IntegrityConflict(str(exc)) from exc
        except sqlite3.OperationalError as exc:
            raise DatabaseError(f"job database {self.url}: {exc}") from exc
        except Exception as exc:
            if type(exc).__module__.startswith("psycopg"):
                import psycopg

                if isinstance(exc, psycopg.IntegrityError):
                    raise IntegrityConflict(str(exc)) from exc
                if isinstance(exc, psycopg.OperationalError):
                    self.close()
                    raise DatabaseError(f"job database: {exc}") from exc
            raise

    def ping(self) -> None:
        with self.tx(write=False) as tx:
            tx.one("SELECT 1 AS ok")
