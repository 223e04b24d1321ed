"""What ``motcomp design`` tells its user while it works and when it is done: the progress names
each stage and the optimiser's or the search's own progress, its share done never goes back;
the report flags a sensitivity at or beyond its bound."""

from __future__ import annotations

import itertools

from motcomp.design.optimal import Constraints, OptimalOptions
from motcomp.design.predictor import PredictionOptions
from motcomp.design.report import design_report, markdown
from motcomp.presets import load_preset
from motcomp.progress import Stages
from tests.conftest import RAILS


def test_stages_share_and_notes() -> None:
    seen: list[tuple[float, float, str]] = []
    stages = Stages(lambda d, t, n: seen.append((d, t, n)), [("one", 1.0), ("two", 3.0)])
    first = stages.start("one")
    assert first is not None
    first(1, 2, "half")
    second = stages.start("two")
    assert second is not None
    second(3, 3, "all")
    assert seen[1] == (0.5, 4.0, "stage 1 of 2, one: 1 of 2, half")
    assert seen[-1] == (4.0, 4.0, "stage 2 of 2, two: 3 of 3, all")
    # what remains is replanned; the share done never goes back
    stages = Stages(lambda d, t, n: seen.append((d, t, n)), [("a", 1.0), ("b", 1.0)])
    a = stages.start("a")
    assert a is not None
    a(1, 1, "")
    before = seen[-1][0] / seen[-1][1]
    stages.plan([("c", 5.0), ("d", 5.0)])
    stages.start("c")
    assert seen[-1][2] == "stage 2 of 3, c" and seen[-1][0] / seen[-1][1] < before
    assert seen[-1][0] == 1.0  # done is weight units: the finished stage's
    assert Stages(None, [("x", 1.0)]).start("x") is None


def test_design_progress_names_each_stage_and_goes_forward() -> None:
    """The hexapod with prediction (``auto``): the PID's screening and starts, the prefilter's
    search, the checks -- in that order, each share at least the previous one."""
    seen: list[tuple[float, float, str]] = []
    design_report(load_preset("hexapod").model, "optimal",
                  options=OptimalOptions(Constraints(peak_db=6.0, hf_command_gain=3.0)),
                  prediction=PredictionOptions(mode="auto", order=12),
                  progress=lambda d, t, n: seen.append((d, t, n)))
    notes = [n for _, _, n in seen]
    assert notes[0].startswith("stage 1 of 3, optimising the PID")
    assert any("screening the gain space" in n for n in notes)
    assert any("start 1 of 6 (screen1): " in n for n in notes)
    assert any(n.startswith("stage 2 of 3, designing the prefilter alone (axis bypassed): ")
               and " ms not met" in n for n in notes)
    assert any("the least command gain at " in n for n in notes)
    assert notes[-1] == "stage 3 of 3, checking the design"
    shares = [d / t for d, t, _ in seen]
    assert all(b >= a - 1e-12 for a, b in itertools.pairwise(shares))
    assert all(0.0 <= s <= 1.0 for s in shares)


def test_ms_at_its_bound_is_flagged() -> None:
    report = design_report(RAILS, "optimal",
                           options=OptimalOptions(Constraints(max_sensitivity=1.5)))
    text = markdown(report)
    assert "| Ms (internal loop) | 1.50 -- AT its bound 1.5 (the bound limits the design) |" \
        in text
    assert "| max sensitivity Ms | 1.5 | 1.50 | AT the bound |" in text  # the optimal block


def test_a_rule_beyond_the_default_ms_bound_is_flagged() -> None:
    text = markdown(design_report(RAILS, "zn"))  # ZN on the rails: Ms 4.79
    assert "| Ms (internal loop) | 4.79 -- BEYOND its bound 4 |" in text
