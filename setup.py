"""The wheel carries the repository's ``config/`` as ``motcomp/_config`` (see
motcomp/resources.py); everything else is in pyproject.toml.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent


class BuildPyWithConfig(build_py):
    """Copy config/ into the built package as motcomp/_config."""

    def run(self) -> None:
        super().run()
        if not self.editable_mode:
            target = Path(self.build_lib) / "motcomp" / "_config"
            shutil.rmtree(target, ignore_errors=True)
            shutil.copytree(ROOT / "config", target)


setup(cmdclass={"build_py": BuildPyWithConfig})
