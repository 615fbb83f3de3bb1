"""The paper's tables as regression tests: Tromme, Brüls & Duysinx, *Weakly and fully coupled
methods for structural optimization of flexible mechanisms*, Tables 1-8.

The published numbers are read from tests/data/paper_tables.json (a transcription of the
paper's tables). Every optimization runs once per session (`optimized`, cached) and serially,
exactly as `flexmbs reproduce` runs it (`flexmbs.paper.reproduce.optimization_job` with the same
options), so the report and these tests check the same numbers.

Tolerances: masses within 1 % of the paper, every design variable within 3 % (Table 5:
5 %; its single active constraint leaves the design flat); Table 7's fully coupled masses within
3 %; the four-bar's (Tables 3, 4) within 5 % (FOURBAR_MASS_TOL, justified there). docs/paper-cases.md
explains why designs are compared more loosely than masses: moving 1 % along the
constraint costs about 0.015 % of mass, so the paper's stopping test accepts designs 2-3 %
apart. Iteration counts depend on the optimizer and the variable scaling: they are printed
beside the paper's (run pytest with -s to see them), never asserted.
"""
import functools
import json

import numpy as np
import pytest

from flexmbs.cli.main import main
from flexmbs.paper.reproduce import (TABLES, design_spread, optimization_job, paper_row,
                               paper_tables)

_PAPER = paper_tables()
#: The starting points of Tables 6 and 7 (mm), from the shipped study (cases/studies/paper.toml).
STARTS = TABLES[7].starts


@functools.lru_cache(maxsize=None)
def _optimize(run):
    return optimization_job(**run.job())


@pytest.fixture(scope="session")
def optimized():
    """run -> the result dict of its optimization (each run once per session)."""
    return _optimize


def _run(table, method, start=None):
    """The run of a table as `flexmbs reproduce` runs it (the study's case, overrides and
    optimizer options)."""
    return TABLES[table].run(method, start)


def _report(table, method, start, res, paper):
    """Print flexmbs's iteration counts and design beside the paper's."""
    fmt = lambda p: "[" + ", ".join("-" if v is None else f"{v:.2f}" for v in p) + "]"  # noqa: E731
    print(f"\nTable {table}, {method} coupled from {list(start)}: "
          f"mass {res['mass_kg']:.4f} kg (paper {paper.get('mass')}), "
          f"iterations {res['iterations']} (paper {paper.get('iter')}), "
          f"inner iterations {res['inner_iterations']} (paper {paper.get('inner_iter')}), "
          f"p = {fmt(res['design'])} (paper {fmt(paper.get('p') or [])}) mm; "
          f"{'converged' if res['converged'] else 'NOT converged'}: {res['reason']}; "
          f"{res['wall_time_s']:.1f} s")


def _check_row(optimized, table, method, start=None, mass_tol=0.01, design_tol=0.03):
    run = _run(table, method, start)
    res = optimized(run)
    paper = paper_row(table, method, run.start_mm, _PAPER)
    _report(table, method, run.start_mm, res, paper)
    assert res["converged"], res["reason"]
    assert res["mass_kg"] == pytest.approx(paper["mass"], rel=mass_tol)
    if design_tol is not None:
        np.testing.assert_allclose(res["design"], paper["p"], rtol=design_tol)
    return res


# ---------------------------------------------------------------------------- robot, 0.65 s
@pytest.mark.parametrize("method", ["weakly", "fully"])
def test_table1(optimized, method):
    """Table 1 (robot, deviation (28), 0.65 s, start 50 mm): weakly 0.962 kg, p = [39.29, 28.33,
    34.94, 25.19] mm; fully 0.962 kg, p = [39.35, 28.25, 35.14, 24.91] mm. Mass 1 %, p 3 %."""
    res = _check_row(optimized, 1, method)
    # an optimum sits on its constraint: the full simulation's maximum is the 1 mm limit
    assert res["max_deviation_m"] == pytest.approx(1e-3, rel=0.01)


@pytest.mark.parametrize("method", ["weakly", "fully"])
def test_table2(optimized, method):
    """Table 2 (robot, tracking deviation (30), 0.65 s): weakly 1.411 kg, p = [47.87, 34.51,
    42.11, 30.08] mm; fully 1.408 kg, p = [48.58, 35.02, 41.43, 29.08] mm. Mass 1 %, p 3 %."""
    res = _check_row(optimized, 2, method)
    assert res["max_deviation_m"] == pytest.approx(1e-3, rel=0.01)


@pytest.mark.parametrize("start", STARTS[1:], ids=lambda s: "-".join(f"{v:g}" for v in s))
@pytest.mark.parametrize("method", ["weakly", "fully"])
def test_table6(optimized, method, start):
    """Table 6 (Table 1's problem from three more starts, [50]*4 being Table 1 itself): every
    start gives 0.961-0.962 kg and p within 0.1 mm of Table 1's. Mass 1 %, p 3 %."""
    _check_row(optimized, 6, method, start)


