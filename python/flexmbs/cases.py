"""The paper's mechanisms as cases: TOML case files, models, rigid references, deviations, mass.

A case file (``cases/*.toml``, human-readable, commented) holds a mechanism's parameters, its
material and section type, the design variables (names, unit mm, bounds, start), the time
settings, the deviation formulation and its limit, and the paper's optimizer settings.
`load_case` reads and validates one; the `Case` it returns builds the model for a design,
simulates it, and evaluates the beam mass and the deviation history against the rigid
reference mechanism, with the derivatives the optimizers need.

Mechanisms (``[case] mechanism``):

``robot_2dof``
    The paper's section 6 (Fig. 4): two arms O-A and A-tip, motors at O and A, the tip
    deployed along the straight line of eq. (26). Design variables p1, p2 (arm 1, root element
    first), p3, p4 (arm 2): outer diameters of the elements of a thin-walled tube. Rigid
    reference: analytic inverse kinematics (`flexmbs.laws.planar_2r_inverse`).
``fourbar``
    The paper's section 7 (Fig. 7): crank O-A driven at O, coupler A-B, follower C-B pinned at
    C. Design variables p1, p2, p3: diameters of the crank, coupler and follower. Rigid
    reference: the loop-closure equations solved in closed form, with rates and accelerations.

Deviation formulations (``[deviation] formulation``): "28" (= the paper's 37) and "30" for the
robot, "33" for the four-bar; subscript r is the rigid reference::

    (28)  sqrt((yA - yA_r)^2 + ((y_tip - y_tip_r) - (yA - yA_r))^2)
    (30)  sqrt((x_tip - x_tip_r)^2 + (y_tip - y_tip_r)^2)
    (33)  sqrt((xA - xA_r)^2 + (yA - yA_r)^2)

Example
-------
>>> from flexmbs.cases import load_case
>>> case = load_case("robot_2dof")                  # cases/robot_2dof.toml
>>> r = case.simulate([39.29, 28.33, 34.94, 25.19])  # Table 1, weakly coupled optimum
>>> round(r.mass, 3), round(r.max_deviation * 1e3, 2)
(0.962, 1.0)
>>> table5 = load_case("robot_2dof", t_end=0.66)    # any key can be overridden
"""
from __future__ import annotations

import copy
import math
import numbers
import os
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from flexmbs.errors import CaseError, ModelError
from flexmbs.laws import TimeLaw, planar_2r_inverse, robot_joint_laws, robot_tip_path
from flexmbs.model import Model
from flexmbs.sections import Circle, Material, Tube
from flexmbs.simulate import Result, time_grid
from flexmbs.simulate import simulate as _simulate

__all__ = ["load_case", "as_case", "Case", "CaseResult", "available_cases", "case_path",
           "fourbar_positions"]

#: Folder of the case files installed with the package (flexmbs/cases_data).
_PACKAGE_DATA = "cases_data"


# ----------------------------------------------------------------------------- schema
@dataclass(frozen=True)
class _Key:
    """One key of a case file: its type and constraints."""
    kind: str                 # 'float' | 'int' | 'str' | 'floats' | 'strs'
    required: bool = True
    choices: tuple = ()
    positive: bool = False    # > 0 (numbers, and every element of a list)
    nonnegative: bool = False
    length: int | None = None
    maximum: float | None = None   # inclusive upper bound (numbers)


_F, _FP, _F0 = _Key("float"), _Key("float", positive=True), _Key("float", nonnegative=True)

#: Largest number of beam elements per arm or link a case file may ask for: a guard against a
#: typo building a model of millions of nodes in Python before simulate() can estimate the
#: run's memory (2 quadratic elements are converged already; 20 000 per arm, 240 012 unknowns,
#: take a few seconds to build and are then refused or run by the memory estimate).
_MAX_ELEMENTS = 20_000

_COMMON = {
    "case": {
        "name": _Key("str"),
        "mechanism": _Key("str", choices=("robot_2dof", "fourbar")),
        "description": _Key("str", required=False),
        "paper": _Key("str", required=False),
    },
    "material": {"E_Pa": _FP, "nu": _F, "rho_kg_m3": _FP},
    "section": {
        "type": _Key("str", choices=("tube", "circle")),
        "wall_ratio": _Key("float", required=False, positive=True),
    },
    "design": {
        "names": _Key("strs"),
        "meaning": _Key("strs", required=False),
        "unit": _Key("str", choices=("mm",)),
        "lower": _Key("floats", positive=True),
        "upper": _Key("floats", positive=True),
        "start": _Key("floats", positive=True),
    },
    "time": {
        "h": _FP,
        "rho_inf": _Key("float", nonnegative=True),
        "t_end": _FP,
        "start_mode": _Key("str", choices=("static", "rest")),
    },
    "deviation": {
        "formulation": _Key("str", choices=("28", "30", "33")),
        "limit_m": _FP,
    },
    "optimizer.fully": {
        "objective_rel_change": _FP,
        "constraint_violation": _FP,
        "design_rel_change": _Key("float", required=False, positive=True),
        "max_iterations": _Key("int", required=False, positive=True),
    },
    "optimizer.weakly": {
        "esl_rel_change": _FP,
        "max_cycles": _Key("int", required=False, positive=True),
    },
}

_MECHANISM = {
    "robot_2dof": {
        "arm_lengths_m": _Key("floats", positive=True, length=2),
        "theta1_0_deg": _F,
        "theta2_0_deg": _F,
        "path_period_s": _FP,
        "path_stroke_m": _F,
        "drive": _Key("str", choices=("absolute", "relative")),
        "elements_per_arm": _Key("int", positive=True, maximum=_MAX_ELEMENTS),
        "element_order": _Key("int", choices=(1, 2)),
        "mass_A_kg": _F0,
        "mass_tip_kg": _F0,
        "gravity_m_s2": _Key("floats", length=2),
    },
    "fourbar": {
        "link_lengths_m": _Key("floats", positive=True, length=3),
        "ground_length_m": _FP,
        "branch": _Key("str", choices=("upper", "lower")),
        "theta0_deg": _F,
        "ramp_time_s": _FP,
        "crank_speed_rpm": _F,
        "elements_per_link": _Key("int", positive=True, maximum=_MAX_ELEMENTS),
        "element_order": _Key("int", choices=(1, 2)),
        "mass_A_kg": _F0,
        "mass_B_kg": _F0,
        "gravity_m_s2": _Key("floats", length=2),
    },
}

