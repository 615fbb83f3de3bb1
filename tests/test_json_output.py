"""What `flexmbs simulate` and `flexmbs evaluate` report (docs/json-output.md): the run's
statistics, units and resolution in the JSON; a case without responses simulated and
summarized; enough digits; one feasibility tolerance (flexmbs.problem.FEASIBILITY_TOL) in every
verdict; the warning on the gradient of a maximum with two tied peaks; the hint of a static
start with a drive moving at t = 0."""
import inspect
import json
import math
import re
import warnings

import numpy as np
import pytest

from flexmbs.cli.main import main
from flexmbs.errors import SettingWarning, SimulationError
from flexmbs.problem import FEASIBILITY_TOL, Evaluation, Problem

ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]
#: cases/fourbar.toml: 5e-4 s steps, 6 elements per link, crank O-A of 0.3048 m, aluminium
#: rho = 2757 kg/m^3, diameters in mm
FOURBAR = ROOT / "cases" / "fourbar.toml"


def _json(capsys, args):
    assert main(args) == 0
    return json.loads(capsys.readouterr().out)


def _without_responses(tmp_path):
    """cases/fourbar.toml without its [[responses]], [objective] and [[constraints]]."""
    text = FOURBAR.read_text()
    cut = re.sub(r"\[\[responses\]\].*?(?=\[time\])", "", text, flags=re.S)
    assert "[[responses]]" not in cut and "[time]" in cut
    path = tmp_path / "motion_only.toml"
    path.write_text(cut)
    return path


# ----------------------------------------------------------------------------- JSON fields
@pytest.mark.parametrize("command", ["simulate", "evaluate"])
def test_json_gives_the_run_statistics_and_the_resolution(capsys, command):
    """--json of simulate and evaluate: the resolution of cases/fourbar.toml with --t-end 0.05
    (h = 5e-4 s: 0.05 / 5e-4 = 100 steps, 101 time points; 6 elements per link, as the case
    file says), the run's step count equal to it, at least one Newton iteration per step and
    one factorization per run (the 'auto' Newton reuses its matrix), fewer step cuts than
    steps, the memory estimate equal to Problem.memory_estimate's for the same run (computed
    apart, without running), and the evaluation's wall time at least the simulation's."""
    out = _json(capsys, [command, "fourbar", "--t-end", "0.05", "--json"])
    res = out["resolution"]
    assert res["h"] == 5e-4 and res["t_end"] == pytest.approx(0.05, abs=1e-15)
    assert res["steps"] == 100 and res["time_points"] == 101
    assert res["elements"] == {"crank": 6, "coupler": 6, "follower": 6}
    run = out["run"]
    assert run["steps"] == 100
    assert run["newton_iterations"] >= run["steps"] and run["factorizations"] >= 1
    assert 0 <= run["step_cuts"] < run["steps"]
    est = Problem("fourbar", overrides={"time.t_end": 0.05}).memory_estimate(gradient=False)
    assert run["memory_estimate"] == pytest.approx(est.total, rel=1e-12)
    assert run["wall_time"] >= run["simulation_wall_time"] > 0 and run["cpu_time"] > 0
    assert run["units"] == {"wall_time": "s", "cpu_time": "s", "simulation_wall_time": "s",
                            "memory_estimate": "B"}
    assert out["feasibility_tol"] == FEASIBILITY_TOL and out["case"] == "fourbar"


def test_json_units_of_values_and_gradients(capsys):
    """units: the fourbar's variables p1..p3 in mm (case file), deviation in m, mass in kg,
    gradients per mm. The unit is checked on the number: the mass gradient along p1 is
    rho pi d L / 2 per metre of diameter, 2757 pi 0.25 0.3048 / 2 = 330.0 kg/m, i.e.
    0.3300 kg/mm at d = 250 mm (tolerance 1e-9 relative: the mass is exact)."""
    out = _json(capsys, ["simulate", "fourbar", "--t-end", "0.01", "--gradient", "--json"])
    u = out["units"]
    assert out["variables"] == ["p1", "p2", "p3"] and u["design"] == ["mm"] * 3
    assert u["responses"] == {"deviation_A": "m", "mass": "kg"}
    assert u["gradients"]["deviation_A"] == ["m/mm"] * 3
    assert u["gradients"]["mass"] == ["kg/mm"] * 3
    assert u["objective"] == "kg" and u["d_objective"] == ["kg/mm"] * 3
    assert u["constraints"] == "1" and u["jacobian"] == ["1/mm"] * 3 and u["time"] == "s"
    expected = 2757.0 * math.pi * 0.25 * 0.3048 / 2 * 1e-3
    assert out["responses"]["mass"]["gradient"][0] == pytest.approx(expected, rel=1e-9)