# ---------------------------------------------------------------------------- robot, 0.66 s
def test_table5_fully_converges(optimized):
    """Table 5 (robot, (28), 0.66 s): the fully coupled method converges (11 iterations) to
    1.099 kg, p = [43.54, 32.56, 34.20, 25.90] mm. Mass 1 %, p 5 % (a single active constraint,
    the last step, leaves the design flat)."""
    _check_row(optimized, 5, "fully", design_tol=0.05)


def test_table5_weakly_oscillates(optimized):
    """Paper 8.1 and Fig. 10: on the 0.66 s problem the weakly coupled method does not converge;
    its objective oscillates between cycles until the maximum number of cycles. flexmbs must
    report it as not converged, stopped by a detected oscillation or the cycle limit, with
    designs that keep changing mass by more than the ESL tolerance from cycle to cycle."""
    run = _run(5, "weakly")
    res = optimized(run)
    _report(5, "weakly", run.start_mm, res, paper_row(5, "weakly", run.start_mm, _PAPER))
    assert not res["converged"]
    assert "oscillation" in res["reason"] or "maximum number" in res["reason"]
    masses = np.array([r["mass_kg"] for r in res["history"]])
    tail = masses[len(masses) // 2:]
    assert np.ptp(tail) / tail.mean() > 1e-2


# ---------------------------------------------------------------------------- robot, 0.6685 s
@pytest.mark.slow
@pytest.mark.parametrize("start", STARTS, ids=lambda s: "-".join(f"{v:g}" for v in s))
def test_table7_weakly(optimized, start):
    """Table 7 (robot, (28), 0.6685 s = 1338 steps), weakly coupled: 1.352-1.355 kg from every
    start, p within 0.2 mm of [52.5, 37.8, 33.2, 24.8] mm. Mass 1 %, p 3 %."""
    _check_row(optimized, 7, "weakly", start)


_T7_FULLY_STARTS = [
    pytest.param(STARTS[0], marks=pytest.mark.xfail(strict=True, reason=(
        "measured 1.3817 kg, -3.2 % from the paper's 1.427 kg: from [50, 50, 50, 50] flexmbs's "
        "fully coupled optimizer reaches the same lighter local optimum as from [55]*4 and "
        "[45]*4, p = [51.80, 36.77, 36.14, 26.30] mm. The paper's design [51.71, 36.89, 38.07, "
        "27.31] mm is feasible in flexmbs's model with its last step nearly active (0.991 "
        "mm): the deviation at step 1338 oscillates over the design space (Fig. 15), "
        "and which optimum a run reaches depends on its path (the paper's own other starts "
        "give 1.350-1.386 kg)"))),
    *STARTS[1:]]


@pytest.mark.slow
@pytest.mark.parametrize("start", _T7_FULLY_STARTS, ids=lambda s: "-".join(f"{v:g}" for v in s))
def test_table7_fully_mass(optimized, start):
    """Table 7, fully coupled: 1.427, 1.386, 1.372, 1.350 kg from the four starts (each a
    different local optimum, paper Fig. 15). Mass within 3 %; designs not compared."""
    _check_row(optimized, 7, "fully", start, mass_tol=0.03, design_tol=None)


@pytest.mark.slow
def test_table7_finding(optimized):
    """Paper 8.2: the weakly coupled method is insensitive to the start (its four designs agree
    within 1 %; the paper's spread 0.3 %), the fully coupled one is not (its four designs differ
    by more; the paper's spread 13 %, p3 from 33.29 to 38.07 mm)."""
    weak = [optimized(_run(7, "weakly", s))["design"] for s in STARTS]
    full = [optimized(_run(7, "fully", s))["design"] for s in STARTS]
    sw, sf = design_spread(weak), design_spread(full)
    print(f"\nTable 7 spread of the designs over the four starts: weakly {100 * sw:.2f} % "
          f"(paper 0.32 %), fully {100 * sf:.2f} % (paper 13.4 %)")
    assert sw <= 0.01
    assert sf > sw


# ---------------------------------------------------------------------------- four-bar
# Tolerance of the four-bar masses: 5 %. The paper's own Table 3 designs, simulated by flexmbs,
# sit 2.2 % below (weakly) and 3.1 % above (fully) the 1 mm limit (docs/reproduction), and the
# maximum deviation is a vibration peak that moves by several per cent with h and rho_inf
# (docs/paper-cases.md); the deviation grows like p^-3 to p^-4 and the mass like p^2, so a few per cent of
# deviation are 1.5-2 % of mass. 5 % leaves room for that, not for a different local optimum.
FOURBAR_MASS_TOL = 0.05
_F250 = (250.0, 250.0, 250.0)

_T3_XFAIL = {
    "weakly": pytest.mark.xfail(strict=True, reason=(
        "measured 30.455 kg (the best feasible design seen, cycle 25) vs paper 20.703 kg "
        "(+47.1 %), and not converged: the cycles oscillate with period 5 (stopped at cycle 28; "
        "ESL change (25) still 0.03-0.22); they wander between 29.5 and 32.9 kg from cycle 6 on, "
        "around p = [73.4, 91.5, 79.0] mm vs the paper's [69.85, 87.61, 37.22] (p3 +110 %). The "
        "paper's design is feasible in flexmbs's model (0.978 mm) but no fixed point of its ESL "
        "cycles: started there, they walk back to 30.1 kg in 7 cycles. Move limits, damping and "
        "ESL averaging (docs/optimizers.md, Weakly coupled cycles) settle between 30.1 and "
        "33.0 kg")),
    "fully": pytest.mark.xfail(strict=True, reason=(
        "measured 4.628 kg vs paper 2.967 kg (+56.0 %): flexmbs converges (KKT) to p = [75.96, "
        "15.00, 15.07] mm, the paper's p1 is 56.15 mm. The paper's design is infeasible in "
        "flexmbs's model (1.031 mm, +3.1 %), and near it the maximum deviation of the slender "
        "links jumps between 0.9 and 4.5 mm with p1 (docs/reproduction, Table 3): the optimizer "
        "stops in another local optimum of this non-monotonic landscape")),
}


@pytest.mark.slow
@pytest.mark.parametrize("method", [pytest.param(m, marks=_T3_XFAIL[m]) for m in ("weakly", "fully")])
def test_table3_mass(optimized, method):
    """Table 3 (four-bar with 5 kg at A and B, start 250 mm): weakly coupled 20.703 kg after 73
    converged cycles, fully coupled 2.967 kg (paper 7.2). Converged, mass within 5 %
    (FOURBAR_MASS_TOL); designs not compared (both are local optima, docs/paper-cases.md)."""
    res = optimized(_run(3, method))
    _report(3, method, _F250, res, paper_row(3, method, _F250, _PAPER))
    assert res["converged"], res["reason"]
    assert res["mass_kg"] == pytest.approx(paper_row(3, method, _F250, _PAPER)["mass"],
                                           rel=FOURBAR_MASS_TOL)


@pytest.mark.slow
def test_table3_fully_seven_times_lighter(optimized):
    """Paper 7.2: "the objective function optimal value is 7 times larger with the weakly
    coupled method" (20.703 / 2.967 = 6.98). Asserted: flexmbs's ratio within 15 % of 6.98:
    5 % on each mass (FOURBAR_MASS_TOL), plus the wander of the unconverged weakly coupled
    cycles, whose mass moves between 29.5 and 32.9 kg (+-5.5 %) from cycle 6 to 30, so that a
    different rounding can stop them anywhere in that band (ratio 6.38-7.10). Measured 6.58
    (weakly: the best feasible design seen, 30.455 kg; both masses ~50 % above the paper's,
    test_table3_mass); the report of 2026-11-22 (older code) had 6.79."""
    w = optimized(_run(3, "weakly"))
    f = optimized(_run(3, "fully"))
    ratio = w["mass_kg"] / f["mass_kg"]
    print(f"\nTable 3: weakly / fully coupled mass = {ratio:.2f} (paper 6.98)")
    assert ratio == pytest.approx(20.703 / 2.967, rel=0.15)


@pytest.mark.slow
def test_table3_fully_optimum_on_its_constraint(optimized):
    """Paper 7.2 and Fig. 8: at convergence at least one constraint is active. The fully coupled
    method's constraint is the deviation (33) itself: its maximum over the 1001 steps is the
    1 mm limit within 1 % (the optimizer's own feasibility test is 1e-6 relative)."""
    f = optimized(_run(3, "fully"))
    assert f["converged"], f["reason"]
    assert f["max_deviation_m"] == pytest.approx(1e-3, rel=0.01)


@pytest.mark.slow
def test_table4_fully_removes_links_2_and_3(optimized):
    """Table 4 (four-bar without lumped masses), paper 7.3: the fully coupled method converges
    with p2 and p3 at their 15 mm lower bound (links 2 and 3 "removed"; within 1 %, as the paper's
    Table 3 p2 = 15.10 mm) and the deviation constraint active (1 mm within 1 %). The paper's
    Table 4 lost its masses in the text: no mass is compared."""
    f = optimized(_run(4, "fully"))
    _report(4, "fully", _F250, f, paper_row(4, "fully", _F250, _PAPER))
    assert f["converged"], f["reason"]
    assert np.all(np.asarray(f["design"][1:]) <= 15.0 * 1.01)
    assert f["max_deviation_m"] == pytest.approx(1e-3, rel=0.01)


@pytest.mark.slow
def test_table4_weakly_keeps_links_2_and_3(optimized):
    """Table 4, paper 7.3: with the weakly coupled method "links 2 and 3 can not be removed,
    they are optimized in order to satisfy (35)"; "the optimum design is quite different".
    Asserted: p2, p3 at least 10 % above the 15 mm bound, and a mass above the fully coupled
    one (whose p2, p3 are at the bound)."""
    w = optimized(_run(4, "weakly"))
    f = optimized(_run(4, "fully"))
    _report(4, "weakly", _F250, w, paper_row(4, "weakly", _F250, _PAPER))
    assert np.all(np.asarray(w["design"][1:]) >= 15.0 * 1.1)
    assert w["mass_kg"] > f["mass_kg"]


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "not converged: flexmbs's weakly coupled cycles on the four-bar without lumped masses stop "
    "at cycle 21 on a period-5 oscillation with the ESL change (25) above eps = 1e-2; they "
    "return the best feasible design seen, 30.99 kg (docs/reproduction); the paper says the "
    "method 'also converges' (design_tol=0.02 converges it, docs/optimizers.md)"))
