"""Where a live reload may read: the service's config directory, nothing else.

A reload (``motcomp reload [--config FILE]``, SIGHUP) is asked for by an operator over the
network; the files it reads are checked here before :func:`motcomp.config.read_toml` opens
them.  The rule, for the file and every file it includes:

- its path, resolved (symlinks and ``..`` followed), lies under the *config directory* (the
  resolved directory of the file the service was started with), or it is one of the files the
  service read at start-up (e.g. a packaged base config included by absolute path: chosen by
  whoever started the service, not by a request);
- it is a regular file (no device, FIFO or ``/proc`` file: it is opened without blocking and
  checked with ``fstat`` before a byte is read), of at most :data:`MAX_CONFIG_BYTES`;
- at most :data:`MAX_CONFIG_FILES` files in all.

A path outside is refused with one message whether it exists or not, naming the request key or
the include and the rule, never anything read from it.  A relative reload path is taken from
the config directory.  Whoever can write into the config directory can change what a reload
reads (between this check and the read, too): keep it writable by root only (DEPLOYMENT.md).
"""

from __future__ import annotations

import os
import stat
import tomllib
from collections.abc import Iterable
from pathlib import Path

from motcomp.errors import ConfigError

__all__ = ["MAX_CONFIG_BYTES", "MAX_CONFIG_FILES", "Confinement"]

MAX_CONFIG_BYTES = 1 << 20
"""Largest config file a reload reads (1 MiB; the example config with its includes is ~20 kB)."""
MAX_CONFIG_FILES = 32
"""Most files one reload reads (the file and its includes)."""


def _shown(text: str) -> str:
    """A requested name for a message: quoted, at most 200 characters."""
    return repr(text if len(text) <= 200 else text[:200] + "...")


class Confinement:
    """The config directory of a service started with ``start_file`` and the files it read at
    start-up (``start_files``; resolved paths)."""

    def __init__(self, start_file: str | Path, start_files: Iterable[Path] = ()) -> None:
        self.root = Path(start_file).resolve().parent
        self.trusted = frozenset(Path(f).resolve() for f in start_files)

    def rule(self) -> str:
        return (f"a reload reads only regular files of at most {MAX_CONFIG_BYTES} bytes under "
                f"the config directory {self.root} (resolved: no symlink or '..' out of it) "
                "and the files the service read at start-up")

    def allowed(self, real: Path) -> bool:
        """``real`` (a resolved path) lies under the config directory or was read at start."""
        return real in self.trusted or real.is_relative_to(self.root)

    def locate(self, path: str | Path, what: str) -> Path:
        """The resolved path of ``path`` (relative: to the config directory) if it is allowed.

        Raises
        ------
        ConfigError
            ``"<what> <path>: refused: <rule>"``; the same whether the file exists or not.
        """
        p = Path(path)
        real = Path(os.path.realpath(p if p.is_absolute() else self.root / p))
        if not self.allowed(real):
            raise ConfigError(f"{what} {_shown(str(path))}: refused: {self.rule()}")
        return real

    def read(self, real: Path) -> bytes:
        """The content of the allowed file ``real``: a regular file, read up to the size cap.

        Raises
        ------
        ConfigError
            Not readable, not a regular file or larger than :data:`MAX_CONFIG_BYTES`.
        """
        try:
            fd = os.open(real, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | os.O_CLOEXEC)
        except OSError as exc:
            raise ConfigError(f"{real}: cannot read: {exc.strerror}") from None
        with os.fdopen(fd, "rb") as f:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise ConfigError(f"{real}: refused: not a regular file ({self.rule()})")
            if st.st_size > MAX_CONFIG_BYTES:
                raise ConfigError(f"{real}: refused: {st.st_size} bytes ({self.rule()})")
            data = f.read(MAX_CONFIG_BYTES + 1)
        if len(data) > MAX_CONFIG_BYTES:
            raise ConfigError(f"{real}: refused: more than {MAX_CONFIG_BYTES} bytes "
                              f"({self.rule()})")
        return data

    def check(self, path: str | Path, what: str = "reload path") -> Path:
        """Check ``path`` and every file it includes (read as :func:`motcomp.config.read_toml`
        reads them: relative to the including file); returns the resolved ``path`` to read.

        A file that is not TOML or has a bad ``include`` value passes here: ``read_toml`` says
        what is wrong with it (it is under the config directory or was read at start-up).

        Raises
        ------
        ConfigError
            A file outside the confinement, not a regular file, too large, or too many files.
        """
        top = self.locate(path, what)
        todo: list[tuple[Path, Path | None]] = [(top, None)]  # a file, and the file including it
        seen: set[Path] = set()
        while todo:
            real, by = todo.pop()
            if real in seen:
                continue  # a cycle: read_toml names it
            seen.add(real)
            if len(seen) > MAX_CONFIG_FILES:
                raise ConfigError(f"{top}: refused: more than {MAX_CONFIG_FILES} files with its "
                                  "includes")
            try:
                data = tomllib.loads(self.read(real).decode())
            except (UnicodeDecodeError, tomllib.TOMLDecodeError):
                continue
            except ConfigError as exc:
                if by is None:
                    raise
                raise ConfigError(f"{exc} (included by {by})") from None
            inc = data.get("include", [])
            names = [inc] if isinstance(inc, str) else inc if isinstance(inc, list) else []
            for name in names:
                if isinstance(name, str):
                    todo.append((self.locate(real.parent / name, f"{real}: include"), real))
        return top