# ----------------------------------------------------------------------------- no responses
def test_a_case_without_responses_simulates_its_motion(tmp_path, capsys):
    """A case without [[responses]]: `simulate` runs the motion (its 100 steps of the
    0.05 s given), prints its summary and what to add in the case's words; --out writes the
    motion (before: 'wall time 0.000 s' having done nothing, and --out refused with "store=
    asks for coordinates"); `check` says there is nothing to check. The crank's largest deflection from the rigid motion is at least
    the deviation (33) of its tip A, which the full case computes on the same run (eq. 33:
    the norm of A's displacement from its rigid position; A is a node of the crank)."""
    case = _without_responses(tmp_path)
    npz = tmp_path / "motion.npz"
    assert main(["simulate", str(case), "--t-end", "0.05", "--out", str(npz)]) == 0
    text = capsys.readouterr().out
    assert "add a [[responses]] table" in text and "100 steps of h = 0.0005 s" in text
    assert "largest deflection from the rigid motion" in text and "motor" in text
    assert "store=" not in text and np.load(npz)["q"].shape[0] == 101
    out = _json(capsys, ["simulate", str(case), "--t-end", "0.05", "--json"])
    assert out["run"]["steps"] == 100 and "add a [[responses]] table" in out["notes"][0]
    full = _json(capsys, ["simulate", "fourbar", "--t-end", "0.05", "--json"])
    crank = out["motion"]["deflection"]["crank"]["max"]
    assert crank >= full["responses"]["deviation_A"]["max"] * (1 - 1e-12)
    assert out["motion"]["drives"]["motor"]["unit"] == "N m"
    assert out["motion"]["drives"]["motor"]["max_abs"] > 0
    ev = _json(capsys, ["evaluate", str(case), "--t-end", "0.05", "--json"])
    assert ev["run"]["steps"] == 100 and "motion" in ev
    assert main(["check", str(case)]) == 2            # it said "every response converged"
    assert "add a [[responses]] table" in capsys.readouterr().err


# ----------------------------------------------------------------------------- digits, tolerance
def _synthetic(values, g, t):
    return Evaluation(x=np.array([250.0, 250.0, 250.0]), t=t, values=values, gradients={},
                      objective=None, d_objective=None, constraints=np.array([g]),
                      jacobian=None, constraint_names=["deviation_A"],
                      units={"responses": {"deviation_A": "m"}})


def test_summary_digits_and_one_feasibility_tolerance(capsys):
    """A deviation of 1.0000009644 mm, g = 9.644e-7 relative to the 1 mm limit: the summary
    shows 0.001000000964 m (it printed 0.001), and calls the design feasible as the optimizers
    do: Evaluation, OptimizationResult, the cycles' control, optimize_fully and multistart all
    take FEASIBILITY_TOL = 1e-6 (Evaluation took 1e-9, the optimizers 1e-6); at g = 1.1e-6
    every verdict is 'infeasible'."""
    from flexmbs.cli.common import print_evaluation
    from flexmbs.methods.cycles import CycleControl
    from flexmbs.methods.result import OptimizationResult
    from flexmbs.model.options import FullyOptions, MultistartOptions

    t = np.linspace(0.0, 0.5, 1001)
    v = 1.0000009644e-3 * np.sin(np.pi * t / 0.5)
    ev = _synthetic({"deviation_A": v}, v.max() / 1e-3 - 1.0, t)
    print_evaluation(Problem("fourbar"), ev)
    text = capsys.readouterr().out
    assert "max 0.001000000964 m" in text and "feasible: largest g = 9.644e-07" in text
    assert "(step 500 of 1000)" in text
    assert FEASIBILITY_TOL == 1e-6
    assert inspect.signature(CycleControl).parameters["feasibility_tol"].default == 1e-6
    assert FullyOptions().constraint_violation == 1e-6       # optimize_fully's
    assert MultistartOptions().feasibility_tol == 1e-6       # multistart's
    fields = {f: None for f in inspect.signature(OptimizationResult).parameters}
    for g, feasible in ((9.644e-7, True), (1.1e-6, False)):
        assert _synthetic({"deviation_A": v}, g, t).feasible is feasible
        assert OptimizationResult(**dict(fields, max_violation=g)).feasible is feasible


