"""The model sent to the core once (flexmbs.core.CoreModel, fortran/flexmbs_api.f90 model_create):
an opaque 64-bit address held by Python, shared by the designs and the threads of one mechanism,
released with its owner and rebuilt after pickling; the runs pass it with the design's element
properties and the law tables of their time grid."""
import copy
import gc
import pickle
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from flexmbs.analysis.settings import SimulationSettings
from flexmbs.analysis.simulate import simulate, system_matrices
from flexmbs.core import CoreModel, Status, core_model, core_model_args, simulate_arrays
from flexmbs.errors import ModelError
from flexmbs.problem import Problem


def _robot(t_end=0.01):
    p = Problem("robot_2dof", {"time.t_end": t_end})
    return p.mechanism, p.description.time.rho_inf


def _run(model, rho_inf, t_end=0.01):
    r = simulate(model, t_end, 5e-4, SimulationSettings(rho_inf=rho_inf, start="rest",
                                                        newton="full", solver="klu"))
    return r.q, r.mu


def test_the_address_above_2_31_reaches_the_core_whole():
    """The handle is a heap address (above 2**31 on a 64-bit Linux process) passed as a 64-bit
    integer: the counts the core reads back through it are the compiled model's (ndof, nc,
    nel, nnz of the 'klu' pattern, n = ndof + nc); a truncated address would read another
    memory's or fault."""
    mech, _ = _robot()
    cm, pat = mech.model.compile(), mech.model.pattern("klu")
    cmod = core_model(mech.model, "klu")
    handle = cmod.handle()
    if handle < 2 ** 31:
        pytest.skip(f"the heap of this process lies below 2**31 ({handle:#x})")
    assert handle >= 2 ** 31
    assert cmod.counts() == dict(ndof=cm.ndof, nc=cm.nc, nel=cm.nel, nload=cm.nload,
                                 nlaw=len(mech.model.laws()), nnz=pat["nnz"], nsd=cm.nsd,
                                 n=cm.ndof + cm.nc)


def test_designs_share_one_core_model_and_threads_give_the_serial_results():
    """Two designs of the robot (Mechanism.design_model) share the structure's one core model
    (built once: builds == 1) and differ only in their element properties; 8 runs of them
    alternating from 4 threads give each design's serial coordinates and multipliers bit for
    bit (a run only reads the shared model: the same arithmetic on the same inputs), and the
    two designs' results differ (a mix-up could not go unseen)."""
    mech, rho = _robot()
    lo, hi = np.asarray(mech.start, float), np.asarray(mech.start, float) * 1.3
    models = [mech.design_model(x) for x in (lo, hi)]
    serial = [_run(m, rho) for m in models]
    assert not np.array_equal(serial[0][0], serial[1][0])
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda k: (k % 2, _run(models[k % 2], rho)), range(8)))
    for k, (q, mu) in got:
        assert np.array_equal(q, serial[k][0]) and np.array_equal(mu, serial[k][1])
    assert core_model(models[0], "klu") is core_model(models[1], "klu")
    assert core_model(models[0], "klu").builds == 1


def test_a_copied_model_builds_its_own_core_model_with_the_same_results():
    """A deep copy of a model makes its own core model on first use (another address) and its
    run equals the original's bit for bit; a pickled CoreModel (sent to a worker process)
    rebuilds from its arrays to the same counts at another address; a model is released in
    the core when its CoreModel goes (its finalizer has run)."""
    mech, rho = _robot()
    model = mech.design_model(mech.start)
    ref = _run(model, rho)
    other = copy.deepcopy(model)
    assert core_model(other, "klu").handle() != core_model(model, "klu").handle()
    got = _run(other, rho)
    assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])
    cmod = CoreModel.of(model.compile(), model.pattern("dense"), len(model.laws()))
    sent = pickle.loads(pickle.dumps(cmod))
    assert sent.counts() == cmod.counts() and sent.handle() != cmod.handle()
    release = cmod._release
    assert release.alive
    del cmod
    gc.collect()
    assert not release.alive


