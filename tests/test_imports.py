"""The pure core imports no I/O, clock or offline stack; the offline stack is imported lazily."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.conftest import subprocess_env

CORE = ["motcomp.core.compensator", "motcomp.core.tuning", "motcomp.core.models",
        "motcomp.core.loop", "motcomp.core.saturation", "motcomp.core.pid", "motcomp.core.lti"]
FORBIDDEN_IN_CORE = ["scipy", "matplotlib", "zenoh", "can", "cantools", "msgpack", "pydantic",
                     "mcap", "socket", "threading", "logging"]


def loaded_after(imports: list[str]) -> set[str]:
    code = (f"import sys\nfor m in {imports!r}: __import__(m)\n"
            "import json; print(json.dumps(sorted(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=subprocess_env(), check=True).stdout
    return {m.split(".")[0] for m in json.loads(out)}


def test_core_is_pure() -> None:
    mods = loaded_after(CORE)
    assert not mods & set(FORBIDDEN_IN_CORE), mods & set(FORBIDDEN_IN_CORE)


def test_design_imports_scipy_and_matplotlib_lazily() -> None:
    mods = loaded_after(["motcomp.design.frequency", "motcomp.design.timedomain",
                         "motcomp.design.report", "motcomp.cli"])
    assert "matplotlib" not in mods
    assert "scipy" not in mods
