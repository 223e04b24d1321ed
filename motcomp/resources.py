"""Where motcomp finds its shipped files (plant presets, example configs, the DBC, units).

In a source checkout or an editable install they are the repository's ``config/``; a wheel
carries a copy as ``motcomp/_config``.  ``MOTCOMP_CONFIG_DIR`` overrides both.
"""

from __future__ import annotations

import os
from pathlib import Path

from motcomp.errors import ConfigError

__all__ = ["config_dir", "config_file"]


def config_dir() -> Path:
    """The directory holding motcomp's shipped configuration files."""
    env = os.environ.get("MOTCOMP_CONFIG_DIR")
    if env:
        return Path(env)
    here = Path(__file__).resolve().parent
    packaged = here / "_config"
    if packaged.is_dir():
        return packaged
    return here.parent / "config"


def config_file(*parts: str) -> Path:
    """Path of a shipped file, e.g. ``config_file("plants", "rails.toml")``.

    Raises
    ------
    ConfigError
        If the file does not exist.
    """
    path = config_dir().joinpath(*parts)
    if not path.is_file():
        raise ConfigError(f"shipped file {'/'.join(parts)} not found in {config_dir()}")
    return path