_FORMULATIONS = {"robot_2dof": ("28", "30"), "fourbar": ("33",)}
_NVAR = {"robot_2dof": 4, "fourbar": 3}


def _schema(mechanism):
    s = dict(_COMMON)
    s["mechanism"] = _MECHANISM[mechanism]
    return s


def _table(data, path):
    """The sub-table at a dotted path, or None."""
    node = data
    for part in path.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def _check_value(where, key, spec, value):
    """Validate one value; return it normalised (floats as float, formulation as str)."""
    def bad(msg):
        return CaseError(f"{where}: key '{key}' {msg}")

    def number(v, integer=False):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise bad(f"must be {'an integer' if integer else 'a number'}, got {v!r}")
        if integer and not isinstance(v, int):
            raise bad(f"must be an integer, got {v!r}")
        if not math.isfinite(v):
            raise bad(f"must be finite, got {v!r}")
        if spec.positive and v <= 0:
            raise bad(f"must be positive, got {v!r}")
        if spec.nonnegative and v < 0:
            raise bad(f"must be >= 0, got {v!r}")
        if spec.maximum is not None and v > spec.maximum:
            raise bad(f"must be at most {spec.maximum:g}, got {v!r}")
        return int(v) if integer else float(v)

    if spec.kind == "float":
        out = number(value)
    elif spec.kind == "int":
        out = number(value, integer=True)
    elif spec.kind == "str":
        # a deviation formulation may be written as a number (28) or a string ("28")
        if key.rsplit(".", 1)[-1] == "formulation" and isinstance(value, int) \
                and not isinstance(value, bool):
            value = str(value)
        if not isinstance(value, str):
            raise bad(f"must be a string, got {value!r}")
        out = value
    elif spec.kind in ("floats", "strs"):
        if not isinstance(value, (list, tuple)):
            raise bad(f"must be a list, got {value!r}")
        if spec.kind == "strs":
            if not all(isinstance(v, str) for v in value):
                raise bad(f"must be a list of strings, got {value!r}")
            out = list(value)
        else:
            out = [number(v) for v in value]
        if spec.length is not None and len(out) != spec.length:
            raise bad(f"must have {spec.length} entries, got {len(out)}")
    else:  # pragma: no cover - schema error
        raise AssertionError(spec.kind)
    if spec.choices and out not in spec.choices:
        raise bad(f"must be one of {', '.join(repr(c) for c in spec.choices)}, got {out!r}")
    return out


def _validate(data, source):
    """Check a case dictionary against the schema; return a normalised deep copy."""
    where = str(source)
    if not isinstance(data, dict):
        raise CaseError(f"{where}: a case must be a table of tables")
    mech = _table(data, "case.mechanism")
    if not isinstance(data.get("case"), dict):
        raise CaseError(f"{where}: missing table [case] (with name and mechanism), got "
                        f"case = {data.get('case')!r}")
    if mech is None:
        raise CaseError(f"{where}: missing key 'case.mechanism' (one of {', '.join(_MECHANISM)})")
    if not isinstance(mech, str) or mech not in _MECHANISM:
        raise CaseError(f"{where}: key 'case.mechanism' must be one of "
                        f"{', '.join(repr(m) for m in _MECHANISM)}, got {mech!r}")
    schema = _schema(mech)
    # unknown tables and keys
    tables = {p.split(".")[0] for p in schema}
    for top, val in data.items():
        if top not in tables:
            raise CaseError(f"{where}: unknown table [{top}] (expected {', '.join(sorted(tables))})")
        if not isinstance(val, dict):
            raise CaseError(f"{where}: [{top}] must be a table of keys, got {top} = {val!r}")
    if "optimizer" in data:
        for sub, val in data["optimizer"].items():
            if f"optimizer.{sub}" not in schema:
                raise CaseError(f"{where}: unknown table [optimizer.{sub}] "
                                "(expected [optimizer.fully] and [optimizer.weakly])")
            if not isinstance(val, dict):
                raise CaseError(f"{where}: [optimizer.{sub}] must be a table of keys, got "
                                f"optimizer.{sub} = {val!r}")
    out = {}
    for path, keys in schema.items():
        tab = _table(data, path)
        if tab is None:
            raise CaseError(f"{where}: missing table [{path}]")
        for key in tab:
            if key not in keys:
                raise CaseError(f"{where}: unknown key '{path}.{key}' (known keys of [{path}]: "
                                f"{', '.join(keys)})")
        norm = {}
        for key, spec in keys.items():
            if key not in tab:
                if spec.required:
                    raise CaseError(f"{where}: missing key '{path}.{key}'")
                continue
            norm[key] = _check_value(where, f"{path}.{key}", spec, tab[key])
        node = out
        parts = path.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = norm
    _check_consistency(out, where)
    return out