# ----------------------------------------------------------------------------- two peaks
def test_gradient_of_a_maximum_with_two_tied_peaks_warns(capsys):
    """v = sin^2(2 pi t) (1 + a t) on [0, 1] has two peaks, at t = 0.25 and 0.75, whose values
    differ by a/2 relative: with a = 1e-3 (0.05 %, within PEAK_TIE_REL = 1 %) and gradients
    that differ there (dv/dp = t), the maximum is not differentiable and the summary and the
    JSON say so, naming both times and KS; with a = 0.1 (5 %), with equal gradients at both
    peaks, or with one peak (sin^2(pi t)), no warning."""
    from flexmbs.cli.common import print_evaluation
    from flexmbs.output import max_gradient_warning

    t = np.linspace(0.0, 1.0, 1001)
    g = t[:, None] * np.ones((1, 3))
    v = np.sin(2 * np.pi * t) ** 2 * (1 + 1e-3 * t)
    ev = _synthetic({"deviation_A": v}, -0.5, t)
    ev.gradients = {"deviation_A": g}
    w = ev.to_json()["warnings"]
    assert len(w) == 1 and "t = 0.75 s" in w[0] and "t = 0.25 s" in w[0] and "'ks'" in w[0]
    print_evaluation(Problem("fourbar"), ev)
    assert "warning         deviation_A" in capsys.readouterr().out
    v_far = np.sin(2 * np.pi * t) ** 2 * (1 + 0.1 * t)
    assert max_gradient_warning("r", v_far, g, t) is None
    assert max_gradient_warning("r", v, np.ones((t.size, 3)), t) is None
    assert max_gradient_warning("r", np.sin(np.pi * t) ** 2, g, t) is None


# ----------------------------------------------------------------------------- static start
def _fourbar_at(speed, start):
    """The fourbar over 0.01 s, its crank at `speed` rad/s from t = 0 (a linear law)."""
    return Problem("fourbar", overrides={
        "time.start": start, "time.t_end": 0.01,
        "drives.0.law": {"type": "polynomial", "coefficients": [0.0, speed]}})


def test_static_start_with_a_moving_drive_says_what_to_do():
    """start = 'static' assumes rest: with the crank already at 10 rad/s at t = 0 a
    SettingWarning names the drive and suggests start = 'rest' or a ramp; a run that fails
    there (1000 rad/s without step cuts: Newton diverges, measured at t = 0.0015 s) says the
    same in its SimulationError; the same failure from start = 'rest' does not, and a static
    start whose drives start at rest (cases/robot_2dof.toml: its cycloid path) warns nothing."""
    from flexmbs.analysis.simulate import simulate

    with pytest.warns(SettingWarning, match=r"drive motor.*start = 'rest'.*ramp_to_speed"):
        _fourbar_at(10.0, "static").simulate()
    for start, hint in (("static", True), ("rest", False)):
        model, t_end, h, kw = _fourbar_at(1000.0, start)._run(None, False, None, None)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SettingWarning)
            with pytest.raises(SimulationError) as err:
                simulate(model, t_end, h, **dict(kw, settings=kw["settings"].replace(max_cuts=0)))
        assert ("assumes the mechanism at rest" in str(err.value)) is hint
    with warnings.catch_warnings():
        warnings.simplefilter("error", SettingWarning)
        Problem("robot_2dof", overrides={"time.t_end": 0.01}).simulate()
