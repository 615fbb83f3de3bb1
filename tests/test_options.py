"""The option objects of the methods and optimizers (flexmbs.model.options): their tables
agree with the code they configure and with docs/optimizers.md, bad values and options of
another optimizer are errors naming them, the case's [optimize] table and `--set optimize...`
reach the optimizer, the options used are recorded (result, history, fingerprint), and the
old keywords give the same run as options= with a DeprecationWarning."""
from __future__ import annotations

import ast
import inspect
import json
import pathlib
import warnings

import numpy as np
import pytest

from flexmbs.errors import CaseError, ModelError, SettingWarning
from flexmbs.methods.fully import OPTIMIZERS
from flexmbs.model.options import (build, doc_rows, FullyOptions, markdown_table, MMAOptions,
                                   MultistartOptions, NLoptOptions, OPTIMIZER_OPTIONS,
                                   OptimizeSection, SLSQPOptions, SQPOptions, WeaklyOptions)
from flexmbs.optimize import multistart, optimize_fully, optimize_weakly, read_history
from flexmbs.problem import FEASIBILITY_TOL, Problem

DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs"
KINDS = [FullyOptions, SQPOptions, MMAOptions, SLSQPOptions, NLoptOptions, WeaklyOptions,
         MultistartOptions]


def _robot(**overrides):
    return Problem("robot_2dof", overrides={"time.t_end": 0.1, **overrides})


@pytest.mark.parametrize("kind", KINDS + [OptimizeSection], ids=lambda k: k.__name__)
def test_docstring_table_is_the_fields(kind):
    """Each options class's docstring table lists its fields, in order, with their defaults
    (a literal, or the class of a nested table followed by '()')."""
    rows = doc_rows(kind)
    own = [n for n in kind.model_fields
           if kind is not OptimizeSection or n not in FullyOptions.model_fields]
    assert [r[0] for r in rows] == own
    for name, text, _ in rows:
        default = kind.model_fields[name].default
        if text.endswith("()"):
            assert type(default).__name__ + "()" == text, name
        else:
            assert ast.literal_eval(text) == default, name


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.__name__)
def test_docs_show_the_tables(kind):
    """docs/optimizers.md holds every options class's table as generated from it."""
    assert markdown_table(kind) in (DOCS / "optimizers.md").read_text(encoding="utf-8")


def test_defaults_are_those_of_the_code_they_configure():
    """The tables' defaults equal the defaults of what they configure: MMA.__init__'s keywords
    (flexmbs.optimizers.mma), run_nlopt's, _run_sqp's absent (its radius0/radius_max are
    required: SQPOptions is their only default), FEASIBILITY_TOL; and the optimizer names of
    the tables are those of optimize_fully."""
    from flexmbs.optimizers.library import run_nlopt
    from flexmbs.optimizers.loops import _run_slsqp, _run_sqp
    from flexmbs.optimizers.mma import MMA

    mma = {n: p.default for n, p in inspect.signature(MMA.__init__).parameters.items()
           if p.kind is p.KEYWORD_ONLY}
    assert MMAOptions().mma_keywords() == mma
    nl = inspect.signature(run_nlopt).parameters
    for name in ("screen", "log_scale", "initial_step", "max_restarts", "feasibility_phase"):
        assert getattr(NLoptOptions(), name) == nl[name].default, name
    assert SLSQPOptions().ftol == inspect.signature(_run_slsqp).parameters["ftol"].default
    assert SQPOptions().model_fidelity == inspect.signature(_run_sqp).parameters["fidelity"].default
    assert FullyOptions().constraint_violation == FEASIBILITY_TOL
    assert MultistartOptions().feasibility_tol == FEASIBILITY_TOL
    assert set(OPTIMIZER_OPTIONS) == set(OPTIMIZERS)
    literal = MultistartOptions.model_fields["optimizer"].annotation.__args__
    assert set(literal) == set(OPTIMIZERS) | {"auto"}


