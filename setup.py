"""Build of the compiled tick: the compensator (motcomp/core/_ckernel.c), the reference shaper's
per-axis loops (motcomp/runtime/_cshaper.c) and the service's input parsing and output packing
(motcomp/io/_cwire.c); everything else is in pyproject.toml.

The extensions are optional: without a C compiler the install still succeeds, the compensator
runs its pure-Python reference kernel (``motcomp config check`` and the service's status say
which kernel runs) and the wire codec falls back to msgpack-python.  ``-ffp-contract=off`` keeps
the compiler from fusing multiply-adds, so the compiled kernels' results stay bit-identical to
the Python reference.

The wheel also carries the repository's ``config/`` as ``motcomp/_config``
(see motcomp/resources.py).
"""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import Extension, setup
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


setup(
    ext_modules=[
        Extension(
            "motcomp.core._ckernel",
            sources=["motcomp/core/_ckernel.c"],
            extra_compile_args=["-O2", "-ffp-contract=off", "-fno-fast-math", "-std=c11"],
            optional=True,
        ),
        Extension(
            "motcomp.runtime._cshaper",
            sources=["motcomp/runtime/_cshaper.c"],
            extra_compile_args=["-O2", "-ffp-contract=off", "-fno-fast-math", "-std=c11"],
            optional=True,
        ),
        Extension(
            "motcomp.io._cwire",
            sources=["motcomp/io/_cwire.c"],
            extra_compile_args=["-O2", "-std=c11"],
            optional=True,
        ),
    ],
    cmdclass={"build_py": BuildPyWithConfig},
)
