"""The motion of a simulated mechanism as a ParaView time series: a .pvd collection of .vtu
files (one per time step), written with meshio.

`to_vtk(problem, result, "motion.pvd")` writes ``motion.pvd`` and a folder ``motion/`` beside it
holding ``frame_00000.vtu``, ``frame_00001.vtu``, ... (the .pvd names them relative to itself,
with their times). Each .vtu holds every body of the mechanism (flexmbs.visual.scene):

- points: every node, at its flexible position (z = 0);
- cells: the beam elements (VTK quadratic edges, 'line3', for 3-node elements: end nodes first,
  then the middle one; 'line' for 2-node ones), the rigid bodies' outlines (segments, 'line'),
  the point masses ('vertex');
- point data: displacement (from t = 0), deflection (flexible minus rigid-reference position),
  deviation (its length), rotation, rotation_deflection (flexmbs.visual.scene.POINT_FIELDS; vectors
  with z = 0);
- cell data: axial_strain, shear_strain, curvature, stress (beam elements; NaN on the other
  cells, flexmbs.visual.scene.CELL_FIELDS), kind (0 beam element, 1 rigid body, 2 point mass) and
  body (the body's position among the case's bodies, from 0).

In ParaView, "Warp By Vector" with the vector `deflection` and scale factor s - 1 draws the
rigid reference plus s times the deflection (the magnified motion of flexmbs.visual.animation).

The frames go to a temporary folder first; an existing ``motion/`` is replaced only if it holds
nothing but frame files, and the .pvd is written last, through a temporary file.
"""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from flexmbs.errors import ModelError
from flexmbs.files import atomic_open
from flexmbs.visual.scene import CELL_FIELDS, frame_steps, scene

__all__ = ["to_vtk", "frame_folder", "read_pvd", "KINDS"]

#: cell data 'kind': the code of each kind of cell
KINDS = {"beam": 0, "rigid": 1, "mass": 2}
_FRAME = re.compile(r"frame_\d{5,}\.vtu")


def frame_folder(path):
    """The folder of a .pvd's frames: its name without the suffix, beside it. ModelError when
    `path` does not end with .pvd, or when that folder is a symbolic link, or exists and holds
    anything but frames."""
    path = Path(path)
    if path.suffix.lower() != ".pvd":
        raise ModelError(f"{os.fspath(path)!r}: a ParaView time series is a .pvd file")
    folder = path.with_suffix("")
    if folder.name in ("", ".", ".."):
        raise ModelError(f"{os.fspath(path)!r}: give the .pvd file a name (its frames go to a "
                         "folder of that name beside it)")
    if folder.is_symlink():     # replaced by a folder of frames: the link, not its target
        raise ModelError(f"{os.fspath(path)!r}: its frames go to {os.fspath(folder)!r}, "
                         f"which is a symbolic link (to {os.readlink(folder)!r}); the frames "
                         "are written to a real folder: remove the link or give another name")
    if folder.exists():
        if not folder.is_dir():
            raise ModelError(f"{os.fspath(path)!r}: its frames go to {os.fspath(folder)!r}, "
                             "which is a file; remove it or give another name")
        other = [p.name for p in folder.iterdir() if not _FRAME.fullmatch(p.name)]
        if other:
            raise ModelError(f"{os.fspath(path)!r}: its frames go to {os.fspath(folder)!r}, "
                             f"which holds other files ({', '.join(sorted(other)[:3])}); "
                             "give another name")
    return folder


def _blocks(sc):
    """meshio cell blocks [(type, connectivity)] and, per block, the indices of its cells in
    sc.cells (a rigid outline gives several segments, all of its cell)."""
    groups = {}
    for c, (_, kind, idx) in enumerate(sc.cells):
        if kind == "beam":
            key = "line3" if len(idx) == 3 else "line"
            conn = [idx[0], idx[2], idx[1]] if len(idx) == 3 else list(idx)
            groups.setdefault((kind, key), ([], []))
            groups[(kind, key)][0].append(conn)
            groups[(kind, key)][1].append(c)
        elif kind == "rigid":
            g = groups.setdefault((kind, "line"), ([], []))
            for a, b in zip(idx[:-1], idx[1:]):
                g[0].append([a, b])
                g[1].append(c)
        else:
            g = groups.setdefault((kind, "vertex"), ([], []))
            g[0].append([idx[0]])
            g[1].append(c)
    return [(key, np.array(conn, int), np.array(owner, int))
            for (_, key), (conn, owner) in groups.items()]


def to_vtk(problem, result, path, *, frames=None):
    """Write the motion of a simulated design as a ParaView time series (module docstring).

    Parameters
    ----------
    problem : flexmbs.problem.Problem
    result : flexmbs.analysis.simulate.Result of the problem, simulated with store='all'
    path : a .pvd file name (its frames go to the folder of its name without the suffix)
    frames : int >= 2, optional: that many time steps spread evenly over the run (first and
        last included); default every time step

    Returns
    -------
    (path of the .pvd, list of the .vtu paths, (k,) the 0-based steps written)
    """
    import meshio

    path = Path(path)
    folder = frame_folder(path)
    if frames is not None and (not isinstance(frames, (int, np.integer)) or frames < 2):
        raise ModelError(f"frames must be an integer >= 2 or None (every step), got {frames!r}")
    steps = frame_steps(result.t.size, frames)
    sc = scene(problem, result, steps)
    blocks = _blocks(sc)
    order = {b.name: i for i, b in enumerate(problem.description.bodies)}
    body = np.array([order[name] for name, _, _ in sc.cells], float)
    kind = np.array([KINDS[k] for _, k, _ in sc.cells], float)
    cells = [(key, conn) for key, conn, _ in blocks]
    pfields = sc.point_fields()
    width = max(5, len(str(steps.size - 1)))
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}.", suffix=".tmp"))
    names = []
    try:
        for j in range(steps.size):
            points = np.column_stack([sc.position[j], np.zeros(sc.nodes.size)])
            pdata = {}
            for name, v in pfields.items():
                v = v[j]
                pdata[name] = np.column_stack([v, np.zeros(v.shape[0])]) if v.ndim == 2 else v
            cdata = {name: [sc.cell_fields[name][j][owner] for _, _, owner in blocks]
                     for name in CELL_FIELDS}
            cdata["kind"] = [kind[owner] for _, _, owner in blocks]
            cdata["body"] = [body[owner] for _, _, owner in blocks]
            name = f"frame_{j:0{width}d}.vtu"
            meshio.write(tmp / name, meshio.Mesh(points, cells, point_data=pdata,
                                                 cell_data=cdata), file_format="vtu")
            names.append(name)
        if folder.exists():
            shutil.rmtree(folder)       # frame files only (frame_folder checked)
        os.replace(tmp, folder)
    except BaseException:
        with contextlib.suppress(OSError):
            shutil.rmtree(tmp)
        raise
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for t, name in zip(sc.t, names):
        ET.SubElement(coll, "DataSet", timestep=repr(float(t)), group="", part="0",
                      file=f"{folder.name}/{name}")
    ET.indent(root)
    with atomic_open(path, "wb") as fh:
        ET.ElementTree(root).write(fh, xml_declaration=True, encoding="utf-8")
    return os.fspath(path), [os.fspath(folder / n) for n in names], steps


def read_pvd(path):
    """[(time, .vtu path)] of a .pvd collection, in its order."""
    root = ET.parse(path).getroot()
    base = Path(path).parent
    return [(float(d.get("timestep")), os.fspath(base / d.get("file")))
            for d in root.iter("DataSet")]
