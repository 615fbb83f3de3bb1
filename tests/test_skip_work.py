"""Skip what a scene does not need: a Problem stores only the coordinates its
responses read, computes the rigid reference only for deviations (or drives that follow it),
differentiates nothing without gradients; the rigid reference's position analysis works on the
constraint rows' nodes only, whatever the number of elements.

Work is checked by counting (what is stored, which functions run), not by timing."""
import json
import math
import tomllib

import numpy as np
import pytest

from flexmbs.errors import ResourceError
from flexmbs.model.casefile import case_path
import flexmbs.model.kinematics as kinematics
import flexmbs.model.mechanism as mechanism
from flexmbs.model.mechanism import Mechanism
from flexmbs.problem import Problem
from flexmbs.resources import check_memory

FOURBAR_DESIGN = [69.85, 87.61, 37.22]          # Table 3, weakly coupled design (mm)


def _fourbar_dict():
    with open(case_path("fourbar"), "rb") as f:
        return tomllib.load(f)


def _fourbar_without_deviation():
    """The four-bar with a stress and a motor-torque response instead of its deviation."""
    d = _fourbar_dict()
    d["responses"] = [{"name": "coupler_stress", "type": "stress", "bodies": ["coupler"]},
                      {"name": "motor_torque", "type": "torque", "drive": "motor"},
                      {"name": "mass", "type": "mass"}]
    d["constraints"] = [{"response": "coupler_stress", "upper": 100e6}]
    d["time"]["t_end"] = 0.05
    return d


def test_evaluation_of_a_large_long_run_stores_only_the_response_coordinates(monkeypatch):
    """The four-bar with 2000 elements per link (36 009 coordinates) over 10^5 steps: the
    estimate of its evaluation stores q, qd, qdd of the 3 coordinates of point A (deviation
    (33)) and nothing else per step, 3 x 8 B x 3 x (10^5 + 1) exactly (resources.estimate_memory),
    while storing every coordinate would take 3 x 8 B x 36 009 x (10^5 + 1) = 86 GB; a 1 GB
    limit holds the evaluation and refuses store='all' before anything runs (ResourceError
    naming the stored outputs)."""
    ov = {f"bodies.{b}.elements": 2000 for b in ("crank", "coupler", "follower")}
    ov["time.t_end"] = 50.0
    prob = Problem("fourbar", overrides=ov)
    nt = prob.mechanism.nsteps + 1
    ndof = prob.mechanism.model.ndof
    assert nt == 100_001 and ndof == 3 * (3 * 4001)
    est = prob.memory_estimate(FOURBAR_DESIGN, gradient=True)
    every = prob.memory_estimate(FOURBAR_DESIGN, gradient=True, store="all")
    assert est.parts["stored q, qd, qdd"] == 3 * 8 * 3 * nt
    assert every.parts["stored q, qd, qdd"] == 3 * 8 * ndof * nt
    # the rest of the estimate does not depend on what is stored
    assert est.total - est.parts["stored q, qd, qdd"] == pytest.approx(
        every.total - every.parts["stored q, qd, qdd"], rel=1e-12)
    assert est.total < 0.5e9 < 50e9 < every.total
    check_memory(est, 1e9)                          # fits: no error
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", "1G")
    with pytest.raises(ResourceError, match="store fewer outputs") as info:
        prob.simulate(FOURBAR_DESIGN, store="all")
    assert info.value.required > 50e9 and info.value.available == 1e9


def test_evaluation_runs_under_a_limit_that_refuses_storing_everything(monkeypatch):
    """The four-bar (Table 3 design, 0.1 s): under a memory limit halfway between the estimate
    of its evaluation and that of storing every coordinate, `evaluate` runs (it keeps the 3
    coordinates of A) and gives the deviation that a run storing everything gives (to 1e-12
    of its maximum: what is stored does not change the solution), and store='all' is refused."""
    prob = Problem("fourbar", overrides={"time.t_end": 0.1})
    full = prob.simulate(FOURBAR_DESIGN, store="all")
    ref = prob.evaluate(FOURBAR_DESIGN, gradient=False)      # no limit
    est = prob.memory_estimate(FOURBAR_DESIGN, gradient=False)
    every = prob.memory_estimate(FOURBAR_DESIGN, gradient=False, store="all")
    limit = 0.5 * (est.total + every.total)
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", str(int(limit)))
    res = prob.simulate(FOURBAR_DESIGN)
    node_a = prob.mechanism.node[("crank", "A")]
    assert res.dofs.tolist() == [3 * node_a, 3 * node_a + 1, 3 * node_a + 2]
    assert full.dofs.size == prob.mechanism.model.ndof > 3
    ev = prob.evaluate(FOURBAR_DESIGN, gradient=False)
    dev = ev.values["deviation_A"]
    assert np.abs(dev - ref.values["deviation_A"]).max() <= 1e-12 * dev.max()
    assert np.abs(res.position(node_a) - full.position(node_a)).max() <= 1e-12
    with pytest.raises(ResourceError, match="store fewer outputs"):
        prob.simulate(FOURBAR_DESIGN, store="all")