@pytest.mark.parametrize("kind, data, text", [
    (FullyOptions, dict(max_iterations=2.5), "option max_iterations = 2.5: Input should be a valid integer"),
    (FullyOptions, dict(kkt_tol=True), "option kkt_tol = True"),
    (FullyOptions, dict(sqp=dict(trust_radius=0)), "option sqp.trust_radius = 0: Input should be greater than 0"),
    (FullyOptions, dict(nlopt=dict(screen=0.5)), "option nlopt.screen = 0.5: Input should be less than or equal to 0"),
    (FullyOptions, dict(verify=0.5), "option verify = 0.5: must be True, False, 'check' or a relative accuracy"),
    (FullyOptions, dict(trust_radus=0.1), "unknown option 'trust_radus'; allowed: max_iterations"),
    (WeaklyOptions, dict(damping=1.5), "option damping = 1.5: Input should be less than or equal to 1"),
    (WeaklyOptions, dict(esl_blend=1.0), "option esl_blend = 1.0: Input should be less than 1"),
    (MultistartOptions, dict(sampler="halton"), "option sampler = 'halton': Input should be 'sobol' or 'lhs'"),
    (MultistartOptions, dict(starts=0), "option starts = 0: Input should be greater than or equal to 1"),
    (MultistartOptions, dict(start_range=[[float("nan"), 1.0], [2.0, 3.0]]), "option start_range.0.0 = nan: Input should be a finite number"),
    (MultistartOptions, dict(start_range=[[1.0, 1.0], [2.0]]), "option start_range = [[1.0, 1.0], [2.0]]: the lower and the upper design must have as many values"),
    (MultistartOptions, dict(start_range=[[], []]), "option start_range.0 = []: List should have at least 1 item"),
    (NLoptOptions, dict(params={"x": float("nan")}), "option params.x = nan: Input should be a finite number"),
    (MMAOptions, dict(move=1.5), "option move = 1.5: Input should be less than or equal to 1"),
    (MMAOptions, dict(asyincr=1.0), "option asyincr = 1.0: Input should be greater than 1"),
    (MMAOptions, dict(asydecr=1.0), "option asydecr = 1.0: Input should be less than 1"),
    (MMAOptions, dict(asydecr=0.0), "option asydecr = 0.0: Input should be greater than 0"),
    (MMAOptions, dict(albefa=1.0), "option albefa = 1.0: Input should be less than 1"),
    (FullyOptions, {"mma": {"move": 0.3}, "move": 0.2}, "option move = 0.2 and option mma.move = 0.3 differ; give it once"),
    (FullyOptions, {"sqp": SQPOptions(trust_radius=0.1), "trust_radius": 0.3}, "option trust_radius = 0.3 and option sqp.trust_radius = 0.1 differ"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_validation_names_the_option(kind, data, text):
    """A bad value is a ModelError naming the option (its table), the value and what is
    allowed."""
    with pytest.raises(ModelError) as err:
        build(kind, data)
    assert text in str(err.value)


def test_flat_option_equal_to_its_table_is_taken():
    """The same option flat and in its table with one value is that value (not an error)."""
    assert build(FullyOptions, {"mma": {"move": 0.3}, "move": 0.3}).mma.move == 0.3


def test_option_of_another_optimizer_is_refused():
    """An SQP option given in options= (flat, or by the old keyword) to a run whose optimizer
    the call names ('mma') is a ModelError naming the option, the optimizer it belongs to and
    the one run (once: "mma (as asked)"), before any simulation."""
    robot = _robot()
    with pytest.raises(ModelError, match=r"option sqp.trust_radius = 0.1 belongs to optimizer "
                                         r"'sqp', but the run uses mma \(as asked\); leave") as e:
        optimize_fully(robot, optimizer="mma", options={"trust_radius": 0.1})
    assert "(mma (as asked))" not in str(e.value)
    with pytest.warns(DeprecationWarning), pytest.raises(ModelError, match=r"option sqp.trust_"
                                                         r"radius = 0.1 belongs to optimizer"):
        optimize_fully(robot, optimizer="mma", trust_radius=0.1)


def test_option_of_another_optimizer_is_set_aside_with_a_warning():
    """optimizer 'auto' (the SQP on the robot's 4 variables) with an NLopt option (the old
    keyword screen=-0.2): a SettingWarning naming nlopt.screen and the SQP, and the run's
    iterates are bitwise those of the same run without that option (it is not used); the
    result records the SQP's table only."""
    with pytest.warns(SettingWarning, match=r"option nlopt.screen = -0.2 belongs to optimizer "
                                            r"'nlopt-mma' / 'nlopt-ccsaq' / 'nlopt-slsqp', but "
                                            r"the run uses sqp \(auto: 4 design variables"), \
            pytest.warns(DeprecationWarning):
        old = optimize_fully(_robot(), screen=-0.2, max_iterations=1, verify=False)
    new = optimize_fully(_robot(), options=dict(max_iterations=1, verify=False))
    assert [r["design"] for r in old.history] == [r["design"] for r in new.history]
    assert "nlopt" not in old.details["options"] and old.details["optimizer"] == "sqp"


def test_case_table_of_another_optimizer_warns():
    """A case's [optimize.sqp] table in a run of MMA (optimizer='mma' in the call, options
    from the case) is set aside with a SettingWarning naming it and MMA, not refused: the
    run goes on to the start's check (a start outside the bounds, here: ModelError)."""
    prob = _robot(**{"optimize.optimizer": "sqp", "optimize.sqp.trust_radius": 0.1})
    with pytest.warns(SettingWarning, match=r"option sqp.trust_radius = 0.1 belongs to "
                                            r"optimizer 'sqp', but the run uses mma \(as "
                                            r"asked\): not used"), \
            pytest.raises(ModelError, match=r"lies outside its bounds"):
        optimize_fully(prob, np.full(4, 1e6), optimizer="mma")


def test_multistart_checks_another_optimizers_table_before_drawing(monkeypatch):
    """A multi-start (default optimizer nlopt-mma) of a case with an [optimize.sqp] table: one
    SettingWarning naming it, before any start is drawn; with fully= holding that table and
    options= naming the optimizer, a ModelError, before any start is drawn (the sampler is
    replaced by one that fails when called)."""
    import flexmbs.methods.multistart as ms

    def drawn(*args, **kwargs):
        raise AssertionError("starts drawn")
    monkeypatch.setattr(ms, "start_designs", drawn)
    prob = _robot(**{"optimize.sqp.trust_radius": 0.1})
    with pytest.warns(SettingWarning, match=r"option sqp.trust_radius = 0.1 belongs to "
                                            r"optimizer 'sqp', but the run uses nlopt-mma "
                                            r"\(the multi-start's optimizer\)") as rec, \
            pytest.raises(AssertionError, match="starts drawn"):
        multistart(prob, 2, workers=1)
    assert sum(issubclass(w.category, SettingWarning) for w in rec) == 1
    with pytest.raises(ModelError, match=r"option sqp.trust_radius = 0.1 belongs to optimizer "
                                         r"'sqp', but the run uses mma \(the multi-start's "
                                         r"optimizer\); leave"):
        multistart(_robot(), options=dict(starts=2, optimizer="mma"),
                   fully={"sqp": {"trust_radius": 0.1}}, workers=1)


def test_case_start_range_has_one_value_per_variable():
    """[optimize.multistart] start_range with 1 value per design for the robot's 4 variables
    is a CaseError naming the key and the variables."""
    with pytest.raises(CaseError, match=r"optimize.multistart.start_range: .* one value per "
                                        r"design variable \(4: "):
        _robot(**{"optimize.multistart.start_range": [[10.0], [60.0]]})


def test_case_start_range_counts_element_wise_variables():
    """robot_2dof_tapered has 2 [[design]] entries of 8 element-wise diameters each: a
    start_range of 16 values per side is accepted, one of 2 is a CaseError counting 16."""
    from flexmbs.problem import Problem
    p = Problem("robot_2dof_tapered", {"optimize.multistart.start_range": [[20.0] * 16,
                                                                            [40.0] * 16]})
    assert len(p.description.optimize.multistart.start_range[0]) == len(p.mechanism.variables)
    with pytest.raises(CaseError, match=r"one value per design variable \(16: "):
        Problem("robot_2dof_tapered", {"optimize.multistart.start_range": [[20.0] * 2,
                                                                            [40.0] * 2]})


def test_options_are_frozen():
    """An options object cannot be changed after it is built (a run's record stays true)."""
    o = FullyOptions()
    with pytest.raises(Exception, match="frozen"):
        o.max_iterations = 3


def test_old_keywords_warn_and_give_the_same_run():
    """optimize_fully(max_iterations=3, trust_radius=0.1, verify=False) (the old spelling)
    warns, naming options=, and follows the same iterates, bitwise, as options= with the
    same values; and options=None follows those of the defaults given explicitly."""
    with pytest.warns(DeprecationWarning, match=r"optimize_fully\(max_iterations=\.\.\., "
                                                r"trust_radius=\.\.\., verify=\.\.\.\) is "
                                                r"deprecated: give options=FullyOptions"):
        old = optimize_fully(_robot(), max_iterations=3, trust_radius=0.1, verify=False)
    new = optimize_fully(_robot(), options=dict(max_iterations=3, trust_radius=0.1,
                                                verify=False))
    assert [r["design"] for r in old.history] == [r["design"] for r in new.history]
    assert old.objective == new.objective
    assert len(new.history) == 4 and new.details["options"]["sqp"]["trust_radius"] == 0.1


def test_weakly_old_keywords_warn_and_give_the_same_run():
    """optimize_weakly(max_cycles=2, verify=False) (old spelling) warns and gives the cycles
    of options=dict(max_cycles=2, verify=False), bitwise."""
    with pytest.warns(DeprecationWarning, match=r"optimize_weakly\(max_cycles=\.\.\., "
                                                r"verify=\.\.\.\) is deprecated"):
        old = optimize_weakly(_robot(), max_cycles=2, verify=False)
    new = optimize_weakly(_robot(), options=WeaklyOptions(max_cycles=2, verify=False))
    assert [r["design"] for r in old.history] == [r["design"] for r in new.history]
    assert new.details["options"] == WeaklyOptions(max_cycles=2, verify=False).as_dict()


def test_multistart_old_keywords_warn_and_give_the_same_starts():
    """multistart(case, 2, optimizer='mma', max_iterations=1, verify=False) (old spelling)
    warns and gives the local optima of options=/fully= with the same values."""
    with pytest.warns(DeprecationWarning, match=r"multistart\(.*is deprecated"):
        old = multistart(_robot(), 2, optimizer="mma", max_iterations=1, verify=False,
                         workers=1)
    new = multistart(_robot(), options=dict(starts=2, optimizer="mma", verify=False),
                     fully=dict(max_iterations=1), workers=1)
    assert [o["design"] for o in old.optima] == [o["design"] for o in new.optima]
    assert new.details["options"]["max_iterations"] == 1
    assert new.details["multistart"]["optimizer"] == "mma"


def test_case_optimize_table_is_used_and_validated():
    """The case's [optimize] table sets the optimizer and the options of a call that gives
    none (one MMA iteration here, recorded in details['options']); a bad value in it is a
    CaseError naming optimize.max_iterations."""
    prob = _robot(**{"optimize.optimizer": "mma", "optimize.max_iterations": 1,
                     "optimize.verify": False, "optimize.mma.move": 0.2})
    res = optimize_fully(prob)
    assert res.details["optimizer"] == "mma" and res.iterations == 1
    assert res.details["options"]["mma"]["move"] == 0.2
    with pytest.raises(CaseError, match=r"optimize.max_iterations"):
        _robot(**{"optimize.max_iterations": 2.5})


def test_set_optimize_reaches_the_optimizer(capsys):
    """`flexmbs optimize --set optimize.max_iterations=1 --set optimize.sqp.trust_radius=0.05`
    runs one iteration of the SQP with that radius (the result's options)."""
    from flexmbs.cli.main import main

    code = main(["optimize", "robot_2dof", "--t-end", "0.1", "--method", "fully", "--json",
                 "--no-verify", "--no-progress", "--set", "optimize.max_iterations=1",
                 "--set", "optimize.sqp.trust_radius=0.05"])
    out = json.loads(capsys.readouterr().out)
    assert code in (0, 1)
    assert out["iterations"] == 1 and out["trust_radius"] == 0.05
    assert out["options"]["max_iterations"] == 1
    assert out["options"]["sqp"]["trust_radius"] == 0.05


def test_command_line_optimizer_sets_aside_the_cases_table(capsys):
    """`flexmbs optimize --optimizer mma --set optimize.sqp.trust_radius=0.05`: a
    SettingWarning on stderr naming the SQP's option, and one MMA iteration (its table
    recorded, not the SQP's)."""
    from flexmbs.cli.main import main

    code = main(["optimize", "robot_2dof", "--t-end", "0.1", "--method", "fully", "--json",
                 "--no-verify", "--no-progress", "--optimizer", "mma", "--set",
                 "optimize.max_iterations=1", "--set", "optimize.sqp.trust_radius=0.05"])
    captured = capsys.readouterr()
    assert ("SettingWarning: option sqp.trust_radius = 0.05 belongs to optimizer 'sqp', but the "
            "run uses mma (as asked): not used") in captured.err
    out = json.loads(captured.out)
    assert code in (0, 1)
    assert out["optimizer"] == "mma" and out["iterations"] == 1
    assert "sqp" not in out["options"] and "mma" in out["options"]


def test_options_recorded_in_history_and_resume_refuses_another(tmp_path):
    """A history's first line holds the options used whole; resuming it with another option
    (the SQP's trust_radius) is refused, naming the option; with more iterations it is not."""
    h = tmp_path / "h.jsonl"
    optimize_fully(_robot(), history=h, options=dict(max_iterations=1, verify=False))
    first = json.loads(h.read_text().splitlines()[0])
    assert first["options"] == dict(FullyOptions(max_iterations=1, verify=False).record("sqp"),
                                    optimizer="sqp")
    with pytest.raises(ModelError, match=r"option sqp.trust_radius: 0.2 -> 0.1"):
        optimize_fully(_robot(), history=h, resume=True,
                       options=dict(max_iterations=2, verify=False, trust_radius=0.1))
    res = optimize_fully(_robot(), history=h, resume=True,
                         options=dict(max_iterations=2, verify=False))
    assert res.iterations == 2 and len(read_history(h)) == 3
    assert np.isfinite(res.objective)


def test_case_weakly_table_is_used_and_validated():
    """The case's [optimize.weakly] table sets the weakly coupled method's options of a call
    that gives none (one cycle here, recorded in details['options']); a bad value in it is a
    CaseError naming optimize.weakly.damping."""
    prob = _robot(**{"optimize.weakly.max_cycles": 1, "optimize.weakly.verify": False})
    res = optimize_weakly(prob)
    assert res.iterations == 1 and res.details["options"]["max_cycles"] == 1
    with pytest.raises(CaseError, match=r"optimize.weakly.damping"):
        _robot(**{"optimize.weakly.damping": 1.5})


def test_stored_start_with_other_limits_runs_again(tmp_path):
    """docs/optimizers.md: a stored multi-start start is reused with the same options, and run
    again (a warning naming the starts) when max_iterations differs: its result then stops at
    the new limit (2 MMA iterations, not the stored 1; the robot's objective still falls by
    60 % in the first, so neither start converges earlier)."""
    kw = dict(options=dict(starts=2, optimizer="mma", verify=False), workers=1,
              store=tmp_path / "starts")
    multistart(_robot(), fully=dict(max_iterations=1), **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("error")              # reused: no warning, no start run
        same = multistart(_robot(), fully=dict(max_iterations=1), **kw)
    assert all("maximum number of iterations (1) reached" in o["reason"] for o in same.optima)
    with pytest.warns(UserWarning, match=r"2 stored result\(s\) answer another question, their "
                                         r"jobs run again: .*start000.json \(option options."
                                         r"max_iterations: 1 -> 2\)"):
        more = multistart(_robot(), fully=dict(max_iterations=2), **kw)
    assert all("maximum number of iterations (2) reached" in o["reason"] for o in more.optima)


def test_flat_option_overrides_a_table_of_defaults():
    """A flat option over a table that holds only defaults (FullyOptions().as_dict(), or an
    SQPOptions() object) is taken (trust_radius 0.3), not refused as given twice."""
    base = build(FullyOptions, {}).as_dict()
    assert build(FullyOptions, dict(base, trust_radius=0.3)).sqp.trust_radius == 0.3
    assert build(FullyOptions, {"trust_radius": 0.3, "sqp": SQPOptions()}).sqp.trust_radius == 0.3