def test_table4_weakly_converges(optimized):
    """Table 4, paper 7.3: "the weakly coupled method also converges" (test (25), eps = 1e-2)."""
    w = optimized(_run(4, "weakly"))
    assert w["converged"], w["reason"]


# ---------------------------------------------------------------------------- Table 8
def _final_active(res):
    act = res["history"][-1]["active_steps"]
    return sorted({s for v in act.values() for s in v})


@pytest.mark.slow
def test_table8_final_active_steps(optimized):
    """Table 8 and paper 8.2 (Table 7's problem from [55, 55, 55, 55]): at convergence the fully
    coupled method has only the last time step (1338) active, the weakly coupled one the
    window 239-242 (0.119-0.1205 s)."""
    w = optimized(_run(7, "weakly", STARTS[1]))
    f = optimized(_run(7, "fully", STARTS[1]))
    print(f"\nTable 8, final active steps: weakly {_final_active(w)} (paper 239-242), "
          f"fully {_final_active(f)} (paper 1338)")
    assert _final_active(f) == [1338]
    assert set(range(239, 243)) <= set(_final_active(w))


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "flexmbs's weakly coupled design keeps the last step active: its static problem and its "
    "full simulation both have steps 238-242 and 1338 within 0.1 % of the limit at convergence, "
    "where the paper's Table 8 lists 239-242 only ('the last constraint is no more active at "
    "convergence'); the design is within 0.6 % of the paper's, whose deviation at step 1338 "
    "in flexmbs's model is 1.005 mm"))
