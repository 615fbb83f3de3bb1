"""SimulationSettings (flexmbs.analysis.settings): the one settings object of `simulate`, the
case file's [solver] table, the JSON output and the fingerprints that record it, and the
former keywords that still work with a DeprecationWarning."""
import dataclasses
import json
import math
import re

import numpy as np
import pytest

import flexmbs as fx
from flexmbs.analysis.settings import (DesignDerivatives, InitialConditions, RunSettings,
                                       SimulationSettings)
from flexmbs.analysis.validity import ValidityLimits
from flexmbs.cli.main import main
from flexmbs.errors import CaseError, ModelError
from flexmbs.model.fingerprint import differences, fingerprint
from flexmbs.problem import Problem, simulation_settings


def _arm():
    """A driven aluminium arm with a tip mass (0.02 s at h = 1e-3: 20 steps)."""
    m = fx.Model()
    arm = m.add_beam("arm", (0.0, 0.0), (0.6, 0.0), 2,
                     material=fx.Material(E=72e9, nu=0.3, rho=2700),
                     section=fx.Tube.with_wall_ratio(0.05, 0.1))
    m.add_point_mass(arm.last, 1.0)
    m.pin(arm.first)
    m.drive_rotation(arm.first, fx.TimeLaw(lambda t: np.pi * t ** 2, lambda t: 2 * np.pi * t,
                                            lambda t: 2 * np.pi + 0 * t))
    m.set_gravity(0.0, -9.81)
    return m, arm


def _same(a, b):
    """Bit-for-bit equal histories of two Results."""
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("q", "qd", "qdd", "mu"))


def test_the_defaults_are_simulates_former_defaults():
    """The documented defaults of SimulationSettings (its docstring's table) are simulate's
    former keyword defaults (rho_inf 0.5, start 'rest', newton 'auto', tol 1e-10, max_iter 20,
    max_cuts 6, solver 'auto', kscale/penalty automatic, polish off, validity 'warn' with
    ValidityLimits' limits, memory_limit None, store 'all'), and a case without [solver]
    gives exactly these settings."""
    s = SimulationSettings()
    assert s.to_dict() == dict(
        rho_inf=0.5, start="rest", newton="auto", tol=1e-10, max_iter=20, max_cuts=6,
        solver="auto", kscale=None, penalty=None, polish=False,
        validity=dataclasses.asdict(ValidityLimits()), memory_limit=None, store="all")
    assert simulation_settings(Problem("fourbar").description) == s
    for f in dataclasses.fields(SimulationSettings):
        assert f"    {f.name} " in SimulationSettings.__doc__, f.name   # one table row each


def test_settings_none_is_the_former_run_and_the_old_keywords_warn_and_agree():
    """settings=None and SimulationSettings() give bit-for-bit the same run; every former
    setting keyword, each at a value other than its default (with a DeprecationWarning naming
    settings=SimulationSettings), gives bit-for-bit the run of the SimulationSettings of the
    same values, and the run records each of these values (a keyword that was dropped on its
    way would record its default); q0=/qd0= and design_derivatives=/sensitivity_dofs= warn
    naming InitialConditions and DesignDerivatives and give the same states and dq/dp."""
    m, arm = _arm()
    ref = fx.simulate(m, 0.02, 1e-3)
    assert _same(ref, fx.simulate(m, 0.02, 1e-3, SimulationSettings()))
    values = dict(rho_inf=0.8, start="static", newton="full", tol=1e-11, max_iter=15,
                  max_cuts=4, solver="dense", kscale=2.0e6, penalty=3.0e6, polish=True,
                  validity="off", memory_limit=1e12, store=[arm.last])
    settings = SimulationSettings(**values)
    assert all(getattr(settings, k) != getattr(SimulationSettings(), k) for k in values)
    assert sorted(values) == sorted(f.name for f in dataclasses.fields(SimulationSettings))
    with pytest.warns(DeprecationWarning, match=r"settings=SimulationSettings\(rho_inf=..., "):
        old = fx.simulate(m, 0.02, 1e-3, **values)
    assert _same(fx.simulate(m, 0.02, 1e-3, settings), old)
    assert {k: getattr(old.settings, k) for k in values} == \
        {k: getattr(settings, k) for k in values}
    q0 = m.reference_coordinates()
    with pytest.warns(DeprecationWarning, match=r"initial=InitialConditions\(q0=...\)"):
        old = fx.simulate(m, 0.02, 1e-3, q0=q0)
    assert _same(ref, old)
    dprop = np.ones((5, len(m._elements), 1))
    new = fx.simulate(m, 0.02, 1e-3, derivatives=DesignDerivatives(dprop, dofs=arm.dofs))
    with pytest.warns(DeprecationWarning, match=r"derivatives=DesignDerivatives\(properties"):
        old = fx.simulate(m, 0.02, 1e-3, design_derivatives=dprop, sensitivity_dofs=arm.dofs)
    assert _same(new, old) and np.array_equal(new.dq, old.dq)


