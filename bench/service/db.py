"""The service's database: SQLAlchemy 2 models, the engine (SQLite in WAL mode by default, PostgreSQL by URL) and
the Alembic migrations run at startup.

Times are stored as UTC epoch seconds (float): the same comparisons on SQLite and PostgreSQL, no time zone lost.
"""

from __future__ import annotations

import datetime as dt
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from sqlalchemy import (JSON, BigInteger, Boolean, Float, ForeignKey, Index, Integer, String, Text, create_engine,
                        event, inspect, text, update)
from sqlalchemy.engine import Engine, make_url
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, sessionmaker

ALEMBIC_DIR = Path(__file__).resolve().parent / "alembic"
FINAL_STATES = ("pass", "fail", "aborted", "error", "cancelled")
STATES = ("queued", "running", *FINAL_STATES)


def now() -> float:
    return time.time()


def iso(ts: float | None) -> str | None:
    if ts is None:
        return None
    return dt.datetime.fromtimestamp(ts, dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class Base(DeclarativeBase):
    pass


class Token(Base):
    __tablename__ = "tokens"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    role: Mapped[str] = mapped_column(String(20))
    sha256: Mapped[str] = mapped_column(String(64), unique=True, index=True)   # never the token itself
    created_ts: Mapped[float] = mapped_column(Float, default=now)
    revoked: Mapped[bool] = mapped_column(Boolean, default=False)


class Rig(Base):
    """Mirrors config/rigs.toml (synced at startup); `lock_seq` is bumped to take the rig's row lock."""
    __tablename__ = "rigs"
    name: Mapped[str] = mapped_column(String(200), primary_key=True)
    bench: Mapped[str] = mapped_column(Text)
    tags: Mapped[list] = mapped_column(JSON, default=list)
    simulated: Mapped[bool] = mapped_column(Boolean)
    max_concurrent: Mapped[int] = mapped_column(Integer, default=1)
    enabled: Mapped[bool] = mapped_column(Boolean, default=True)
    lock_seq: Mapped[int] = mapped_column(Integer, default=0)


class Run(Base):
    __tablename__ = "runs"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    state: Mapped[str] = mapped_column(String(20), index=True)
    verdict: Mapped[str | None] = mapped_column(String(20))
    rig: Mapped[str | None] = mapped_column(String(200), index=True)
    tag: Mapped[str | None] = mapped_column(String(200))
    candidates: Mapped[list | None] = mapped_column(JSON)   # rigs of the tag the scenario fits (drive kind, validation)
    scenario: Mapped[str] = mapped_column(Text)            # as submitted: a path under the root, or "scenario_toml"
    scenario_file: Mapped[str] = mapped_column(Text)       # the file the run process reads
    scenario_name: Mapped[str | None] = mapped_column(String(300), index=True)
    scenario_sha256: Mapped[str | None] = mapped_column(String(64))
    seed: Mapped[int | None] = mapped_column(BigInteger)     # seeds go up to 2**63 - 1
    owner: Mapped[str] = mapped_column(String(200))
    owner_token_id: Mapped[int | None] = mapped_column(Integer)
    submitted_ts: Mapped[float] = mapped_column(Float, default=now)
    started_ts: Mapped[float | None] = mapped_column(Float)
    ended_ts: Mapped[float | None] = mapped_column(Float)
    duration_s: Mapped[float | None] = mapped_column(Float)
    progress_s: Mapped[float | None] = mapped_column(Float)
    scenario_duration_s: Mapped[float | None] = mapped_column(Float)
    host: Mapped[str | None] = mapped_column(String(200))   # the service instance that runs it (its --host-id)
    instance_id: Mapped[int | None] = mapped_column(Integer, index=True)   # that instance's incarnation
    pid: Mapped[int | None] = mapped_column(Integer)
    pid_start: Mapped[int | None] = mapped_column(BigInteger)   # the run process's start time (tells pid reuse)
    run_dir: Mapped[str | None] = mapped_column(Text)
    reason: Mapped[str | None] = mapped_column(Text)
    abort_requested_by: Mapped[str | None] = mapped_column(String(200))
    aborted_by: Mapped[str | None] = mapped_column(String(200))
    drive: Mapped[dict | None] = mapped_column(JSON)
    firmware_version: Mapped[str | None] = mapped_column(String(200))
    revision: Mapped[str | None] = mapped_column(String(64), index=True)
    software: Mapped[dict | None] = mapped_column(JSON)
    criteria: Mapped[list | None] = mapped_column(JSON)


class RunCandidate(Base):
    """A rig a queued run submitted by tag may start on (the scheduler asks per free rig, in SQL)."""
    __tablename__ = "run_candidates"
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True)
    rig: Mapped[str] = mapped_column(String(200), primary_key=True, index=True)


class CriterionValue(Base):
    """One criterion of one finished run: the trend plot queries these."""
    __tablename__ = "criterion_values"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(300), index=True)
    signal: Mapped[str | None] = mapped_column(String(200))
    value: Mapped[float | None] = mapped_column(Float)
    limit: Mapped[float | None] = mapped_column(Float)
    passed: Mapped[bool] = mapped_column(Boolean)
    status: Mapped[str | None] = mapped_column(String(20))


ONE_RUN_WHERE = "kind = 'run' AND exclusive_rig AND released_ts IS NULL"
LIVE_INSTANCE_WHERE = "stopped_ts IS NULL"


