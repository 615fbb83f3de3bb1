"""The motion as a film and as a ParaView time series (flexmbs.visual.animation, flexmbs.visual.export,
``flexmbs animate``), on every shipped case: the files exist, hold the frames asked for, and
what ParaView would read back (meshio) is the case's geometry on the case's time grid."""
import re
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
from PIL import Image

from flexmbs.cli.main import main
from flexmbs.errors import ModelError
from flexmbs.model.casefile import available_cases
from flexmbs.model.description import Beam, Rigid, Stress
from flexmbs.problem import Problem
from flexmbs.visual.export import read_pvd
from flexmbs.visual.scene import frame_steps

CASES = sorted(available_cases())
FRAMES = 3
_RUNS = {}


def _run(case):
    """(problem, evaluation with its result) of a shipped case at its start, simulated once."""
    if case not in _RUNS:
        prob = Problem(case)
        _RUNS[case] = (prob, prob.evaluate(gradient=False, store="all"))
    return _RUNS[case]


@pytest.mark.parametrize("case", CASES)
def test_film_and_time_series_of_every_shipped_case(case, tmp_path):
    """A 3-frame GIF has 3 frames (Pillow reads them back); the .pvd names 3 .vtu files at the
    times j h of the case's grid (h from the case file), each with one point per node of the
    model and one cell per beam element of the case file (plus one per rigid outline segment
    and point mass); at t = 0 the rigid reference (points minus the deflection field) puts
    every beam's end nodes on the case file's points (1e-9 m; the points are the case's
    data, not computed) and the third node of every quadratic edge halfway between its first
    two (VTK's node order of a 'line3': ends, then middle; the beams are straight); where the case has a stress response, the written stress field's
    largest value over the response's beams equals the response at that step (relative 1e-9)."""
    prob, ev = _run(case)
    d = prob.description
    gif = tmp_path / "m.gif"
    a = ev.result.animate(gif, prob, evaluation=ev, frames=FRAMES)
    assert a.frames == FRAMES and Image.open(gif).n_frames == FRAMES

    pvd, files, steps = ev.result.to_vtk(tmp_path / "m.pvd", prob, frames=FRAMES)
    series = read_pvd(pvd)
    assert [f for _, f in series] == files and len(files) == FRAMES
    h = d.time.h
    assert np.allclose([t for t, _ in series], steps * h, rtol=0, atol=1e-12)
    nodes = {n for b in prob.mechanism.model.bodies.values() for n in b.nodes}
    elements = sum(b.elements for b in d.bodies if isinstance(b, Beam))
    beam_type = {b.order for b in d.bodies if isinstance(b, Beam)}
    mesh0 = meshio.read(files[0])
    assert mesh0.points.shape == (len(nodes), 3)
    kinds = np.concatenate(mesh0.cell_data["kind"])
    assert np.sum(kinds == 0) == elements
    if beam_type == {2}:
        assert sum(len(c.data) for c in mesh0.cells if c.type == "line3") == elements
    # rigid reference at t = 0: the case's points at the beams' ends
    rigid0 = mesh0.points[:, :2] - mesh0.point_data["deflection"][:, :2]
    for c in mesh0.cells:       # VTK's quadratic edge: both ends, then the middle node
        if c.type == "line3":
            ends = 0.5 * (rigid0[c.data[:, 0]] + rigid0[c.data[:, 1]])
            assert np.allclose(rigid0[c.data[:, 2]], ends, rtol=0, atol=1e-9)
    index = {n: i for i, n in enumerate(sorted(nodes))}
    mech = prob.mechanism
    for b in d.bodies:
        if isinstance(b, Beam):
            for p in (b.start, b.end):
                got = rigid0[index[mech.node[(b.name, p)]]]
                assert np.allclose(got, d.points[p], rtol=0, atol=1e-9), (b.name, p)
    for r in d.responses:
        if isinstance(r, Stress):
            beams = [k for k, b in enumerate(d.bodies) if b.name in r.bodies]
            for j, f in enumerate(files):
                m = meshio.read(f)
                s = np.concatenate(m.cell_data["stress"])
                body = np.concatenate(m.cell_data["body"])
                want = ev.values[r.name][steps[j]]
                assert np.isclose(np.max(s[np.isin(body, beams)]), want, rtol=1e-9)


def test_mp4_frames_and_duration(tmp_path):
    """An MP4 of 12 frames at 6 fps: ffmpeg (imageio-ffmpeg) counts 12 frames and 2 s."""
    import imageio_ffmpeg
    prob, ev = _run("slider_crank_press")
    out = tmp_path / "m.mp4"
    ev.result.animate(out, prob, evaluation=ev, frames=12, fps=6, color_by="stress")
    n, secs = imageio_ffmpeg.count_frames_and_secs(str(out))
    assert n == 12 and abs(secs - 2.0) < 0.1