def test_table8_weakly_last_step_inactive(optimized):
    """Table 8: the weakly coupled method's last cycle (Table 7's problem, start [55]*4) has the
    steps 239-242 active and no longer step 1338."""
    w = optimized(_run(7, "weakly", STARTS[1]))
    assert 1338 not in _final_active(w)


# ---------------------------------------------------------------------------- the report
def test_reproduce_report_from_stored_runs(optimized, tmp_path, capsys):
    """`flexmbs reproduce --table 1` over a store that holds Table 1's runs (as an interrupted
    run leaves it: each with its job's fingerprint) runs no optimization, prints every row
    beside the paper's and writes README.md, comparison.json and Fig. 5. The stored results
    are this session's, so the printed numbers are the ones test_table1 checked."""
    from flexmbs.sweep import job_fingerprint
    store = tmp_path / "jobs" / "optimizations"
    store.mkdir(parents=True)
    runs = TABLES[1].runs()
    for run in runs:
        stored = dict(optimized(run), fingerprint=job_fingerprint(optimization_job, run.job()))
        (store / f"{run.name}.json").write_text(json.dumps(stored))
    assert main(["reproduce", "--table", "1", "--out", str(tmp_path), "--workers", "1"]) == 0
    out = capsys.readouterr().out
    assert "Table 1:" in out and out.count("paper ") >= 2
    for run in runs:
        res = optimized(run)
        assert f"{res['mass_kg']:9.4f}" in out
    data = json.loads((tmp_path / "comparison.json").read_text())
    rows = data["rows"]["1"]
    assert [r["flexmbs"]["mass_kg"] for r in rows] == [optimized(r)["mass_kg"] for r in runs]
    assert [r["paper"]["mass"] for r in rows] == [0.962, 0.962]
    readme = (tmp_path / "README.md").read_text()
    assert "| weakly | [50, 50, 50, 50] | paper | 0.962 |" in readme
    assert "figures/fig05.png" in readme
    assert (tmp_path / "figures" / "fig05.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # nothing was recomputed: the stored files are the ones written above
    assert sorted(data["settings"]["stored_runs"]) == sorted(r.name for r in runs)