class Lease(Base):
    """A hold of a rig that ends at expires_ts unless extended: a run's or a person's (kind manual)."""
    __tablename__ = "leases"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    rig: Mapped[str] = mapped_column(ForeignKey("rigs.name"), index=True)
    holder: Mapped[str] = mapped_column(String(200))
    kind: Mapped[str] = mapped_column(String(20))           # run | manual
    run_id: Mapped[int | None] = mapped_column(Integer)
    reason: Mapped[str | None] = mapped_column(Text)
    created_ts: Mapped[float] = mapped_column(Float, default=now)
    expires_ts: Mapped[float] = mapped_column(Float, index=True)
    released_ts: Mapped[float | None] = mapped_column(Float)
    released_by: Mapped[str | None] = mapped_column(String(200))
    # a run's lease on a real rig: until released (not merely expired) no other run may claim the rig, and the
    # database itself refuses a second one (unique index below), whatever two services decide at once
    exclusive_rig: Mapped[bool] = mapped_column(Boolean, default=False, server_default=text("false"))

    __table_args__ = (Index("ux_leases_one_run_per_real_rig", "rig", unique=True,
                            sqlite_where=text(ONE_RUN_WHERE), postgresql_where=text(ONE_RUN_WHERE)),)

    def active(self, at: float | None = None) -> bool:
        return self.released_ts is None and self.expires_ts > (now() if at is None else at)


class RigProbe(Base):
    """One `drivebench probe` of a rig started from the service: what the drive said about itself (identity, units,
    PDOs) and the checklist built from it, or why the probe failed. The rig page shows the newest."""
    __tablename__ = "rig_probes"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    rig: Mapped[str] = mapped_column(ForeignKey("rigs.name"), index=True)
    by: Mapped[str] = mapped_column(String(200))
    started_ts: Mapped[float] = mapped_column(Float)
    ended_ts: Mapped[float] = mapped_column(Float)
    exit_code: Mapped[int | None] = mapped_column(Integer)      # the probe process's; None: it did not start or end
    report: Mapped[dict | None] = mapped_column(JSON)           # `probe --json`: {"bench", "drive", "checklist"}
    error: Mapped[str | None] = mapped_column(Text)             # the probe's own one-line reasons when it failed


class Instance(Base):
    """One start of `drivebench serve` (an incarnation): its own liveness lease, renewed by the runner loop.
    At most one live instance per name (--host-id): the unique index refuses a second one even under a race."""
    __tablename__ = "service_instances"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200), index=True)
    hostname: Mapped[str] = mapped_column(String(255))
    boot_id: Mapped[str | None] = mapped_column(String(64))   # boot id/pid namespace: with the host name, where its
                                                               # pids can be checked
    pid: Mapped[int] = mapped_column(Integer)
    pid_start: Mapped[int | None] = mapped_column(BigInteger)
    started_ts: Mapped[float] = mapped_column(Float, default=now)
    heartbeat_ts: Mapped[float] = mapped_column(Float)
    expires_ts: Mapped[float] = mapped_column(Float)
    stopped_ts: Mapped[float | None] = mapped_column(Float)
    stopped_by: Mapped[str | None] = mapped_column(String(200))

    __table_args__ = (Index("ux_instances_live_name", "name", unique=True, sqlite_where=text(LIVE_INSTANCE_WHERE),
                            postgresql_where=text(LIVE_INSTANCE_WHERE)),)


# --- engine --------------------------------------------------------------------------------------------

def default_url(data_dir: Path) -> str:
    return f"sqlite:///{(Path(data_dir) / 'drivebench.sqlite').resolve()}"


def normalize_url(url: str) -> str:
    """postgresql:// without a driver means psycopg 3 (the driver the [service] extra installs)."""
    parsed = make_url(url)
    if parsed.drivername in ("postgresql", "postgres"):
        parsed = parsed.set(drivername="postgresql+psycopg")
    return parsed.render_as_string(hide_password=False)


def make_engine(url: str) -> Engine:
    url = normalize_url(url)
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30},
                               pool_size=10, max_overflow=20)

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn, _record):
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")      # readers never wait for the writer
            cur.execute("PRAGMA synchronous=NORMAL")    # WAL + NORMAL: durable across a process crash
            cur.execute("PRAGMA busy_timeout=30000")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)


def migrate(engine: Engine) -> None:
    """Bring the schema to the newest Alembic revision (the migrations ship inside the package)."""
    from alembic import command
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(ALEMBIC_DIR))
    with engine.begin() as conn:
        cfg.attributes["connection"] = conn
        command.upgrade(cfg, "head")


def schema_tables(engine: Engine) -> set[str]:
    return set(inspect(engine).get_table_names())


class Database:
    def __init__(self, url: str):
        self.url = normalize_url(url)
        self.engine = make_engine(self.url)
        self.sessions = sessionmaker(self.engine, expire_on_commit=False)

    @property
    def is_sqlite(self) -> bool:
        return self.url.startswith("sqlite")

    @contextmanager
    def session(self) -> Iterator[Session]:
        with self.sessions() as s:
            with s.begin():
                yield s

    def lock_rig(self, s: Session, name: str) -> bool:
        """Serialise lease decisions on one rig: a write to its row takes SQLite's write lock or PostgreSQL's
        row lock until the transaction ends, so two services cannot both see the rig free."""
        return s.execute(update(Rig).where(Rig.name == name).values(lock_seq=Rig.lock_seq + 1)).rowcount == 1

    def dispose(self) -> None:
        self.engine.dispose()


def open_database(url: str) -> Database:
    db = Database(url)
    migrate(db.engine)
    return db


def as_dict(obj: Any) -> dict:
    return {c.key: getattr(obj, c.key) for c in inspect(obj).mapper.column_attrs}