def _check_consistency(d, where):
    """Checks that involve several keys."""
    mech = d["case"]["mechanism"]
    des = d["design"]
    nv = _NVAR[mech]
    for key in ("names", "lower", "upper", "start"):
        if len(des[key]) != nv:
            raise CaseError(f"{where}: key 'design.{key}' must have {nv} entries for a {mech}, "
                            f"got {len(des[key])}")
    if "meaning" in des and len(des["meaning"]) != nv:
        raise CaseError(f"{where}: key 'design.meaning' must have {nv} entries, got {len(des['meaning'])}")
    if len(set(des["names"])) != nv:
        raise CaseError(f"{where}: key 'design.names' has duplicates: {des['names']}")
    lo, up, st = (np.array(des[k]) for k in ("lower", "upper", "start"))
    if np.any(lo >= up):
        raise CaseError(f"{where}: key 'design.lower' must be below 'design.upper' for every "
                        f"variable, got lower = {des['lower']}, upper = {des['upper']}")
    if np.any(st < lo) or np.any(st > up):
        raise CaseError(f"{where}: key 'design.start' must lie within the bounds [design.lower, "
                        f"design.upper] = [{des['lower']}, {des['upper']}], got {des['start']}")
    sec = d["section"]
    if sec["type"] == "tube":
        if "wall_ratio" not in sec:
            raise CaseError(f"{where}: missing key 'section.wall_ratio' (needed by type = 'tube')")
        if not 0 < sec["wall_ratio"] <= 0.5:
            raise CaseError(f"{where}: key 'section.wall_ratio' must lie in (0, 0.5], "
                            f"got {sec['wall_ratio']}")
    elif "wall_ratio" in sec:
        raise CaseError(f"{where}: key 'section.wall_ratio' only applies to type = 'tube'")
    if not 0.0 <= d["time"]["rho_inf"] <= 1.0:
        raise CaseError(f"{where}: key 'time.rho_inf' must lie in [0, 1], got {d['time']['rho_inf']}")
    t_end, h = d["time"]["t_end"], d["time"]["h"]
    ratio = t_end / h            # checked without building the grid (it may be huge)
    nsteps = round(ratio) if math.isfinite(ratio) else 0
    if nsteps < 1 or abs(nsteps * h - t_end) > 1e-9 * max(1.0, t_end):
        raise CaseError(f"{where}: keys 'time.t_end' and 'time.h': t_end = {t_end} s must be a "
                        f"whole number (>= 1) of steps h = {h} s")
    form = d["deviation"]["formulation"]
    if form not in _FORMULATIONS[mech]:
        raise CaseError(f"{where}: key 'deviation.formulation' must be one of "
                        f"{', '.join(repr(f) for f in _FORMULATIONS[mech])} for a {mech}, got {form!r}")
    mec = d["mechanism"]
    if not -1.0 < d["material"]["nu"] < 0.5:
        raise CaseError(f"{where}: key 'material.nu' must lie in (-1, 0.5), got {d['material']['nu']}")
    if mech == "robot_2dof":
        if mec["elements_per_arm"] % 2:
            raise CaseError(f"{where}: key 'mechanism.elements_per_arm' must be even (each half arm "
                            f"carries one design variable), got {mec['elements_per_arm']}")
        l1, l2 = mec["arm_lengths_m"]
        t1, t2 = math.radians(mec["theta1_0_deg"]), math.radians(mec["theta2_0_deg"])
        if abs(math.sin(t2)) < 1e-6:
            raise CaseError(f"{where}: key 'mechanism.theta2_0_deg' puts the robot in a singular "
                            "posture (arms aligned)")
        x0 = l1 * math.cos(t1) + l2 * math.cos(t1 + t2)
        y0 = l1 * math.sin(t1) + l2 * math.sin(t1 + t2)
        xe, ye, *_ = robot_tip_path(np.array([d["time"]["t_end"]]), x0, y0,
                                    mec["path_period_s"], mec["path_stroke_m"])
        if math.hypot(xe[0], ye[0]) >= l1 + l2:
            raise CaseError(f"{where}: key 'time.t_end' = {d['time']['t_end']} s takes the tip "
                            "out of the robot's reach")
    else:
        l1, l2, l3 = mec["link_lengths_m"]
        l4 = mec["ground_length_m"]
        # the coupler and follower must close the loop at every crank angle
        if not (abs(l2 - l3) < l4 - l1 and l4 + l1 < l2 + l3):
            raise CaseError(f"{where}: keys 'mechanism.link_lengths_m' and 'mechanism.ground_length_m' "
                            "do not make a crank-rocker that closes at every crank angle")


def _set_override(data, key, value, where):
    """Set one override (a leaf key name or a dotted path) in the raw case dictionary."""
    mech = _table(data, "case.mechanism")
    schema = _schema(mech if isinstance(mech, str) and mech in _MECHANISM else "robot_2dof")
    if not isinstance(key, str) or not key:
        raise CaseError(f"{where}: override keys must be non-empty strings, got {key!r}")
    leaves = sorted({k for keys in schema.values() for k in keys})
    if "." in key:
        path, leaf = key.rsplit(".", 1)
        if path not in schema:
            raise CaseError(f"{where}: unknown override key '{key}': no table [{path}] (tables: "
                            f"{', '.join(schema)})")
        if leaf not in schema[path]:
            raise CaseError(f"{where}: unknown override key '{key}' (keys of [{path}]: "
                            f"{', '.join(schema[path])})")
    else:
        hits = [p for p, keys in schema.items() if key in keys]
        if not hits:
            raise CaseError(f"{where}: unknown override key '{key}'; allowed keys: "
                            f"{', '.join(leaves)} (or a dotted path such as "
                            "'mechanism.mass_tip_kg')")
        if len(hits) > 1:
            raise CaseError(f"{where}: override key '{key}' is ambiguous: use one of "
                            f"{', '.join(p + '.' + key for p in hits)}")
        path, leaf = hits[0], key
    node = data
    for p in path.split("."):
        node = node.setdefault(p, {})
        if not isinstance(node, dict):
            raise CaseError(f"{where}: [{path}] must be a table, got {node!r}")
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    node[leaf] = value


# ----------------------------------------------------------------------------- finding case files
def _repository_cases():
    """The repository's cases/ folder when flexmbs runs from a source tree, else None."""
    root = Path(__file__).resolve().parents[2]
    folder = root / "cases"
    if folder.is_dir() and (root / "python" / "flexmbs").is_dir():
        return folder
    return None


def _installed_cases():
    """The case files installed with the package (importlib.resources), as a Traversable."""
    try:
        folder = resources.files("flexmbs") / _PACKAGE_DATA
        return folder if folder.is_dir() else None
    except (ModuleNotFoundError, FileNotFoundError, NotADirectoryError):
        return None


def case_folders():
    """The folders that hold shipped case files: the repository's cases/ (source tree) and
    the copy installed with the package (flexmbs/cases_data)."""
    return [f for f in (_repository_cases(), _installed_cases()) if f is not None]


def available_cases():
    """Names of the case files shipped with flexmbs (repository cases/ or installed copy)."""
    names = set()
    for folder in (_repository_cases(), _installed_cases()):
        if folder is None:
            continue
        names.update(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))
    return sorted(names)