def test_frames_are_spread_over_the_run():
    """100 frames of a 1301-point grid: 100 distinct steps, the first 0 and the last 1300,
    gaps of 13 or 14 steps (1300 / 99 = 13.1)."""
    s = frame_steps(1301, 100)
    assert s.size == 100 and s[0] == 0 and s[-1] == 1300
    assert set(np.diff(s)) <= {13, 14}
    assert np.array_equal(frame_steps(5, 100), np.arange(5))


def test_default_magnification_makes_the_deflection_visible():
    """The default factor is a round number (1, 2 or 5 x 10^k) making the largest magnified
    deflection at most 8 % of the mechanism's size and more than 0.4 x that (the rounding down
    loses at most 2.5x); the hinges' two nodes stay together when magnified (1e-9 m)."""
    from flexmbs.visual.animation import MAGNIFIED_FRACTION, default_magnification
    from flexmbs.visual.scene import scene
    prob, ev = _run("robot_2dof")
    sc = scene(prob, ev.result, frame_steps(ev.t.size, 50))
    f = default_magnification(sc)
    mant = f / 10 ** np.floor(np.log10(f))
    assert min(abs(mant - m) for m in (1, 2, 5)) < 1e-12
    ratio = f * sc.deviation.max() / sc.size()
    assert 0.4 * MAGNIFIED_FRACTION < ratio <= MAGNIFIED_FRACTION
    mech = prob.mechanism
    shown = sc.magnified(f)
    index = {n: i for i, n in enumerate(sc.nodes)}
    for j in prob.description.joints:
        if j.type == "hinge":
            a, b = (index[mech.node[(body, j.at)]] for body in j.bodies)
            assert np.max(np.abs(shown[:, a] - shown[:, b])) < 1e-9


