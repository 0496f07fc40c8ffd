"""The evaluation's planned row (``gpt-auto``: `gradsep render --seconds T --gradients auto` at equal time, its
pilot charged) and the report's section "The planner's choice".

The report section is checked on synthetic rows (its counts and verdicts are computed from them); the row itself
on a tiny procedural frame: a budget below the planner's start-up and a pilot that gives up record the fallback
with the reason and no prediction, the deadline keeps the reconstruction's time free, and one small evaluation
with a budget a pilot fits shows the chosen plan, its prediction and the measured error in the report.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from gradsep.evaluation.report_time import PlannedFrame, planned_frames, planner_choice, time_misses
from gradsep.renderer.plans import FALLBACK

SCENE = "procedural:90001"


# ---------------------------------------------------------------------------------------- the report


def _row(method: str, spp: int, relmse: float, scene: str = "s", **extra) -> dict:
    return {"scene": scene, "method": method, "spp": spp, "relmse": relmse, "method_spp": spp, "total_seconds": 1.0,
            "render_seconds": 0.9, "reconstruct_seconds": 0.1, **extra}


def _auto(spp: int, relmse: float, predicted: float | None, scene: str = "s", **extra) -> dict:
    return _row("gpt-auto", spp, relmse, scene, target_seconds=2.0, budget_method="oidn-l1", attempts=1,
                plan="direct-alternate" if predicted is not None else "all", predicted_relmse=predicted,
                plan_layers="direct=alternate,indirect=none", pilot_seconds=0.3,
                plan_candidates={"all": 0.02, "primal": 0.03, "direct-alternate": predicted} if predicted else {},
                **extra)


def test_planner_section_compares_each_prediction_with_the_measured_error():
    rows = [
        _auto(16, 0.012, 0.010), _row("oidn-l1", 16, 0.011), _row("gpt-oidn-l1", 16, 0.013),
        _row("path-oidn", 16, 0.02), _row("path-sep-oidn", 16, 0.015), _row("path", 16, 0.001),  # path: not fixed
        _auto(64, 0.003, 0.001), _row("path-sep-oidn", 64, 0.004),
        _auto(16, 0.05, None, scene="t", predicted_note="the budget is too small for a checkpoint"),
        _auto(16, 0.025, 0.02, scene="u", seeds=2, seed_plan=["primal", "all"], seed_predicted_relmse=[0.02, None],
              seed_predicted_note=[None, "the budget is too small for a checkpoint"], seed_relmse=[0.021, 0.029],
              seed_spp=[100, 50], seed_seconds=[1.9, 2.05]),
    ]
    text = "\n".join(planner_choice(rows))
    assert "## The planner's choice" in text
    lines = text.splitlines()
    first = next(line for line in lines if line.startswith("| s | 16 |"))
    # plan, predicted, measured, their ratio, the verdict, the best fixed pipeline (path is no fixed pipeline)
    assert "| direct-alternate |" in first and "| 0.01 | 0.012 | 0.83 | yes |" in first
    assert "0.011 (oidn-l1) | 1.091×" in first and "all 0.02, primal 0.03, direct-alternate 0.01" in first
    second = next(line for line in lines if line.startswith("| s | 64 |"))
    assert "| 0.33 | **no** |" in second and "0.004 (path-sep-oidn) | 0.750×" in second
    assert "| t | 16 |" in text and "no prediction" in next(line for line in lines if line.startswith("| t | 16 |"))
    seeds = [line for line in lines if line.startswith("| u (seed")]
    assert len(seeds) == 2 and "| primal |" in seeds[0] and "| 1.9 |" in seeds[0] and "| yes |" in seeds[0]
    assert "no prediction" in seeds[1]
    # 0.83 and 0.02 / 0.021 within 1.5x, 0.33 not; t and u's second seed without a prediction
    assert "within 1.5× of the measured one on 2 of 3 frames with a prediction (67%); 2 of 5 frames have none" in text
    assert "at most 1.05× on 1 of 2 rows; geometric mean of auto / best 0.905×" in text
    assert "- t, 16 spp: the budget is too small for a checkpoint" in text
    assert "- u (seed 1), 16 spp: the budget is too small for a checkpoint" in text


def test_planner_section_without_the_row_says_so_and_a_negative_error_is_not_a_hit():
    assert "was not evaluated" in "\n".join(planner_choice([_row("l1", 16, 0.1)]))
    frame = planned_frames(_auto(16, -0.001, 0.01))[0]
    assert frame == PlannedFrame("", "direct-alternate", 0.01, None, -0.001, 16, 1.0) and frame.ratio is None
    text = "\n".join(planner_choice([_auto(16, -0.001, 0.01)]))
    assert "**no** (measured ≤ 0)" in text and "on 0 of 1 frames" in text


def test_a_planned_row_outside_the_tolerance_is_listed_with_its_reason():
    row = _auto(16, 0.01, 0.01, total_seconds=1.6, time_note="pass granularity")
    (miss,) = time_misses([row])
    assert "gpt-auto: 1.6 s for a 2 s budget (-20%; 1 try, kept 16 spp): pass granularity" in miss


def test_a_planned_row_over_its_budget_does_not_count_as_the_best_g_pt_at_equal_time():
    """More time than the rows it is compared with: its RelMSE is shown but wins nothing; an early one counts."""
    from gradsep.evaluation.report import _fused_and_equal_time_targets
    from gradsep.evaluation.report_time import over_budget

    late = _auto(16, 0.001, 0.001, total_seconds=2.2)  # budget 2 s: +10 %
    assert over_budget(late) and not over_budget({**late, "total_seconds": 2.09})
    assert not over_budget({**late, "total_seconds": 1.2}) and not over_budget(_row("oidn-l1", 16, 0.1))
    rows = [late, _row("oidn-l1", 16, 0.011), _row("path-oidn", 16, 0.02, budget_method="oidn-l1")]
    text = "\n".join(_fused_and_equal_time_targets(rows))
    assert "the best G-PT row (`oidn-l1`)" in text
    text = "\n".join(_fused_and_equal_time_targets([{**late, "total_seconds": 1.9}, *rows[1:]]))
    assert "the best G-PT row (`gpt-auto`)" in text


def test_a_multi_seed_planned_row_keeps_each_seeds_plan_and_prediction():
    from gradsep.evaluation.scores import seed_mean

    seeds = [_auto(16, 0.01, 0.012), {**_auto(16, 0.02, None), "predicted_note": "too small"},
             {**_auto(16, 0.03, 0.02), "plan": "primal"}]
    row = seed_mean(seeds)
    assert row["seed_plan"] == ["direct-alternate", "all", "primal"] and row["plan"] == "direct-alternate/all/primal"
    assert row["seed_predicted_relmse"] == [0.012, None, 0.02] and row["predicted_relmse"] is None
    assert row["seed_predicted_note"] == [None, "too small", None]
    assert seed_mean(seeds[::2])["predicted_relmse"] == pytest.approx(0.016)
    frames = planned_frames(row)
    assert [(f.label, f.plan, f.predicted, f.note, f.measured) for f in frames] == [
        ("seed 0", "direct-alternate", 0.012, None, 0.01), ("seed 1", "all", None, "too small", 0.02),
        ("seed 2", "primal", 0.02, None, 0.03)]


# ------------------------------------------------------------------------------------------ the row


def test_the_planned_rows_time_note_names_what_missed():
    """Within ±5 %: no note. Else the part that missed: a refused budget, the render stopping a pass short, the
    pilot or a pass running past the deadline, the reconstruction against its reserve."""
    from types import SimpleNamespace

    from gradsep.evaluation.runners import PlannedTimes, _planned_time_note

    def note(target, render, post, tail, refused, chosen, plan, pilot):
        return _planned_time_note(PlannedTimes(target, render, post, tail, refused, chosen, plan, pilot))

    assert note(2.0, 1.7, 0.25, 0.25, "", None, "all", 0.5) == ""
    assert note(0.1, 0.5, 0.01, 0.01, "below start-up", None, "all", 0.0) == (
        "below start-up (render 0.5 s, the refused attempt included)")
    early = note(2.0, 1.2, 0.25, 0.25, "", SimpleNamespace(per_sample=0.3), "primal", 0.5)
    assert early.startswith("the render stopped 0.55 s before") and "`primal` (0.3 s per spp)" in early
    assert "granularity" in early and ";" not in early  # the reconstruction took what was reserved
    pilot = note(2.0, 2.2, 0.25, 0.25, "", None, "all", 2.1)
    assert "ended 0.45 s past" in pilot and "the checkpoint alone took 2.1 s" in pilot
    slow = note(2.0, 2.2, 0.25, 0.25, "", None, "all", 0.5)
    assert "a pass slower than predicted" in slow
    recon = note(2.0, 1.75, 0.6, 0.25, "", None, "all", 0.5)
    assert recon == "the reconstruction took 0.6 s against the 0.25 s reserved"


def test_the_planned_row_is_keyed_by_the_planner_sources():
    """A planner change must recompute the row: its key holds the planner's code, and every file named exists
    (a missing one would hash as "absent" and never change)."""
    from gradsep.evaluation.cache import REPO_ROOT
    from gradsep.evaluation.methods import METHOD_SOURCES, PLANNER_SOURCES

    assert all((REPO_ROOT / f).is_file() for f in PLANNER_SOURCES)
    assert "renderer/planner.py" in PLANNER_SOURCES and not set(PLANNER_SOURCES) & set(METHOD_SOURCES)
    # every row's timing depends on the process evaluation/run.py sets up (which scenes stay loaded)
    assert "evaluation/run.py" in METHOD_SOURCES and all((REPO_ROOT / f).is_file() for f in METHOD_SOURCES)


@pytest.fixture(scope="module")
def tiny():
    """A 32×32 scene, its 1-spp G-PT frame and the per-scene renderer (the planner's kernels compiled)."""
    from gradsep.evaluation.baselines import PathRenderer
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene

    loaded = load_scene(SCENE, width=32, height=32)
    frame = render_frame(loaded, spp=1, seed=1)
    renderer = PathRenderer(loaded)
    renderer.planner_tail(tuple(frame.layers))
    return frame, renderer


def _run(tiny, budget: float):
    from gradsep.evaluation.methods import method_by_name
    from gradsep.evaluation.runners import MethodContext, NetworkPool, run_method

    frame, renderer = tiny
    ctx = MethodContext(frame=frame, render_seconds=0.1, spp=1, seed=12345, alpha=0.2, models_dir=Path("none"),
                        networks=NetworkPool(), path=lambda: renderer, budget_seconds=budget, budget_method="oidn-l1")
    return run_method(method_by_name("gpt-auto"), ctx)


@pytest.mark.render
def test_a_budget_below_the_planners_start_up_renders_the_fallback_and_says_so(tiny):
    """0.02 s cannot hold the planner's first pass (its per-frame tracing alone takes longer) and the
    reconstruction: `gradsep render --seconds` refuses that; the row renders 1 spp of the fallback regardless, finite,
    with the overrun's reason and no prediction."""
    out = _run(tiny, 0.02)
    extra = out.extra
    assert out.method_spp == 1 and extra["plan"] == FALLBACK and extra["attempts"] == 1
    assert extra["predicted_relmse"] is None and extra["plan_candidates"] == {}
    assert "below the planner's start-up" in extra["predicted_note"]
    assert "below the planner's start-up" in extra["time_note"] and "refused attempt included" in extra["time_note"]
    assert out.render_seconds + out.reconstruct_seconds > 0.02 * 1.05  # a miss, recorded as one
    assert math.isfinite(float(out.image.sum())) and out.image.min() >= 0


@pytest.mark.render
def test_a_checkpoint_that_does_not_fit_fills_the_budget_with_the_fallback_and_no_prediction(tiny, monkeypatch):
    from gradsep.renderer import frame_budget

    monkeypatch.setattr(frame_budget, "PILOT_SHARE", 0.0)  # no checkpoint fits: the fallback after its first pass
    out = _run(tiny, 1.0)
    extra = out.extra
    assert extra["plan"] == FALLBACK and extra["predicted_relmse"] is None
    assert extra["predicted_note"] == "the budget is too small for a checkpoint" and extra["plan_candidates"] == {}
    assert out.method_spp >= 1 and extra["pilot_seconds"] > 0 and extra["plan_method"] == "oidn-l1"
    total = out.render_seconds + out.reconstruct_seconds
    assert abs(total - 1.0) <= 0.05 or extra["time_note"]  # within the tolerance, or the reason recorded


@pytest.mark.render
def test_the_deadline_keeps_its_tail_free_for_the_reconstruction(tiny):
    """Deadline.tail replaces the command's reserve (write + exit): the passes stop so that the tail is left."""
    from gradsep.renderer.budget import Deadline
    from gradsep.renderer.frame_budget import FrameBudget
    from gradsep.renderer.planner import FixedChoice, render_planned
    from gradsep.renderer.plans import plan_named

    frame, renderer = tiny
    deadline = Deadline(3.0, tail=2.0)
    planned = render_planned(renderer.loaded, tuple(frame.layers), FixedChoice(plan_named("primal")),
                             FrameBudget(deadline), seed=3)
    assert planned.spp >= 1
    # the tail is left, up to a pass slower than predicted (without it the passes would fill all but ~0.5 s)
    assert deadline.left() >= 0.8 * 2.0


@pytest.mark.render
def test_an_in_process_deadline_measures_no_write(tiny, monkeypatch):
    """The caller of a Deadline with a tail writes nothing, so the planner spends none of the budget timing a write
    (at the evaluation's sub-second budgets that timing took a third of the time after the first pass)."""
    from gradsep.renderer import frame_budget
    from gradsep.renderer.budget import Deadline
    from gradsep.renderer.planner import CheckpointChoice, FixedChoice, render_planned
    from gradsep.renderer.plans import plan_named

    def no_write(*args, **kwargs):
        raise AssertionError("the write was measured")

    monkeypatch.setattr(frame_budget, "write_seconds", no_write)
    frame, renderer = tiny
    for choice in (FixedChoice(plan_named("direct-alternate")), CheckpointChoice()):
        planned = render_planned(renderer.loaded, tuple(frame.layers), choice,
                                 frame_budget.FrameBudget(Deadline(1.0, tail=0.2)), seed=4)
        assert planned.spp >= 1


@pytest.mark.render
def test_a_warm_planner_sizes_its_first_pass_from_the_costs_measured_beforehand(tiny, monkeypatch):
    """The row's priors (measured untimed, like the searched rows' cost models): each candidate's cost line of two
    warm sizes and the reconstruction's rate. With them no 1-spp probe is spent: the first pass is sized from the
    line, whether the plan is fixed or the checkpoint is known not to fit before any pass."""
    from gradsep.renderer import frame_budget, passes
    from gradsep.renderer.budget import Deadline
    from gradsep.renderer.planner import CheckpointChoice, FixedChoice, PlannerOptions, render_planned
    from gradsep.renderer.plans import judged_plans, plan_named

    frame, renderer = tiny
    layers = tuple(frame.layers)
    priors = renderer.planner_priors(layers)
    assert renderer.planner_priors(layers) is priors  # measured once per scene
    assert set(priors.costs) == {c.name for c in judged_plans(layers)}
    assert all(priors.warm(name) and c.per_sample > 0 for name, c in priors.costs.items())
    assert 0 < priors.reconstruct_rate < 1e-3 and set(priors.reconstruct_seconds) == set(priors.costs)
    runs: list[tuple[str, int]] = []
    original = passes.Passes.run
    monkeypatch.setattr(passes.Passes, "run", lambda self, c, spp: runs.append((c.name, spp)) or original(self, c, spp))
    monkeypatch.setattr(frame_budget, "PILOT_SHARE", 0.0)  # the checkpoint does not fit, and that is known beforehand
    for choice in (FixedChoice(plan_named(FALLBACK)), CheckpointChoice()):
        runs.clear()
        deadline = Deadline(2.0, tail=0.1)  # room for one warm pass on a loaded machine
        planned = render_planned(renderer.loaded, layers, choice, frame_budget.FrameBudget(deadline), seed=4,
                                 options=PlannerOptions(priors=priors))
        assert runs[0][0] == FALLBACK and runs[0][1] > 1 and planned.spp == sum(n for _, n in runs)
        assert planned.judgement is None or planned.judgement.note == "the budget is too small for a checkpoint"
        # the tail kept free is the chosen plan's own reconstruction time once the plan is known
        assert deadline.tail == priors.reconstruct_seconds[planned.plan.name] > 0
    # the caller's priors are left as they were (the frame refines a copy)
    assert all(len(c.warm) == 2 for c in priors.costs.values())


@pytest.mark.slow
@pytest.mark.render
def test_a_quick_evaluation_reports_the_plan_and_its_predicted_against_measured_error(tmp_path, monkeypatch):
    """A budget a checkpoint fits (the 32×32 G-PT frame at 4096 spp: a few seconds; the checkpoint's share of it
    raised, since under a parallel suite's load the first pass alone can take a tenth of it): the row chose a plan
    from two predictions, its time is within ±5 % of the budget or the reason is recorded (and listed), and the
    report's section shows its predicted and measured RelMSE."""
    from gradsep.evaluation.config import EvalConfig
    from gradsep.evaluation.run import run_evaluation
    from gradsep.renderer import frame_budget
    from gradsep.renderer.plans import judged_plans as applicable

    monkeypatch.setattr(frame_budget, "PILOT_SHARE", 0.5)

    config = EvalConfig(scenes=(SCENE,), spp=(4096,), width=32, height=32, ref_spp=16, output=tmp_path / "report",
                        cache_dir=tmp_path / "cache", models_dir=tmp_path / "models",
                        methods=("gpt-primal", "gpt-auto"), seed=3)
    evaluation = run_evaluation(config, progress=False, log=lambda message: None)
    row = next(r for r in evaluation.rows if r["method"] == "gpt-auto")
    assert row["budget_method"] == "G-PT render only" and row["target_seconds"] > 2
    names = {c.name for c in applicable(("direct", "indirect"))}
    assert row["plan"] in names and set(row["plan_candidates"]) == names
    # the frame's own estimate from its halves where it fits the budget (a 32x32 frame's does), else the checkpoint's
    assert row["predicted_from"] == "frame" and row["predicted_relmse"] > 0
    assert row["pilot_seconds"] > 0 and row["method_spp"] > 16 and math.isfinite(row["relmse"])
    assert row["gradients"] == {"primal": "none", "direct-alternate": "direct"}[row["plan"]]
    report = (tmp_path / "report" / "report.md").read_text()
    miss = abs(row["total_seconds"] / row["target_seconds"] - 1) > 0.05
    assert not miss or (row["time_note"] and row["time_note"] in report)
    section = report[report.index("## The planner's choice"):]
    line = next(r for r in section.splitlines() if r.startswith(f"| {SCENE} | 4096 |"))
    assert f"| {row['plan']} |" in line and f"{row['predicted_relmse']:.4g}" in line and f"{row['relmse']:.4g}" in line
    assert "frames with a prediction" in section
    with open(tmp_path / "report" / "results.json") as fh:
        saved = next(r for r in json.load(fh)["rows"] if r["method"] == "gpt-auto")
    assert saved["plan"] == row["plan"] and saved["predicted_relmse"] == row["predicted_relmse"]
    results = tmp_path / "cache" / "evaluate" / "results"
    cached = [json.loads(p.read_text()) for p in results.rglob("gpt-auto-*.json")]
    assert len(cached) == 1 and "planner" in cached[0]["key"]