def test_the_core_refuses_a_null_handle_and_another_models_extents(monkeypatch):
    """A run with the null address, or with the robot's address and the arrays of the
    four-bar (another ndof), returns Status.BAD_INPUT and computes nothing (no step, outputs
    zero); system_matrices of the robot handed the four-bar's core model raises ModelError."""
    import flexmbs.core as core
    mech, _ = _robot()
    model = mech.model
    grid = np.array([0.0, 5e-4])
    margs = core_model_args(model, "dense", grid)
    four = Problem("fourbar").mechanism.model
    other = core_model_args(four, "dense", grid)
    for args in (dict(margs, model=0), dict(other, model=margs["model"])):
        ndof = args["ndof"]
        out = simulate_arrays(
            **args, nsteps=1, q0=np.zeros(ndof), qd0=np.zeros(ndof), ap=np.zeros(1, np.int32),
            ai=np.zeros(1, np.int32), h=5e-4, rho_inf=0.5, tol=1e-8, max_iter=10, max_cuts=0,
            solver=0, newton=0, static_start=0, kscale=0.0, penalty=0.0,
            out_dofs=np.ones(1, np.int32), nv=0,
            dprop=np.zeros((5, args["el_prop"].shape[1], 1), order="F"),
            sens_dofs=np.ones(1, np.int32), want_dmu=0, ndmu=1, polish=0, ntape=1, nckr=1, nck=1,
            ckpt_every=0, restart=0, x_start=np.zeros(1), j_start=0, klu_analysis=0,
            tg=np.zeros(1))
        assert out.status == Status.BAD_INPUT and not out.q.any() and int(out.stats[5]) == 0
    monkeypatch.setattr(core, "core_model", lambda m, storage: CoreModel.of(
        four.compile(), four.pattern(storage), len(four.laws())))
    with pytest.raises(ModelError, match="extents of another model"):
        system_matrices(model, model.reference_coordinates())


def test_run_arguments_keep_their_model_alive_after_an_edit():
    """core_model_args hands the runs its CoreModel, not a bare address: a model edited after
    its arguments were made (its compiled form and CoreModel dropped from its caches) and
    collected still runs them on the model they were made of. The counts read through the
    arguments' model are the robot's before the edit (ndof 3 more after a point mass on a
    new node would be wrong), and a run gives the same motion as before the edit."""
    mech, rho_inf = _robot()
    model = mech.model
    grid = np.array([0.0, 5e-4])
    margs = core_model_args(model, "dense", grid)
    before = margs["model"].counts()
    node = model.add_node(5.0, 5.0)
    model.add_point_mass(node, 1.0)
    gc.collect()
    assert margs["model"].counts() == before
    assert model.compile().ndof == before["ndof"] + 3


def test_gravity_set_after_a_run_reaches_the_next_run():
    """set_gravity after a first run changes the next run (the compiled model and its
    CoreModel are made anew): a cantilever under gravity set after a run at zero gravity
    sags as one that had gravity from the start, to 1e-12 m (the same computation)."""
    import flexmbs as fx

    def arm():
        m = fx.Model("cantilever")
        b = m.add_beam("beam", (0, 0), (1.0, 0), 2, section=fx.Circle(0.02),
                       material=fx.Material(E=210e9, nu=0.3, rho=7800))
        m.clamp(b.first)
        return m, b

    late, beam = arm()
    simulate(late, 0.01, 5e-4)
    late.set_gravity(0.0, -9.81)
    tip_late = simulate(late, 0.01, 5e-4).q[-1]
    early, _ = arm()
    early.set_gravity(0.0, -9.81)
    tip_early = simulate(early, 0.01, 5e-4).q[-1]
    ref = late.reference_coordinates()
    tip_late, tip_early = tip_late - ref, tip_early - ref
    assert np.abs(tip_late).max() > 0
    assert np.abs(tip_late - tip_early).max() < 1e-12
