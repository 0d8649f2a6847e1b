"""Where a study lives: a journal file (``JournalStorage`` + ``JournalFileBackend``, the default) or any
Optuna storage URL (``sqlite:///…``, ``postgresql://…``).

Several tuners may start at once against one fresh PostgreSQL database (one command per machine).
Optuna creates its tables on first use and two processes doing so at once collide (the loser dies of
a unique violation on ``CREATE TYPE``). So against PostgreSQL every tuner takes one advisory lock of
the database (``study_lock``) while it creates the tables, the study, its worker number and the
baseline trial: the tuners take turns for those steps, then run their trials side by side. Other
storages take no lock (the journal file locks each write itself)."""
from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

from localization.eval.tuning.errors import TuneError

#: the key of the PostgreSQL advisory lock (``pg_advisory_lock``) the tuners of one database share
ADVISORY_LOCK_KEY = 0x6C6F632D74756E65  # b"loc-tune"
DRIVER_HINT = "pip install 'localization[distributed]' (the PostgreSQL driver psycopg)"


def is_postgresql(url) -> bool:
    """A PostgreSQL URL (``postgresql://…``, ``postgresql+psycopg2://…``)."""
    scheme = str(url).partition("://")[0] if "://" in str(url) else ""
    return scheme.split("+")[0] == "postgresql"


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:300]


@contextmanager
def study_lock(url):
    """Hold the database's tuner lock while the body runs (yields True) when ``url`` is PostgreSQL: a
    session-level advisory lock on a connection of its own, released when the body ends. Any other
    storage: no lock (yields False). A database that cannot be reached: TuneError (one line)."""
    if not is_postgresql(url):
        yield False
        return
    import sqlalchemy

    try:
        engine = sqlalchemy.create_engine(str(url), poolclass=sqlalchemy.pool.NullPool)
    except ImportError:
        raise TuneError(f"cannot open study storage {url}: no PostgreSQL driver: {DRIVER_HINT}") from None
    except Exception as exc:  # noqa: BLE001 - a malformed URL: one line
        raise TuneError(f"cannot open study storage {url}: {_one_line(exc)}") from None
    try:
        try:
            connection = engine.connect()
            connection.execute(sqlalchemy.text("SELECT pg_advisory_lock(:key)"), {"key": ADVISORY_LOCK_KEY})
        except sqlalchemy.exc.SQLAlchemyError as exc:
            raise TuneError(f"cannot open study storage {url}: {_one_line(exc)}") from None
        try:
            yield True
        finally:
            connection.close()  # the session ends: PostgreSQL releases its advisory lock
    finally:
        engine.dispose()


def make_storage(url: str):
    """An Optuna storage: a URL (``sqlite:///f.db``, ``postgresql://…``) as Optuna reads it, anything
    else a journal file (created on first use; safe for processes sharing the file). Against
    PostgreSQL the tables are created under ``study_lock``."""
    import optuna
    from optuna.storages.journal import JournalFileBackend, JournalStorage

    if "://" in str(url):
        with study_lock(url):
            try:
                return optuna.storages.get_storage(str(url))
            except Exception as exc:  # noqa: BLE001 - any driver/connection problem: one line
                raise TuneError(f"cannot open study storage {url}: {_one_line(exc)}") from None
    path = Path(url).expanduser()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return JournalStorage(JournalFileBackend(str(path)))
    except OSError as exc:
        raise TuneError(f"cannot open study journal {path}: {exc}") from None