def test_forces_alone_store_one_node_and_no_rigid_reference(monkeypatch):
    """A four-bar whose responses are a stress, a motor torque and the mass: its evaluation
    (with gradients) never computes the rigid reference (the rigid_reference the mechanism calls
    replaced by a function that fails), stores the coupler's nodes only; with the torque alone, one
    node's 3 coordinates (the torque comes from the multipliers, kept at every step). The
    same replacement does fail the deviation case, so it is the function the reference uses."""
    calls = []

    def fail(*args, **kwargs):
        calls.append(1)
        raise AssertionError("rigid reference computed")

    monkeypatch.setattr(mechanism, "rigid_reference", fail)
    prob = Problem(_fourbar_without_deviation())
    ev = prob.evaluate(FOURBAR_DESIGN, gradient=True)
    assert not calls
    assert ev.gradients["motor_torque"].shape == (prob.mechanism.nsteps + 1, 3)
    coupler = prob.mechanism.model.body("coupler").nodes
    assert prob.simulate(FOURBAR_DESIGN).dofs.size == 3 * len(coupler)
    torque = prob.simulate(FOURBAR_DESIGN, responses=["motor_torque"], gradient=True)
    assert torque.dofs.size == 3 and torque.dmu is not None
    with pytest.raises(AssertionError, match="rigid reference computed"):
        Problem("fourbar", overrides={"time.t_end": 0.05}).evaluate(FOURBAR_DESIGN,
                                                                     gradient=False)
    assert calls == [1]


def test_no_gradient_no_sensitivities(monkeypatch):
    """evaluate(x, gradient=False) asks no design derivative: the element property derivatives
    (the input of the sensitivity solves) are never computed, and the core reports no
    sensitivity factorization; with gradient=True the same replaced function is reached."""
    prob = Problem("fourbar", overrides={"time.t_end": 0.05})

    def fail(self, x):
        raise AssertionError("sensitivities asked")

    monkeypatch.setattr(Mechanism, "element_property_derivatives", fail)
    ev = prob.evaluate(FOURBAR_DESIGN, gradient=False)
    assert ev.gradients == {} and ev.jacobian is None
    assert ev.stats["sensitivity_factorizations"] == 0
    with pytest.raises(AssertionError, match="sensitivities asked"):
        prob.evaluate(FOURBAR_DESIGN, gradient=True)


