"""Configuration in one place: limits, paths and the astropy set-up.

Every value can be overridden by an environment variable named in
:class:`Settings`; the CLI and the server read the same settings.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field
from pathlib import Path


def _cache_dir() -> Path:
    base = os.environ.get("STARID_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "starid")
    return Path(base)


@dataclass(frozen=True)
class Settings:
    #: Largest telemetry file accepted (STARID_MAX_UPLOAD_BYTES).
    max_upload_bytes: int = field(
        default_factory=lambda: int(os.environ.get("STARID_MAX_UPLOAD_BYTES", 5 * 1024 * 1024)))
    #: Where the bright-pair index and other derived data are cached (STARID_CACHE_DIR).
    cache_dir: Path = field(default_factory=_cache_dir)
    #: Camera used for files without a camera block (STARID_DEFAULT_CAMERA).
    default_camera: str = field(
        default_factory=lambda: os.environ.get("STARID_DEFAULT_CAMERA", "tubsat-752x582-20deg"))
    # Every setting is read when Settings() is made (not at import), so a
    # test or a launcher can set the environment first.
    #: Database path or URL for `serve` and `batch` (STARID_DB, else DATABASE_URL); None: the storage
    #: default (SQLite in ~/.local/share/starid).  ``postgresql://user:password@host:port/db`` selects
    #: the PostgreSQL archive several servers can share.
    database: str | None = field(
        default_factory=lambda: os.environ.get("STARID_DB") or os.environ.get("DATABASE_URL") or None)
    #: Most connections one process keeps to a PostgreSQL archive (STARID_DB_POOL_SIZE): each method
    #: holds one for its transaction only (about a millisecond), so a few serve many request threads.
    database_pool_size: int = field(
        default_factory=lambda: max(1, int(os.environ.get("STARID_DB_POOL_SIZE", "8"))))
    #: Bearer tokens "token1=alice,token2=bob" (STARID_TOKENS).
    tokens: str = field(default_factory=lambda: os.environ.get("STARID_TOKENS", ""))
    #: File of "token operator" lines (STARID_TOKENS_FILE); None: no file.
    tokens_file: str | None = field(default_factory=lambda: os.environ.get("STARID_TOKENS_FILE") or None)
    #: The time-out users see, seconds (STARID_SEARCH_TIMEOUT_S): a search or an upload is answered
    #: within it, with its result or with 503 (nothing stored); it is also the wall-clock budget of
    #: one identification run.
    search_timeout_s: float = field(
        default_factory=lambda: float(os.environ.get("STARID_SEARCH_TIMEOUT_S", "5.0")))
    #: Searches run at once; more wait in line (STARID_SEARCH_WORKERS; default: one per core).
    search_workers: int = field(
        default_factory=lambda: int(os.environ.get("STARID_SEARCH_WORKERS", "0")) or os.cpu_count() or 1)
    #: Searches run in worker processes, one per search worker, so that they use every core
    #: (STARID_SEARCH_PROCESSES=0: in threads of the server process).
    search_processes: bool = field(
        default_factory=lambda: os.environ.get("STARID_SEARCH_PROCESSES", "1") not in ("0", "false", "no"))
    #: Worker processes for large uploads (more than app.workflow.archive.LARGE_UPLOAD_SOURCES
    #: sources), apart from the search workers and at a lower CPU priority, so that worst-case
    #: files never hold up ordinary searches (STARID_BULK_WORKERS, at least 1).
    bulk_workers: int = field(default_factory=lambda: max(1, int(os.environ.get("STARID_BULK_WORKERS", "1"))))
    #: Processes that compile the numba kernels on a first run, the first included (STARID_COMPILE_PROCESSES;
    #: default 0: one per core this process may use, at most 4; see app.compiled).
    compile_processes: int = field(default_factory=lambda: max(0, int(os.environ.get("STARID_COMPILE_PROCESSES", "0"))))


    @property
    def search_budget_s(self) -> float:
        """The identification's own wall-clock budget inside the time-out users see (60 % of it).

        A search that uses its whole budget must still be answered within
        ``search_timeout_s``, after waiting for a worker and before its result
        is stored; with the budget equal to the time-out it never would be.
        """
        return 0.6 * self.search_timeout_s


MAX_SNAPSHOTS = 64
MAX_SOURCES_PER_SNAPSHOT = 64


def settings() -> Settings:
    return Settings()


@functools.lru_cache(maxsize=1)
def configure_astropy() -> None:
    """No network here or at ground stations: never let astropy download.

    Uses the IERS tables bundled with astropy and the `builtin` ephemeris.
    """
    from astropy.utils import iers

    iers.conf.auto_download = False
    iers.conf.auto_max_age = None
    iers.conf.iers_degraded_accuracy = "warn"
