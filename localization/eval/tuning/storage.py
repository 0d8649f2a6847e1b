"""Where a study lives: a journal file (``JournalStorage`` + ``JournalFileBackend``, the default) or any
Optuna storage URL (``sqlite:///…``, ``postgresql://…``)."""
from __future__ import annotations

from pathlib import Path

from localization.eval.tuning.errors import TuneError


def make_storage(url: str):
    """An Optuna storage: a URL (``sqlite:///f.db``, ``postgresql://…``) as Optuna reads it, anything
    else a journal file (created on first use; safe for processes sharing the file)."""
    import optuna
    from optuna.storages.journal import JournalFileBackend, JournalStorage

    if "://" in str(url):
        try:
            return optuna.storages.get_storage(str(url))
        except Exception as exc:  # noqa: BLE001 - any driver/connection problem: one line
            raise TuneError(f"cannot open study storage {url}: {' '.join(str(exc).split())[:300]}") from None
    path = Path(url).expanduser()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return JournalStorage(JournalFileBackend(str(path)))
    except OSError as exc:
        raise TuneError(f"cannot open study journal {path}: {exc}") from None