def test_rigid_reference_work_does_not_grow_with_the_elements(monkeypatch):
    """The robot's rigid reference (position analysis) with 2 and 400 elements per arm: the
    analysis evaluates the node map only on the nodes the constraint rows use (4: O, A on
    each arm, the tip), whatever the mesh; its node histories follow by rigid transforms: the
    middle node of arm 1 lies halfway between O and A, and the tip on the path of eq. (26)
    (x0 + D(t), y0 + D(t), D the cycloid of docs/paper-cases.md), to 1e-12 m."""
    calls = []          # (times, nodes) of each evaluation of the node map
    original = kinematics._Poses.q

    def counted(self, z, nodes=None):
        times = int(np.prod(np.shape(z)[:-2]))
        calls.append((times, self.r.shape[0] if nodes is None else len(nodes)))
        return original(self, z, nodes)

    monkeypatch.setattr(kinematics._Poses, "q", counted)
    for nel in (2, 400):
        calls.clear()
        mech = Mechanism(Problem("robot_2dof", overrides={
            "bodies.arm1.elements": nel, "bodies.arm2.elements": nel,
            "time.t_end": 0.1}).description)
        # over the time grid at most the 4 nodes; every node only for single configurations
        # (the assembled initial state)
        assert sum(k for k, _ in calls) > mech.nsteps
        assert all(n <= 4 for k, n in calls if k > 1), (nel, calls)
        assert sum(1 for k, n in calls if n > 4) <= 4
        ref = mech.reference
        t = mech.t
        arm1 = mech.model.body("arm1").nodes
        mid = arm1[len(arm1) // 2]
        o, a, tip = (mech.node[k] for k in (("arm1", "O"), ("arm1", "A"), ("arm2", "tip")))
        xy = ref.coordinates([3 * n + k for n in (o, mid, a, tip) for k in (0, 1)])
        assert np.abs(xy[:, 2:4] - 0.5 * (xy[:, 0:2] + xy[:, 4:6])).max() <= 1e-12
        T = 0.5
        D = 0.5 * (t / T - np.sin(2 * math.pi * t / T) / (2 * math.pi))     # stroke 0.5 m
        x0, y0 = 0.21961524227066315, 0.21961524227066315
        assert np.abs(xy[:, 6] - (x0 + D)).max() <= 1e-12
        assert np.abs(xy[:, 7] - (y0 + D)).max() <= 1e-12


def test_rigid_reference_coordinates_are_computed_once_per_case(monkeypatch):
    """The rigid reference does not depend on the sizing design: evaluating the robot at three
    designs maps the poses to the deviation's nodes once per coordinate set (first design),
    not again at each design; what `coordinates` returns is the caller's to change (a changed
    copy leaves the next call's values as they were)."""
    calls = []
    original = kinematics._Poses.q

    def counted(self, z, nodes=None):
        calls.append(np.shape(z))
        return original(self, z, nodes)

    prob = Problem("robot_2dof", overrides={"time.t_end": 0.05})
    prob.evaluate(gradient=False)
    monkeypatch.setattr(kinematics._Poses, "q", counted)
    first = prob.evaluate(1.02 * prob.start, gradient=False)
    assert calls == []
    prob.evaluate(1.05 * prob.start, gradient=False)
    assert calls == []
    ref = prob.mechanism.reference
    a = ref.coordinates([0, 1])
    a[:] = np.nan
    assert np.all(np.isfinite(ref.coordinates([0, 1])))
    assert np.isfinite(first.objective)


def test_gradients_of_the_used_responses_only(monkeypatch):
    """evaluate(x, gradient='used') differentiates only what the objective (mass) and the
    constraint (coupler stress) read: the motor torque, reported but not constrained, gets no
    gradient and the simulation no multiplier derivatives (Result.dmu None, which
    gradient=True computes); the constraint jacobian is the one of gradient=True (1e-12
    relative: the same sensitivity solves). An unknown name is a ModelError naming it."""
    from flexmbs.errors import ModelError
    prob = Problem(_fourbar_without_deviation())
    seen = []
    original = Problem.simulate

    def spy(self, *args, **kwargs):
        res = original(self, *args, **kwargs)
        seen.append(res)
        return res

    monkeypatch.setattr(Problem, "simulate", spy)
    used = prob.evaluate(FOURBAR_DESIGN, gradient="used")
    assert prob.used_responses() == ["coupler_stress", "mass"]
    assert sorted(used.gradients) == ["coupler_stress", "mass"]
    assert seen[-1].dmu is None and seen[-1].dq is not None
    full = prob.evaluate(FOURBAR_DESIGN, gradient=True)
    assert seen[-1].dmu is not None and "motor_torque" in full.gradients
    scale = np.abs(full.jacobian).max()
    assert np.abs(used.jacobian - full.jacobian).max() <= 1e-12 * scale
    assert np.abs(used.d_objective - full.d_objective).max() <= 1e-12 * np.abs(
        full.d_objective).max()
    with pytest.raises(ModelError, match="unknown response.*'torque'"):
        prob.evaluate(FOURBAR_DESIGN, gradient=["torque"])
    with pytest.raises(ModelError, match="gradient must be True, False, 'used'"):
        prob.evaluate(FOURBAR_DESIGN, gradient="all")


def test_cli_simulate_stores_everything_only_for_out(monkeypatch, tmp_path, capsys):
    """`flexmbs simulate` keeps every coordinate only when --out (or --plot) asks for them:
    without it its one simulation stores the 3 coordinates of the four-bar's point A; with
    --out its one simulation stores all of them (the .npz holds every coordinate) and the
    responses are those of the lean run (the deviation history to 1e-12 m)."""
    import flexmbs.problem as problem_module
    from flexmbs.cli.main import main
    stored = []
    original = problem_module.simulate

    def spy(model, *args, **kwargs):
        res = original(model, *args, **kwargs)
        stored.append(res.dofs.size)
        return res

    monkeypatch.setattr(problem_module, "simulate", spy)
    assert main(["simulate", "fourbar", "--set", "time.t_end=0.05", "--json"]) == 0
    assert stored == [3]
    lean = json.loads(capsys.readouterr().out)["responses"]
    stored.clear()
    out = tmp_path / "r.npz"
    assert main(["simulate", "fourbar", "--set", "time.t_end=0.05", "--out", str(out)]) == 0
    ndof = Problem("fourbar", overrides={"time.t_end": 0.05}).mechanism.model.ndof
    assert stored == [ndof]
    with np.load(out) as d:
        assert d["q"].shape[1] == ndof
        name = next(k for k in d.files if k.startswith("response_deviation"))
        assert abs(d[name].max() - lean[name[len("response_"):]]["max"]) < 1e-12
    capsys.readouterr()