def test_result_records_the_settings_that_ran():
    """Result.settings is the RunSettings of the run: the settings given, solver 'auto'
    resolved to 'klu' (DENSE_MAX_UNKNOWNS = 0), h and t_end; Result.initial the state it
    started from; the former dict access warns and still answers."""
    m, _ = _arm()
    r = fx.simulate(m, 0.02, 1e-3, SimulationSettings(tol=1e-12, max_iter=30))
    assert isinstance(r.settings, RunSettings)
    assert (r.settings.tol, r.settings.max_iter, r.settings.solver, r.settings.h,
            r.settings.t_end) == (1e-12, 30, "klu", 1e-3, 0.02)
    assert np.array_equal(r.initial.q0, m.reference_coordinates())
    with pytest.warns(DeprecationWarning, match=r"use Result.settings.tol"):
        assert r.settings["tol"] == 1e-12


def test_result_settings_read_as_the_former_dict():
    """The deprecated dict reading of Result.settings answers as the former dict did, each
    read with a DeprecationWarning: kscale and penalty 0.0 when automatic (the dict held
    float(kscale or 0.0)), 'steps' the non-uniform step grid given (None on the uniform one),
    'q0'/'qd0' the initial state, get() with its default for a key the dict did not hold,
    'in' for the dict's keys only."""
    m, _ = _arm()
    grid = np.array([0.0, 5e-4, 2e-3, 4e-3])
    r = fx.simulate(m, 0.004, 1e-3, SimulationSettings(kscale=3e6))
    rs = fx.simulate(m, 0.004, 1e-3, steps=grid)
    with pytest.warns(DeprecationWarning, match=r"Result.settings\['kscale'\] is deprecated"):
        assert r.settings["kscale"] == 3e6
    with pytest.warns(DeprecationWarning, match=r"Result.settings\['penalty'\] is deprecated"):
        assert r.settings["penalty"] == 0.0
    with pytest.warns(DeprecationWarning, match="Result.steps"):
        assert r.settings["steps"] is None
    with pytest.warns(DeprecationWarning, match="Result.steps"):
        assert np.array_equal(rs.settings["steps"], grid)
    with pytest.warns(DeprecationWarning, match="Result.initial.q0"):
        assert np.array_equal(r.settings["q0"], r.initial.q0)
    with pytest.warns(DeprecationWarning):
        assert np.array_equal(r.settings.get("qd0"), r.initial.qd0)
    with pytest.warns(DeprecationWarning):
        assert r.settings.get("polish", True) is False and r.settings.get("nope", 7) == 7
    with pytest.warns(DeprecationWarning):
        assert "polish" in r.settings and "h" in r.settings and "nope" not in r.settings
    with pytest.warns(DeprecationWarning), pytest.raises(KeyError, match="nope"):
        r.settings["nope"]


@pytest.mark.parametrize("settings", [
    SimulationSettings(), SimulationSettings(memory_limit=math.inf),
    SimulationSettings(memory_limit=2e9, validity=ValidityLimits(mode="error", drift_warn=1e-8),
                       store=[0, 2], kscale=1e5, newton="reuse")])
def test_to_dict_round_trips_through_coerce(settings):
    """SimulationSettings.coerce(s.to_dict()) == s (to_dict's validity table and memory_limit
    'inf' are taken back), also through JSON (the JSON output's resolution.settings)."""
    assert SimulationSettings.coerce(settings.to_dict()) == settings
    assert SimulationSettings.coerce(json.loads(json.dumps(settings.to_dict()))) == settings