def test_cli_refuses_unknown_suffix_before_the_run(tmp_path, monkeypatch, capsys):
    """--out m.avi: one error line naming the value and the allowed suffixes, no simulation,
    nothing written."""
    def forbidden(self, *a, **k):
        raise AssertionError("simulation started although --out was bad")
    monkeypatch.setattr(Problem, "evaluate", forbidden)
    out = tmp_path / "m.avi"
    assert main(["animate", "robot_2dof", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "m.avi" in err[0] and ".gif" in err[0] and ".mp4" in err[0] \
        and ".pvd" in err[0]
    assert not out.exists()


def test_cli_pvd_keeps_a_folder_of_other_files(tmp_path, monkeypatch, capsys):
    """--out m.pvd when m/ holds a file of the user's: refused before the run, the file kept."""
    def forbidden(self, *a, **k):
        raise AssertionError("simulation started although --out was bad")
    monkeypatch.setattr(Problem, "evaluate", forbidden)
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "notes.txt").write_text("mine")
    assert main(["animate", "robot_2dof", "--out", str(tmp_path / "m.pvd")]) == 2
    assert "notes.txt" in capsys.readouterr().err
    assert (tmp_path / "m" / "notes.txt").read_text() == "mine"
    assert not (tmp_path / "m.pvd").exists()


@pytest.mark.parametrize("name", ["..pvd", "...pvd"])
def test_a_pvd_without_a_name_is_refused(tmp_path, monkeypatch, name):
    """frame_folder of '..pvd' or '...pvd': the frames would go to '.' or '..' (the current or
    the parent folder, whose files would be replaced): a ModelError before anything is
    written, the folder's file kept. ('.pvd' alone has no suffix for Python: refused as not
    a .pvd file.)"""
    from flexmbs.errors import ModelError
    from flexmbs.visual.export import frame_folder
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine.txt").write_text("mine")
    with pytest.raises(ModelError, match="give the .pvd file a name"):
        frame_folder(name)
    with pytest.raises(ModelError, match="give the .pvd file a name"):
        frame_folder(tmp_path / name)
    with pytest.raises(ModelError):
        frame_folder(".pvd")
    assert (tmp_path / "mine.txt").read_text() == "mine"


def test_cli_animate_writes_a_gif_and_a_pvd(tmp_path, capsys):
    """flexmbs animate with --frames 4 --magnify 20: a GIF of 4 frames, a .pvd of 4 frames
    whose DataSets are the files in the folder beside it; written twice, the second .pvd
    replaces the first's frames (4 files, not 8)."""
    gif = tmp_path / "r.gif"
    assert main(["animate", "robot_2dof", "--out", str(gif), "--frames", "4", "--magnify",
                 "20", "--fps", "10"]) == 0
    assert Image.open(gif).n_frames == 4 and "deflection x 20" in capsys.readouterr().out
    pvd = tmp_path / "r.pvd"
    for _ in range(2):
        assert main(["animate", "robot_2dof", "--out", str(pvd), "--frames", "4"]) == 0
    files = [d.get("file") for d in ET.parse(pvd).getroot().iter("DataSet")]
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == sorted(f.split("/")[1]
                                                                         for f in files)
    assert len(files) == 4


def test_color_by_stress_without_a_depth_is_refused():
    """A beam of a 'given' section has no depth, so no stress: color_by='stress' is refused
    naming the option and the allowed values."""
    from flexmbs.errors import ModelError
    prob, ev = _run("robot_2dof")
    given = Problem("robot_2dof", overrides={
        f"bodies.{b.name}.section": {"shape": "given", "EA": 1e8, "EI": 1e3, "rhoA": 5.0, "rhoI": 1e-4}
        for b in prob.description.bodies if isinstance(b, Beam)})
    ev2 = given.evaluate(gradient=False, store="all")
    with pytest.raises(ModelError, match="color_by='stress'.*allowed: deviation, stress, none"):
        ev2.result.animate("never.gif", given, frames=2, color_by="stress")


def test_rigid_bodies_are_cells():
    """The press's crank (a rigid body with its centre at O and the point A) is one outline
    cell O-A: its written length is the crank radius |OA| of the case file (1e-9 m) at every
    frame."""
    from flexmbs.visual.scene import scene
    prob, ev = _run("slider_crank_press")
    d = prob.description
    sc = scene(prob, ev.result, frame_steps(ev.t.size, 5))
    rigid = [(name, idx) for name, kind, idx in sc.cells if kind == "rigid"]
    names = [b.name for b in d.bodies if isinstance(b, Rigid)]
    assert [n for n, _ in rigid] == names
    (_, idx), = rigid
    length = np.linalg.norm(np.subtract(d.points["A"], d.points["O"]))
    seg = sc.position[:, idx[0]] - sc.position[:, idx[-1]]
    assert np.allclose(np.hypot(seg[:, 0], seg[:, 1]), length, rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- overview figure
def _overview(case_or_problem):
    from flexmbs.visual.plots import plot_overview
    prob = case_or_problem if isinstance(case_or_problem, Problem) else _run(case_or_problem)[0]
    ev = prob.evaluate(gradient=False, store="all")
    return prob, plot_overview(prob, ev.result, ev)


def test_overview_time_labels_do_not_overlap():
    """The press's overview: the boxes of its time labels (and of the point names) overlap
    none another, all inside the motion panel; every posture has its label, or its time in
    the legend."""
    from flexmbs.visual.plots import _renderer
    _, fig = _overview("slider_crank_press")
    ax = fig.axes[0]
    r = _renderer(fig)
    fig.draw_without_rendering()
    boxes = [t.get_window_extent(r) for t in ax.texts]
    times = [t.get_text() for t in ax.texts if re.fullmatch(r"\d+\.\d\d s( \(max\))?",
                                                            t.get_text())]
    for i, a in enumerate(boxes):
        assert all(not a.overlaps(b) for b in boxes[i + 1:]), ax.texts[i].get_text()
    inside = ax.get_window_extent(r)
    assert all(inside.contains(b.x0, b.y0) and inside.contains(b.x1, b.y1) for b in boxes)
    also = [t.get_text() for t in ax.get_legend().get_texts()
            if t.get_text().startswith("postures also at ")]
    unplaced = also[0][len("postures also at "):].split(", ") if also else []
    assert len(times) + len(unplaced) >= 5 and len(times) >= 3


def test_overview_draws_rigid_bodies():
    """The press's crank is drawn: a line from O to A of the case file at t = 0 (a rest start:
    nothing deflected yet; 1e-9 m)."""
    prob, fig = _overview("slider_crank_press")
    o, a = (np.array(prob.description.points[p]) for p in ("O", "A"))
    ends = [np.array(line.get_xydata())[[0, -1]] for line in fig.axes[0].lines
            if len(line.get_xydata()) >= 2]
    assert any(np.allclose(e, [a, o], atol=1e-9) or np.allclose(e, [o, a], atol=1e-9)
               for e in ends)


def test_overview_without_constraints_has_no_empty_panel():
    """A case without constraints: the overview is the motion panel alone (one axes with
    lines), where it had an empty second panel."""
    import tomllib
    from flexmbs.model.casefile import case_path
    with open(case_path("robot_2dof"), "rb") as fh:
        data = tomllib.load(fh)
    data.pop("constraints")
    _, fig = _overview(Problem(data))
    assert len(fig.axes) == 1 and fig.axes[0].lines


def test_evaluation_of_another_design_is_refused(tmp_path):
    """Problem.animate(result, path, evaluation=ev) with ev of another design of the four-bar
    (every diameter 10 mm larger): a ModelError naming `evaluation` and both designs, and no
    film written (one design's motion is never drawn over another's histories). The same
    design evaluated again (a separate Evaluation) is accepted."""
    prob = Problem("fourbar", overrides={"time.t_end": 3 * 5e-4})
    drawn = prob.simulate(store="all")
    other = prob.evaluate(prob.start + 10.0, gradient=False)
    path = tmp_path / "m.gif"
    with pytest.raises(ModelError, match=r"evaluation is of design x = \[260, 260, 260\], the "
                                         r"motion drawn is of design \[250, 250, 250\]"):
        prob.animate(drawn, path, evaluation=other, frames=2)
    assert not path.exists()
    prob.animate(drawn, path, evaluation=prob.evaluate(gradient=False), frames=2)
    assert path.exists()