def case_path(name):
    """Locate a case: an existing file path, or a name (with or without .toml) in the
    repository's cases/ folder, or in the copy installed with the package (flexmbs/cases_data).

    Returns a pathlib.Path or an importlib.resources Traversable; raises CaseError if not found.
    """
    p = Path(name)
    if p.is_file():
        return p
    stem = p.name[:-5] if p.name.endswith(".toml") else p.name
    if p.suffix == ".toml" and len(p.parts) > 1:
        raise CaseError(f"case file {str(name)!r} not found")
    for folder in (_repository_cases(), _installed_cases()):
        if folder is not None:
            f = folder / f"{stem}.toml"
            if f.is_file():
                return f
    known = ", ".join(available_cases()) or "none found"
    raise CaseError(f"case {str(name)!r} not found: give a path to a .toml file or one of: {known}")


def load_case(case, /, **overrides):
    """Read, validate and return a case.

    Parameters
    ----------
    case : str or path-like or dict
        A path to a TOML case file, the name of a shipped case ("robot_2dof",
        "robot_2dof_tracking", "fourbar", "fourbar_no_masses"), or an already parsed dictionary.
    **overrides
        Case-file keys to replace, by leaf name (``t_end=0.66``, ``drive="relative"``,
        ``theta0_deg=0.0``) or by dotted path (``**{"mechanism.mass_tip_kg": 0.5}``).

    Returns
    -------
    Case

    Raises
    ------
    CaseError
        If the file is missing or malformed (the message names the file and the key).
    """
    if isinstance(case, dict):
        data, source = copy.deepcopy(case), "<dict>"
    elif not isinstance(case, (str, os.PathLike)):
        raise CaseError(f"load_case: case must be a case name (one of "
                        f"{', '.join(available_cases())}), a path to a .toml file or a dict, "
                        f"got {case!r} ({type(case).__name__})")
    else:
        f = case_path(case)
        source = str(f)
        try:
            data = tomllib.loads(f.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as exc:
            raise CaseError(f"{source}: not valid TOML: {exc}") from None
        except UnicodeDecodeError as exc:
            raise CaseError(f"{source}: not a UTF-8 text file: {exc}") from None
        except OSError as exc:
            raise CaseError(f"{source}: cannot be read: {exc}") from None
    return Case(data, source, overrides)


def _float_array(value):
    """np.asarray(value, float), or None if it is not an array of numbers."""
    if isinstance(value, (str, bytes, dict)):
        return None
    try:
        return np.asarray(value, float)
    except (TypeError, ValueError):
        return None


def as_case(case, what="case"):
    """A Case from a Case, a case name, a path to a case file or a case dictionary.

    The optimizers' entry points take any of them (``optimize_fully("robot_2dof")``).
    """
    if isinstance(case, Case):
        return case
    if isinstance(case, (str, os.PathLike, dict)):
        return load_case(case)
    raise CaseError(f"{what} must be a Case (see load_case), a case name (one of "
                    f"{', '.join(available_cases())}), a path to a .toml file or a dict, "
                    f"got {case!r} ({type(case).__name__})")


# ----------------------------------------------------------------------------- four-bar kinematics
def fourbar_positions(theta, lengths, ground, branch="upper", rate=None, accel=None):
    """Rigid four-bar kinematics from the loop-closure equations, in closed form (vectorized).

    O = (0, 0), A = l1 (cos theta, sin theta), C = (ground, 0); B is the intersection of the
    circles of radius l2 about A and l3 about C, to the left of the directed line A -> C for
    branch="upper" (to the right for "lower").

    Parameters
    ----------
    theta : array
        Crank angles (rad).
    lengths : (l1, l2, l3)
        Crank, coupler and follower lengths (m).
    ground : float
        Ground length l4 (m).
    branch : {'upper', 'lower'}, default 'upper'
    rate, accel : arrays, optional
        Crank angular velocity and acceleration; when given, the rates and accelerations of the
        coupler and follower angles are returned too, from the differentiated loop closure
        l1 e(theta) + l2 e(phi2) - l3 e(phi3) = (l4, 0).

    Returns
    -------
    dict with A, B (n, 2) positions, phi_coupler (angle of A -> B) and phi_follower (angle of
    C -> B), and if rate is given phi_coupler_rate, phi_follower_rate, and with accel also
    phi_coupler_accel, phi_follower_accel.
    """
    l1, l2, l3 = (float(v) for v in lengths)
    th = np.asarray(theta, float)
    A = np.stack([l1 * np.cos(th), l1 * np.sin(th)], axis=-1)
    AC = np.array([float(ground), 0.0]) - A
    d = np.hypot(AC[..., 0], AC[..., 1])
    a = (l2 * l2 - l3 * l3 + d * d) / (2 * d)
    h2 = l2 * l2 - a * a
    if np.any(h2 <= 0):
        raise ModelError("four-bar: the loop does not close at some crank angle")
    hh = np.sqrt(h2) * (1.0 if branch == "upper" else -1.0)
    u = AC / d[..., None]
    n = np.stack([-u[..., 1], u[..., 0]], axis=-1)
    B = A + a[..., None] * u + hh[..., None] * n
    out = dict(A=A, B=B, phi_coupler=np.arctan2(B[..., 1] - A[..., 1], B[..., 0] - A[..., 0]),
               phi_follower=np.arctan2(B[..., 1], B[..., 0] - float(ground)))
    if rate is None:
        return out
    p2, p3 = out["phi_coupler"], out["phi_follower"]

    def e(p):
        return np.stack([np.cos(p), np.sin(p)], axis=-1)

    def eperp(p):
        return np.stack([-np.sin(p), np.cos(p)], axis=-1)

    # [l2 e_perp(phi2), -l3 e_perp(phi3)] [phi2', phi3'] = rhs
    m11, m21 = l2 * eperp(p2)[..., 0], l2 * eperp(p2)[..., 1]
    m12, m22 = -l3 * eperp(p3)[..., 0], -l3 * eperp(p3)[..., 1]
    det = m11 * m22 - m12 * m21

    def solve(rhs):
        return ((m22 * rhs[..., 0] - m12 * rhs[..., 1]) / det,
                (-m21 * rhs[..., 0] + m11 * rhs[..., 1]) / det)

    w = np.asarray(rate, float)
    w2, w3 = solve(-l1 * w[..., None] * eperp(th))
    out["phi_coupler_rate"], out["phi_follower_rate"] = w2, w3
    if accel is not None:
        al = np.asarray(accel, float)
        rhs = (-l1 * (al[..., None] * eperp(th) - (w * w)[..., None] * e(th))
               + l2 * (w2 * w2)[..., None] * e(p2) - l3 * (w3 * w3)[..., None] * e(p3))
        out["phi_coupler_accel"], out["phi_follower_accel"] = solve(rhs)
    return out


def _crank_law(theta0, ramp, speed):
    """theta(t) = theta0 + speed t^2 / (2 ramp) for t <= ramp, then linear at `speed`."""
    k = speed / (2.0 * ramp)

    def value(t):
        t = np.asarray(t, float)
        return theta0 + np.where(t <= ramp, k * t * t, 0.5 * speed * ramp + speed * (t - ramp))

    def rate(t):
        t = np.asarray(t, float)
        return np.where(t <= ramp, 2 * k * t, speed)

    def accel(t):
        t = np.asarray(t, float)
        return np.where(t <= ramp, 2 * k, 0.0)

    return TimeLaw(value, rate, accel, name="crank angle")


# ----------------------------------------------------------------------------- results
@dataclass
class CaseResult:
    """A case simulated at one design.

    Attributes
    ----------
    case_name : str
    formulation : str
        The deviation formulation ("28", "30" or "33").
    design_mm : (nv,) design (mm).
    mass : float
        Beam mass (kg), lumped masses excluded.
    t : (nt,) time grid (s).
    deviation : (nt,) deviation history (m).
    max_deviation : float
        Its maximum (m).
    t_at_max : float
        Time of the maximum (s).
    step_at_max : int
        Time step of the maximum, counted as in the paper (1-based: t_n = (n - 1) h).
    limit_m : float
        The deviation limit (m).
    reference : dict
        Rigid reference histories on `t` (see Case.rigid_reference).
    result : flexmbs.Result
        The simulation (coordinates, statistics, wall time).
    """
    case_name: str
    formulation: str
    design_mm: np.ndarray
    mass: float
    t: np.ndarray
    deviation: np.ndarray
    max_deviation: float
    t_at_max: float
    step_at_max: int
    limit_m: float
    reference: dict = field(repr=False)
    result: Result = field(repr=False)
    case: "Case" = field(repr=False, default=None)

    @property
    def feasible(self):
        """True when the deviation stays within its limit at every step."""
        return bool(self.max_deviation <= self.limit_m)

    def summary(self):
        """A JSON-ready dictionary of the main numbers."""
        st = self.result.stats
        return dict(case=self.case_name, formulation=self.formulation,
                    design_mm=[float(v) for v in self.design_mm], mass_kg=float(self.mass),
                    max_deviation_m=float(self.max_deviation), t_at_max_s=float(self.t_at_max),
                    step_at_max=int(self.step_at_max), limit_m=float(self.limit_m),
                    feasible=self.feasible, t_end_s=float(self.t[-1]),
                    h_s=float(self.result.settings.get("h", self.t[1] - self.t[0])),
                    rho_inf=float(self.result.settings.get("rho_inf", float("nan"))),
                    steps=int(st["steps"]), newton_iterations=int(st["newton_iterations"]),
                    factorizations=int(st["factorizations"]),
                    wall_time_s=float(self.result.wall_time))


# ----------------------------------------------------------------------------- the case
class Case:
    """One of the paper's mechanisms, with its design variables and deviation measure.

    Build it with `load_case`. The model's structure (nodes, elements, joints, motors) is built
    once per case; `build_model(design)` only sets the element sections of a design. The rigid
    reference is computed once per time grid.

    Attributes
    ----------
    name, mechanism : str
    formulation : str
        "28", "30" or "33".
    design_names : list of str
    lower_mm, upper_mm, start_mm : (nv,) arrays, mm
    h, rho_inf, t_end : float
    start_mode : {'static', 'rest'}
    limit_m : float
    optimizer : dict
        {'fully': {...}, 'weakly': {...}}: the paper's stopping criteria from the file.
    parameters : dict
        The [mechanism] table.
    material : flexmbs.Material
    config : dict
        The validated case dictionary (overrides applied), e.g. to record with results.
    source : str
        The file the case came from.
    beams : list of str
        The flexible bodies: ['arm1', 'arm2'] or ['crank', 'coupler', 'follower'].
    points : dict
        Named nodes: robot O, A (arm 1's end), tip; four-bar O, A (crank's end), B (coupler's
        end), C.
    esl_bodies : list of (body name, node)
        The bodies of the weakly coupled method and the node of each one's tangent
        corotational frame: robot arm1 at O, arm2 at A; four-bar crank at O, coupler at B,
        follower at C.
    sensor_dofs : (nsens,) int array
        The coordinates (0-based) the deviation needs, in the column order of
        `deviation_from_sensors` (same for every design): (28) y_A, y_tip; (30) x_tip, y_tip;
        (33) x_A, y_A.
    element_design_map : (nel,) int array
        The design variable (0-based) of every element, in the model's element order.
    """

    def __init__(self, data, source="<dict>", overrides=None):
        raw = copy.deepcopy(data)
        for key, value in (overrides or {}).items():
            _set_override(raw, key, value, source)
        self._raw = raw
        self.source = str(source)
        cfg = _validate(raw, self.source)
        self.config = cfg
        self.name = cfg["case"]["name"]
        self.mechanism = cfg["case"]["mechanism"]
        self.description = cfg["case"].get("description", "")
        self.parameters = dict(cfg["mechanism"])
        self.formulation = cfg["deviation"]["formulation"]
        self.limit_m = cfg["deviation"]["limit_m"]
        des = cfg["design"]
        self.design_names = list(des["names"])
        self.design_meaning = list(des.get("meaning", des["names"]))
        self.lower_mm = np.array(des["lower"])
        self.upper_mm = np.array(des["upper"])
        self.start_mm = np.array(des["start"])
        tm = cfg["time"]
        self.h, self.rho_inf, self.t_end = tm["h"], tm["rho_inf"], tm["t_end"]
        self.start_mode = tm["start_mode"]
        self.optimizer = copy.deepcopy(cfg["optimizer"])
        m = cfg["material"]
        self.material = Material(E=m["E_Pa"], nu=m["nu"], rho=m["rho_kg_m3"])
        self._section_type = cfg["section"]["type"]
        self._wall_ratio = cfg["section"].get("wall_ratio")
        self._model = None
        self._ref_cache = {}
        try:
            self._build_structure()
        except CaseError:
            raise
        except ModelError as exc:
            raise CaseError(f"{self.source}: the case's parameters do not make a valid model: "
                            f"{exc}") from None

    # ------------------------------------------------------------------ basics
    def __repr__(self):
        return (f"Case({self.name!r}, mechanism={self.mechanism!r}, formulation={self.formulation!r}, "
                f"t_end={self.t_end}, h={self.h}, design={self.design_names})")

    def with_overrides(self, **overrides):
        """A new case with some keys replaced (see `load_case`)."""
        return Case(self._raw, self.source, overrides)

    @property
    def nsteps(self):
        """Number of time steps of the case grid (the paper counts nsteps + 1 time steps)."""
        return int(round(self.t_end / self.h))

    @property
    def t(self):
        """The case's time grid t_j = j h, j = 0..nsteps."""
        return time_grid(self.t_end, self.h)[1]

    @property
    def model(self):
        """The case's Model (sections of the last design given to build_model)."""
        return self._model

    def section(self, p_mm):
        """The cross section of a design variable value p (mm)."""
        if isinstance(p_mm, (bool, np.bool_)) or not isinstance(p_mm, (numbers.Real, np.number)):
            raise CaseError(f"case {self.name!r}: a design value must be a positive number (mm), "
                            f"got {p_mm!r}")
        d = float(p_mm) * 1e-3
        if self._section_type == "tube":
            return Tube.with_wall_ratio(d, self._wall_ratio)
        return Circle(d)

    def _design(self, design_mm):
        """A design as a float array of shape (nv,): a flat sequence of nv positive numbers."""
        nv = len(self.design_names)
        want = (f"design must be a flat sequence of {nv} positive numbers (mm) "
                f"({', '.join(self.design_names)})")
        if design_mm is None:
            return np.array(self.start_mm, float)
        if isinstance(design_mm, (str, bytes, dict)) or np.isscalar(design_mm):
            raise CaseError(f"case {self.name!r}: {want}, got {design_mm!r}")
        raw = np.asarray(design_mm, dtype=object) if not isinstance(design_mm, np.ndarray) \
            else design_mm
        if raw.ndim != 1:
            raise CaseError(f"case {self.name!r}: {want}, got a nested sequence of shape "
                            f"{np.shape(raw)}: {design_mm!r}")
        if raw.dtype == object or raw.dtype.kind not in "iuf":
            for v in raw:
                if isinstance(v, (bool, np.bool_)) or not isinstance(v, (numbers.Real, np.number)):
                    raise CaseError(f"case {self.name!r}: {want}, got {design_mm!r} (entry {v!r})")
        p = np.asarray(raw, float)
        if p.shape != (nv,):
            raise CaseError(f"case {self.name!r}: design must have {nv} values "
                            f"({', '.join(self.design_names)}), got {p.size}")
        if not np.all(np.isfinite(p)) or np.any(p <= 0):
            raise CaseError(f"case {self.name!r}: design values must be positive and finite (mm), "
                            f"got {p.tolist()}")
        return p

    def start_design(self, start_mm=None, what="start design"):
        """A start design (mm; default the case's) checked: nv positive numbers within the bounds."""
        nv = len(self.design_names)
        if start_mm is None:
            p = np.array(self.start_mm, float)
        else:
            try:
                p = self._design(start_mm)
            except CaseError as exc:
                raise CaseError(f"{what} must have {nv} finite values (mm) within the bounds "
                                f"[{self.lower_mm.tolist()}, {self.upper_mm.tolist()}]: {exc}") from None
        if np.any(p < self.lower_mm) or np.any(p > self.upper_mm):
            raise CaseError(f"{what} {p.tolist()} is outside the bounds "
                            f"[{self.lower_mm.tolist()}, {self.upper_mm.tolist()}] mm")
        return p

    # ------------------------------------------------------------------ structure
    def _build_structure(self):
        P = self.parameters
        sec = self.section(self.start_mm[0])
        mat = self.material
        m = Model(self.name)
        if self.mechanism == "robot_2dof":
            l1, l2 = P["arm_lengths_m"]
            t10, t20 = math.radians(P["theta1_0_deg"]), math.radians(P["theta2_0_deg"])
            th1, th2, th12 = robot_joint_laws(l1, l2, t10, t20, P["path_period_s"], P["path_stroke_m"])
            A = (l1 * math.cos(t10), l1 * math.sin(t10))
            T = (A[0] + l2 * math.cos(t10 + t20), A[1] + l2 * math.sin(t10 + t20))
            n, order = P["elements_per_arm"], P["element_order"]
            arm1 = m.add_beam("arm1", (0.0, 0.0), A, n, material=mat, section=sec, order=order)
            arm2 = m.add_beam("arm2", A, T, n, material=mat, section=sec, order=order)
            m.pin(arm1.first)
            m.drive_rotation(arm1.first, th1)
            m.hinge(arm1.last, arm2.first)
            if P["drive"] == "absolute":
                m.drive_rotation(arm2.first, th12)
            else:
                m.drive_rotation(arm2.first, th2, relative_to=arm1.last)
            if P["mass_A_kg"] > 0:
                m.add_point_mass(arm1.last, P["mass_A_kg"])
            if P["mass_tip_kg"] > 0:
                m.add_point_mass(arm2.last, P["mass_tip_kg"])
            m.set_gravity(*P["gravity_m_s2"])
            self.points = {"O": arm1.first, "A": arm1.last, "tip": arm2.last}
            self.beams = ["arm1", "arm2"]
            self.esl_bodies = [("arm1", arm1.first), ("arm2", arm2.first)]
            half = n // 2
            var = {}
            for k, e in enumerate(arm1.elements):
                var[e] = 0 if k < half else 1
            for k, e in enumerate(arm2.elements):
                var[e] = 2 if k < half else 3
            if self.formulation == "28":
                self.sensor_dofs = np.array([3 * arm1.last + 1, 3 * arm2.last + 1])
            else:
                self.sensor_dofs = np.array([3 * arm2.last, 3 * arm2.last + 1])
        else:
            l1, l2, l3 = P["link_lengths_m"]
            l4 = P["ground_length_m"]
            th0 = self._theta0()
            pos = fourbar_positions(np.array([th0]), (l1, l2, l3), l4, P["branch"])
            A = tuple(pos["A"][0])
            B = tuple(pos["B"][0])
            n, order = P["elements_per_link"], P["element_order"]
            crank = m.add_beam("crank", (0.0, 0.0), A, n, material=mat, section=sec, order=order)
            coupler = m.add_beam("coupler", A, B, n, material=mat, section=sec, order=order)
            follower = m.add_beam("follower", (l4, 0.0), B, n, material=mat, section=sec, order=order)
            m.pin(crank.first)
            speed = P["crank_speed_rpm"] * 2 * math.pi / 60
            m.drive_rotation(crank.first, _crank_law(th0, P["ramp_time_s"], speed))
            m.hinge(crank.last, coupler.first)
            m.hinge(coupler.last, follower.last)
            m.pin(follower.first)
            if P["mass_A_kg"] > 0:
                m.add_point_mass(crank.last, P["mass_A_kg"])
            if P["mass_B_kg"] > 0:
                m.add_point_mass(coupler.last, P["mass_B_kg"])
            m.set_gravity(*P["gravity_m_s2"])
            self.points = {"O": crank.first, "A": crank.last, "B": coupler.last, "C": follower.first}
            self.beams = ["crank", "coupler", "follower"]
            self.esl_bodies = [("crank", crank.first), ("coupler", coupler.last),
                               ("follower", follower.first)]
            var = {}
            for i, b in enumerate((crank, coupler, follower)):
                for e in b.elements:
                    var[e] = i
            self.sensor_dofs = np.array([3 * crank.last, 3 * crank.last + 1])
        nel = len(m._elements)
        #: design variable (0-based) of every element, in the model's element order
        self.element_design_map = np.array([var[e] for e in range(nel)], dtype=int)
        self._element_lengths = np.array([m._elements[e][1] for e in range(nel)])
        self._model = m

    def _theta0(self):
        """Initial crank angle (rad) in (-pi, pi], the range of the beam's reference rotation."""
        th = math.radians(self.parameters["theta0_deg"])
        return math.atan2(math.sin(th), math.cos(th))

    def build_model(self, design_mm=None):
        """The case's Model with the element sections of a design (mm; default: start design).

        The structure is built once per case: the same Model object is returned every time,
        with its sections replaced (keep a design's results, not its model).
        """
        p = self._design(design_mm)
        secs = [self.section(v) for v in p]
        for name in self.beams:
            body = self._model.body(name)
            self._model.set_element_sections(body, [secs[self.element_design_map[e]]
                                                    for e in body.elements])
        return self._model

    # ------------------------------------------------------------------ mass
    def mass(self, design_mm):
        """Beam mass (kg) of a design (mm), lumped masses excluded."""
        p = self._design(design_mm)
        rho_a = np.array([self.section(v).properties(self.material)[3] for v in p])
        return float(np.sum(self._element_lengths * rho_a[self.element_design_map]))

    def mass_gradient(self, design_mm):
        """d(mass)/dp (kg/mm), shape (nv,)."""
        dprops = self.element_property_derivatives(design_mm)          # (5, nel, nv)
        return np.einsum("e,ev->v", self._element_lengths, dprops[3])

    def element_property_derivatives(self, design_mm):
        """d[EA, kGA, EI, rhoA, rhoI]/dp of every element, shape (5, nel, nv), p in mm.

        Element e depends on design variable element_design_map[e] only; the derivatives come
        from Section.property_derivatives (with Cowper's shear factor).
        """
        p = self._design(design_mm)
        nel = self.element_design_map.size
        out = np.zeros((5, nel, p.size))
        dsec = [self.section(v).property_derivatives(self.material)[:, 0] * 1e-3 for v in p]
        for e, i in enumerate(self.element_design_map):
            out[:, e, i] = dsec[i]
        return out

    # ------------------------------------------------------------------ rigid reference
    @property
    def rigid_reference(self):
        """Histories of the rigid reference mechanism on the case grid (computed once).

        Robot: t, theta1, theta2 (rad), x_A, y_A, x_tip, y_tip (m).
        Four-bar: t, theta (crank), phi_coupler, phi_follower (rad) with their rates and
        accelerations, x_A, y_A, x_B, y_B (m).
        """
        return self.rigid_reference_at(self.t)

    def rigid_reference_at(self, t):
        """Rigid reference histories on any time grid `t` (cached per grid)."""
        t = _float_array(t)
        if t is None or t.ndim != 1 or t.size < 1 or not np.all(np.isfinite(t)):
            raise ModelError(f"case {self.name!r}: t must be a non-empty 1-D array of finite times, "
                             f"got {t!r:.80}")
        key = (t.size, float(t[0]), float(t[-1]))
        if key in self._ref_cache:
            return self._ref_cache[key]
        P = self.parameters
        if self.mechanism == "robot_2dof":
            l1, l2 = P["arm_lengths_m"]
            t10, t20 = math.radians(P["theta1_0_deg"]), math.radians(P["theta2_0_deg"])
            x0 = l1 * math.cos(t10) + l2 * math.cos(t10 + t20)
            y0 = l1 * math.sin(t10) + l2 * math.sin(t10 + t20)
            path = robot_tip_path(t, x0, y0, P["path_period_s"], P["path_stroke_m"])
            elbow = -1.0 if math.sin(t20) < 0 else 1.0
            th1, th2, *_ = planar_2r_inverse(*path, l1, l2, elbow)
            ref = dict(t=t, theta1=th1, theta2=th2, x_A=l1 * np.cos(th1), y_A=l1 * np.sin(th1),
                       x_tip=path[0], y_tip=path[1])
        else:
            l1, l2, l3 = P["link_lengths_m"]
            law = _crank_law(self._theta0(), P["ramp_time_s"],
                             P["crank_speed_rpm"] * 2 * math.pi / 60)
            th, w, al = law.value(t), law.rate(t), law.accel(t)
            k = fourbar_positions(th, (l1, l2, l3), P["ground_length_m"], P["branch"], w, al)
            ref = dict(t=t, theta=th, theta_rate=w, theta_accel=al,
                       phi_coupler=k["phi_coupler"], phi_follower=k["phi_follower"],
                       phi_coupler_rate=k["phi_coupler_rate"],
                       phi_follower_rate=k["phi_follower_rate"],
                       phi_coupler_accel=k["phi_coupler_accel"],
                       phi_follower_accel=k["phi_follower_accel"],
                       x_A=k["A"][:, 0], y_A=k["A"][:, 1], x_B=k["B"][:, 0], y_B=k["B"][:, 1])
        for v in ref.values():
            v.setflags(write=False)
        self._ref_cache[key] = ref
        return ref

    def _check_reference(self, reference):
        keys = ("theta1", "x_A") if self.mechanism == "robot_2dof" else ("theta", "phi_coupler")
        if not isinstance(reference, dict) or not all(k in reference for k in ("t",) + keys):
            raise ModelError(f"case {self.name!r}: reference must be a dict from "
                             f"rigid_reference / rigid_reference_at, got {reference!r:.80}")
        return reference

    def rigid_frames(self, reference):
        """Root position (nt, 2) and angle (nt,) of every beam of the rigid reference."""
        r = self._check_reference(reference)
        if self.mechanism == "robot_2dof":
            zero = np.zeros_like(r["t"])
            return {"arm1": (np.stack([zero, zero], -1), r["theta1"]),
                    "arm2": (np.stack([r["x_A"], r["y_A"]], -1), r["theta1"] + r["theta2"])}
        zero = np.zeros_like(r["t"])
        return {"crank": (np.stack([zero, zero], -1), r["theta"]),
                "coupler": (np.stack([r["x_A"], r["y_A"]], -1), r["phi_coupler"]),
                "follower": (np.stack([zero + self.parameters["ground_length_m"], zero], -1),
                             r["phi_follower"])}

    def rigid_node_positions(self, reference, body):
        """Positions (nt, nnodes, 2) of a beam's nodes in the rigid reference mechanism."""
        self._check_reference(reference)
        b = self._model.body(body)
        if b.name not in self.beams:
            raise ModelError(f"case {self.name!r}: body must be one of its beams {self.beams}, "
                             f"got {body!r}")
        q = self._model.reference_coordinates().reshape(-1, 3)
        s = np.hypot(*(q[b.nodes, :2] - q[b.first, :2]).T)          # distance from the root
        root, ang = self.rigid_frames(reference)[body]
        e = np.stack([np.cos(ang), np.sin(ang)], -1)                  # (nt, 2)
        return root[:, None, :] + s[None, :, None] * e[:, None, :]

    # ------------------------------------------------------------------ deviation
    def deviation_from_sensors(self, qs, t=None):
        """Deviation history and its Jacobian w.r.t. the sensor coordinates.

        Parameters
        ----------
        qs : (nt, nsens) array
            The coordinates `sensor_dofs` at every time step.
        t : (nt,) array, optional
            Their time grid (default: the case grid).

        Returns
        -------
        dev : (nt,) deviation (m) of the case's formulation.
        jac : (nt, nsens) d dev_n / d qs_n (exact; zero where dev_n = 0).
        """
        tt = self.t if t is None else _float_array(t)
        qs = _float_array(qs)
        if tt is None or qs is None or tt.ndim != 1 or qs.shape != (tt.size, self.sensor_dofs.size):
            raise ModelError(f"case {self.name!r}: sensor history qs must be a number array of shape "
                             f"(nt, {self.sensor_dofs.size}) on a 1-D time grid t")
        ref = self.rigid_reference_at(tt)
        jac = np.zeros_like(qs)
        if self.formulation == "28":
            a = qs[:, 0] - ref["y_A"]
            b = (qs[:, 1] - ref["y_tip"]) - a
            dev = np.hypot(a, b)
            safe = np.where(dev > 0, dev, 1.0)
            jac[:, 0] = np.where(dev > 0, (a - b) / safe, 0.0)
            jac[:, 1] = np.where(dev > 0, b / safe, 0.0)
        else:
            pt = "tip" if self.formulation == "30" else "A"
            a = qs[:, 0] - ref[f"x_{pt}"]
            b = qs[:, 1] - ref[f"y_{pt}"]
            dev = np.hypot(a, b)
            safe = np.where(dev > 0, dev, 1.0)
            jac[:, 0] = np.where(dev > 0, a / safe, 0.0)
            jac[:, 1] = np.where(dev > 0, b / safe, 0.0)
        return dev, jac

    # ------------------------------------------------------------------ simulation
    def simulate(self, design_mm=None, **sim_kw):
        """Simulate a design (mm; default: the start design) and evaluate its deviation.

        Parameters
        ----------
        design_mm : (nv,) array, optional
        **sim_kw
            Passed to flexmbs.simulate; t_end, h, rho_inf and start default to the case's
            (t_end, h, rho_inf, start_mode). With store=[...] the sensor nodes are added.

        Returns
        -------
        CaseResult
        """
        p = self._design(design_mm)
        model = self.build_model(p)
        kw = dict(rho_inf=self.rho_inf, start=self.start_mode)
        kw.update(sim_kw)
        t_end = kw.pop("t_end", self.t_end)
        h = kw.pop("h", self.h)
        store = kw.get("store", "all")
        if isinstance(store, (list, tuple, np.ndarray)):
            kw["store"] = list(store) + sorted({int(d) // 3 for d in self.sensor_dofs})
        res = _simulate(model, t_end, h, **kw)
        qs = res.coordinates(self.sensor_dofs)
        dev, _ = self.deviation_from_sensors(qs, res.t)
        k = int(np.argmax(dev))
        return CaseResult(case_name=self.name, formulation=self.formulation, design_mm=p,
                          mass=self.mass(p), t=res.t, deviation=dev, max_deviation=float(dev[k]),
                          t_at_max=float(res.t[k]), step_at_max=k + 1, limit_m=self.limit_m,
                          reference=self.rigid_reference_at(res.t), result=res, case=self)