@pytest.mark.parametrize("field, value, allowed", [
    ("rho_inf", 1.5, r"\[0, 1\]"), ("start", "still", "'rest' or 'static'"),
    ("newton", "modified", "'full', 'reuse', 'auto'"), ("tol", -1.0, "> 0"),
    ("max_iter", 0, ">= 1"), ("max_cuts", 2.5, ">= 0"), ("solver", "lu", "'klu'"),
    ("kscale", 0.0, "positive"), ("penalty", math.inf, "positive"), ("polish", "yes", "True"),
    ("validity", "loud", "'warn', 'error', 'off'"), ("memory_limit", -1, "positive"),
    ("store", "tip", "'all' or a list"),
])
def test_each_invalid_field_is_a_model_error_naming_it(field, value, allowed):
    """Every field of SimulationSettings is validated when the object is made: a ModelError
    whose message names the field, the value and what is allowed."""
    with pytest.raises(ModelError) as err:
        SimulationSettings(**{field: value})
    msg = str(err.value)
    assert field in msg and repr(value) in msg
    assert re.search(allowed, msg), msg


def test_unknown_setting_and_replace():
    """replace() validates like the constructor; an unknown field is a ModelError listing the
    settings; a dict is taken as the settings' fields."""
    s = SimulationSettings().replace(tol=1e-12)
    assert s.tol == 1e-12 and SimulationSettings.coerce({"tol": 1e-12}) == s
    with pytest.raises(ModelError, match="tol must be > 0"):
        s.replace(tol=0.0)
    with pytest.raises(ModelError, match="unknown setting.*tolerance.*the settings are"):
        SimulationSettings.coerce({"tolerance": 1.0})
    with pytest.raises(TypeError, match="unexpected keyword argument 'tolerance'"):
        fx.simulate(_arm()[0], 0.02, 1e-3, tolerance=1.0)
    with pytest.raises(ModelError, match="initial state once"):
        fx.simulate(_arm()[0], 0.02, 1e-3, initial=InitialConditions(), q0=None)


def test_case_solver_table_is_validated():
    """[solver] is validated with the description: a bad value is a CaseError naming
    solver.KEY, a warning limit above its failure limit too."""
    with pytest.raises(CaseError, match=r"solver\.max_iter"):
        Problem("fourbar", {"solver.max_iter": 0})
    with pytest.raises(CaseError, match=r"solver\.linear_solver"):
        Problem("fourbar", {"solver.linear_solver": "lu"})
    with pytest.raises(CaseError, match="strain_warn = 0.2 is above strain_fail = 0.1"):
        Problem("fourbar", {"solver.strain_warn": 0.2, "solver.strain_fail": 0.1})
    with pytest.raises(CaseError, match=r"\[solver\].*strain_warn = 0.2 is above strain_fail"):
        Problem("fourbar", {"solver.strain_warn": 0.2})      # against the default 10 %
    p = Problem("fourbar", {"solver.tol": 1e-12, "solver.linear_solver": "dense",
                            "solver.validity": "error", "solver.drift_warn": 1e-7})
    assert (p.settings.tol, p.settings.solver, p.settings.validity.mode,
            p.settings.validity.drift_warn) == (1e-12, "dense", "error", 1e-7)


def test_set_solver_tol_reaches_the_core(capsys):
    """`flexmbs simulate --set solver.tol=1e-13` (fourbar, 0.05 s): the JSON's
    resolution.settings says tol = 1e-13, and Newton takes more iterations than at the
    default 1e-10 (the tolerance reached the core's convergence test)."""
    def run(*extra):
        assert main(["simulate", "fourbar", "--json", "--set", "time.t_end=0.05", *extra]) == 0
        return json.loads(capsys.readouterr().out)
    default, tight = run(), run("--set", "solver.tol=1e-13")
    assert default["resolution"]["settings"]["tol"] == 1e-10
    assert tight["resolution"]["settings"]["tol"] == 1e-13
    assert tight["run"]["newton_iterations"] > default["run"]["newton_iterations"]


def test_fingerprint_covers_the_settings():
    """A changed solver.tol changes the fingerprint of a stored result (its description's
    'solver' digest) and the fingerprint records the settings whole; a case without [solver]
    has no 'solver' digest (its fingerprint is that of a description without the table)."""
    base = Problem("fourbar").description
    tight = Problem("fourbar", {"solver.tol": 1e-12}).description
    fa, fb = fingerprint(base, "weakly"), fingerprint(tight, "weakly")
    assert "solver" not in fa["description"]
    assert differences(fa, fb) == ["the case description's solver"]
    assert fb["settings"]["tol"] == 1e-12 and fa["settings"]["tol"] == 1e-10
    assert fa["settings"]["max_iter"] == 20 and fa["settings"]["rho_inf"] == 0.5
