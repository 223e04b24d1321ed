"""The pure core: models, the tick and all it calls.  Its hot modules may be compiled (see
:mod:`motcomp.core.native`); this picks the compiled or the plain Python ones, all together."""

from pathlib import Path

from motcomp.core import native

native.choose(__name__, Path(__file__).resolve().parent)
