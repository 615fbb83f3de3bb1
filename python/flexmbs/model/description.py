"""The general description of a planar mechanism and its sizing problem (the case format).

One description, two ways in: a TOML case file (`flexmbs.model.casefile.load_problem`) or Python
(``Description(**dict)`` or `Description.model_validate`). Every key is documented in
``docs/case-format.md``; the validation is pydantic's (types, ranges, unknown keys), completed
by the cross-references checked in `Description.check_references` (a body named by a joint
exists, a point named by a body exists, a section parameter names a design variable, ...).

Units are SI, except where a design variable says otherwise (``unit = "mm"``: its bounds and
start are in mm, and so are the values a user passes for it).

Example (a pendulum: a beam pinned at O, driven by a ramp to 60 rpm)::

    >>> from flexmbs.model.description import Description
    >>> d = Description.model_validate({
    ...     "points": {"O": [0, 0], "A": [0.5, 0]},
    ...     "materials": {"steel": {"E": 210e9, "nu": 0.3, "rho": 7850}},
    ...     "bodies": [{"name": "arm", "type": "beam", "from": "O", "to": "A",
    ...                 "material": "steel", "section": {"shape": "circle", "diameter": 0.02}}],
    ...     "joints": [{"type": "pin", "body": "arm", "at": "O"}],
    ...     "drives": [{"type": "rotation", "body": "arm", "at": "O",
    ...                 "law": {"type": "ramp_to_speed", "speed_rpm": 60, "ramp_s": 0.2}}],
    ...     "time": {"t_end": 0.4, "h": 1e-3}})
    >>> d.bodies[0].elements
    2
"""
from __future__ import annotations

import math
import sys
from typing import Annotated, Literal, Union

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, field_validator, model_validator

from flexmbs.model.options import OptimizeSection
from flexmbs.resources import MAX_STEPS

__all__ = ["Description", "Law", "Beam", "Rigid", "PointMass", "Joint", "Drive", "Load",
           "SpringDamper", "DesignVariable", "Deviation", "Mass", "Stress", "Torque", "Reaction",
           "Station", "Deflection", "Strain", "Constraint", "TimeSettings", "SolverSettings",
           "InitialState", "InitialBeam", "Section", "MaterialSpec", "Term", "PointRef", "GROUND",
           "design_layout"]



def _not_bool(v):
    """A number of a case is never a boolean (TOML's true is not 1 kg, 1 s or 1 element)."""
    if isinstance(v, bool):
        raise ValueError("must be a number, not a boolean")
    return v


#: refuses a boolean where a number is expected (pydantic would read true as 1)
NoBool = BeforeValidator(_not_bool)
Finite = Annotated[float, NoBool, Field(allow_inf_nan=False)]
Positive = Annotated[float, NoBool, Field(gt=0, allow_inf_nan=False)]
NonNegative = Annotated[float, NoBool, Field(ge=0, allow_inf_nan=False)]
#: an integer, never a boolean
Int = Annotated[int, NoBool]
Name = Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z_][A-Za-z0-9_.\-]*$")]
Pair = Annotated[list[Finite], Field(min_length=2, max_length=2)]
#: the name that stands for the ground in a prismatic joint's bodies and a deviation's frame
GROUND = "ground"
#: a section dimension: a number (m), a design variable's name, or one of them per element
Dimension = Union[Positive, Name, list[Union[Positive, Name]]]


def _direction_error(axis):
    """Why `axis` ([ax, ay]) is no direction, or None: its squared length must be a positive
    normal double (it is normalised, and squared in the joints' equations)."""
    if axis is None:
        return "got none"
    sq = axis[0] * axis[0] + axis[1] * axis[1]
    if not (sys.float_info.min <= sq < math.inf):
        return (f"got axis = {axis} (length {math.hypot(*axis):.3g}); give a direction whose "
                f"length is between 1e-150 and 1e150 (e.g. [1, 0])")
    return None


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True, frozen=False)


# ----------------------------------------------------------------------------- laws
class Law(_Strict):
    """A time law with analytic rate and acceleration (motors, loads, paths).

    type:
      constant       value
      ramp_to_speed  start + speed*t^2/(2 ramp_s) for t <= ramp_s, then at constant speed
                     (speed in rad/s or m/s, or speed_rpm); the paper's crank law
      smooth_step    from `start` to `end` over [t0, t1] by a quintic with zero rate and
                     acceleration at both ends
      harmonic       offset + amplitude sin(2 pi frequency_hz t + phase)
      cycloid        start + stroke (t/period - sin(2 pi t/period)/(2 pi)) (used as is
                     beyond the period, like the paper's eq. 26)
      polynomial     sum coefficients[k] t^k
      samples        through (times, values): 'pchip' (monotone cubic, no overshoot; default)
                     or 'cubic' (cubic spline, continuous acceleration) `interpolation`;
                     beyond its times an error unless `extrapolate` = 'hold' (the end value)
                     or 'linear' (on along the end tangent)
      reference      (drives only) the motion the rigid reference gives this drive when the
                     mechanism's ideal motion is prescribed by `paths`
      piecewise      `segments`: a list of {until, law}, each law (any type but 'reference')
                     over [the previous segment's until, its until); the last segment has no
                     until and runs on; the laws are of the absolute time t
      sum            `laws`: the sum of a list of laws (any type but 'reference')
    A rotation drive's law is added to the driven node's initial angle unless
    `absolute = true` (then the law is the angle itself, rad).
    """
    type: Literal["constant", "ramp_to_speed", "smooth_step", "harmonic", "cycloid",
                  "polynomial", "samples", "reference", "piecewise", "sum"]
    value: Finite | None = None
    start: Finite = 0.0
    end: Finite | None = None
    speed: Finite | None = None
    speed_rpm: Finite | None = None
    ramp_s: Positive | None = None
    t0: NonNegative = 0.0
    t1: Positive | None = None
    amplitude: Finite | None = None
    frequency_hz: Positive | None = None
    phase: Finite = 0.0
    offset: Finite = 0.0
    stroke: Finite | None = None
    period: Positive | None = None
    coefficients: Annotated[list[Finite], Field(min_length=1)] | None = None
    times: list[Finite] | None = None
    values: list[Finite] | None = None
    interpolation: Literal["pchip", "cubic"] = "pchip"
    extrapolate: Literal["hold", "linear"] | None = None
    segments: Annotated[list["Segment"], Field(min_length=1)] | None = None
    laws: Annotated[list["Law"], Field(min_length=1)] | None = None
    absolute: bool = False

    @model_validator(mode="after")
    def _needs(self):
        need = {"constant": ["value"], "ramp_to_speed": ["ramp_s"],
                "smooth_step": ["end", "t1"], "harmonic": ["amplitude", "frequency_hz"],
                "cycloid": ["stroke", "period"], "polynomial": ["coefficients"],
                "samples": ["times", "values"], "reference": [], "piecewise": ["segments"],
                "sum": ["laws"]}[self.type]
        missing = [k for k in need if getattr(self, k) is None]
        if missing:
            raise ValueError(f"law type {self.type!r} needs {', '.join(missing)}")
        if self.type == "ramp_to_speed" and (self.speed is None) == (self.speed_rpm is None):
            raise ValueError("law type 'ramp_to_speed' needs exactly one of speed, speed_rpm")
        if self.type == "smooth_step" and not self.t1 > self.t0:
            raise ValueError(f"smooth_step: t1 = {self.t1} must be after t0 = {self.t0}")
        if self.extrapolate is not None and self.type != "samples":
            raise ValueError(f"extrapolate applies to a 'samples' law, not to {self.type!r}")
        for key, kind in (("segments", "piecewise"), ("laws", "sum")):
            if getattr(self, key) is not None and self.type != kind:
                raise ValueError(f"{key} belongs to a {kind!r} law, not to {self.type!r}")
        inner = [g.law for g in self.segments or []] + list(self.laws or [])
        for k, law in enumerate(inner):
            if law.type == "reference":
                raise ValueError(f"{self.type}: law {k + 1} is of type 'reference', which is "
                                 "a whole drive's law, not a part of one")
            if law.absolute:
                raise ValueError(f"{self.type}: law {k + 1} sets absolute = true; set it on "
                                 f"the {self.type} law itself")
        if self.segments is not None:
            ends = [g.until for g in self.segments]
            if any(u is None for u in ends[:-1]) or ends[-1] is not None:
                raise ValueError("piecewise: every segment but the last needs until (the end "
                                 "of its interval, s); the last has none (it runs on)")
            if any(b <= a for a, b in zip(ends[:-1], ends[1:-1])):
                raise ValueError(f"piecewise: the segments' until = {ends[:-1]} must increase "
                                 "strictly")
        if self.type == "samples":
            if len(self.times) != len(self.values) or len(self.times) < 2:
                raise ValueError("samples: times and values need the same length, at least 2")
            if any(b <= a for a, b in zip(self.times, self.times[1:])):
                raise ValueError("samples: times must increase strictly")
        return self


#: how far a path may move its point, in sizes of the mechanism (the diagonal of the box
#: around its points):
#: coordinates beyond it keep fewer than 6 of double precision's 16 digits for the mechanism's
#: own lengths, which the constraint tolerances (1e-10 of the size) need
PATH_REACH = 1e6


def law_bound(law, t_end):
    """An upper bound of |law(t)| over 0 <= t <= t_end, from the law's parameters (float;
    inf when they overflow); of a 'samples' law, its largest sample (a linear extrapolation
    beyond them is not counted)."""
    k, T = law.type, max(t_end, 1.0)
    start0 = abs(law.start)
    if k == "constant":
        return abs(law.value)
    if k == "ramp_to_speed":
        w = law.speed if law.speed is not None else law.speed_rpm * 2 * math.pi / 60
        return start0 + abs(w) * T
    if k == "smooth_step":
        return max(start0, abs(law.end))
    if k == "harmonic":
        return abs(law.offset) + abs(law.amplitude)
    if k == "cycloid":
        return start0 + abs(law.stroke) * (T / law.period + 1.0)
    if k == "polynomial":
        return sum(abs(c) * T ** j for j, c in enumerate(law.coefficients))
    if k == "samples":
        return max(abs(x) for x in law.values)
    if k == "piecewise":
        return max(law_bound(g.law, t_end) for g in law.segments)
    if k == "sum":
        return sum(law_bound(x, t_end) for x in law.laws)
    return 0.0


class Segment(_Strict):
    """A piece of a 'piecewise' law: `law` up to time `until` (s; from the previous segment's
    until, or from the start); the last segment has no until."""
    until: Finite | None = None
    law: Law


Law.model_rebuild()


# ----------------------------------------------------------------------------- parts
class MaterialSpec(_Strict):
    """Linear elastic isotropic material: E (Pa), nu, rho (kg/m^3); optionally Kelvin–Voigt
    damping of its beams (flexmbs.Material): `damping_time` eta (s), or `damping_ratio` zeta
    at `damping_frequency` f (Hz), eta = 2 zeta / (2 pi f)."""
    E: Positive
    nu: Annotated[float, NoBool, Field(gt=-1.0, lt=0.5)]
    rho: Positive
    damping_time: NonNegative | None = None
    damping_ratio: NonNegative | None = None
    damping_frequency: Positive | None = None

    @model_validator(mode="after")
    def _damping(self):
        if (self.damping_ratio is None) != (self.damping_frequency is None):
            raise ValueError("damping_ratio and damping_frequency go together (the ratio zeta "
                             "at the frequency f in Hz)")
        if self.damping_time is not None and self.damping_ratio is not None:
            raise ValueError("give either damping_time or damping_ratio with "
                             "damping_frequency, not both")
        return self


class Section(_Strict):
    """A beam cross section. Dimensions (m) are numbers, design variable names (an
    element-wise variable, `DesignVariable.elementwise`, gives each element its own
    component), or a list of numbers and scalar variables' names with one entry per element
    (root element first) or per group of elements (the elements are split into len(list)
    equal consecutive groups).

    shape:
      circle     diameter
      tube       diameter and thickness, or diameter and wall_ratio (thickness = ratio * d)
      rectangle  width (out of plane) and height (in the plane of bending)
      given      EA, EI, rhoA, rhoI > 0 (and optionally GA: the shear stiffness kGA); without
                 GA the beam is shear-rigid in practice (kGA = 1e4 EA / ... see docs)
    """
    shape: Literal["circle", "tube", "rectangle", "given"]
    diameter: Dimension | None = None
    thickness: Dimension | None = None
    wall_ratio: Annotated[float, NoBool, Field(gt=0, le=0.5)] | None = None
    width: Dimension | None = None
    height: Dimension | None = None
    EA: Positive | None = None
    EI: Positive | None = None
    GA: Positive | None = None
    rhoA: Positive | None = None
    rhoI: NonNegative | None = None

    @model_validator(mode="after")
    def _dims(self):
        need = {"circle": ["diameter"], "tube": ["diameter"],
                "rectangle": ["width", "height"], "given": ["EA", "EI", "rhoA"]}[self.shape]
        missing = [k for k in need if getattr(self, k) is None]
        if missing:
            raise ValueError(f"section shape {self.shape!r} needs {', '.join(missing)}")
        if self.shape == "given" and not self.rhoI:
            raise ValueError(
                f"section shape 'given' needs rhoI > 0 (kg m, the rotary inertia per unit "
                f"length), got {'none' if self.rhoI is None else self.rhoI}: without it a "
                f"node's rotation has no mass; for a homogeneous section rhoI = rhoA EI / EA "
                f"(here {self.rhoA * self.EI / self.EA:.6g})")
        if self.shape == "tube" and (self.thickness is None) == (self.wall_ratio is None):
            raise ValueError("section shape 'tube' needs exactly one of thickness, wall_ratio")
        allowed = {"circle": {"diameter"}, "tube": {"diameter", "thickness", "wall_ratio"},
                   "rectangle": {"width", "height"},
                   "given": {"EA", "EI", "GA", "rhoA", "rhoI"}}[self.shape]
        extra = [k for k in ("diameter", "thickness", "wall_ratio", "width", "height", "EA", "EI",
                             "GA", "rhoA", "rhoI") if getattr(self, k) is not None and k not in allowed]
        if extra:
            raise ValueError(f"section shape {self.shape!r} does not take {', '.join(extra)}")
        return self

    def dimensions(self):
        """{dimension: value} of the dimensions that may carry design variables."""
        return {k: getattr(self, k) for k in ("diameter", "thickness", "width", "height")
                if getattr(self, k) is not None}


class Beam(_Strict):
    """A flexible beam: a chain of `elements` elements of `order` (1: 2-node, 2: 3-node)
    from point `from` to point `to` (named in [points]); its nodes at the two ends are the
    body's points `from` and `to` (joints, loads and responses name them)."""
    name: Name
    type: Literal["beam"]
    start: Name = Field(alias="from")
    end: Name = Field(alias="to")
    elements: Annotated[int, NoBool, Field(ge=1, le=20_000)] = 2
    order: Annotated[Literal[1, 2], NoBool] = 2
    material: Name | None = None
    section: Section

    @model_validator(mode="after")
    def _material(self):
        if self.material is None and self.section.shape != "given":
            raise ValueError(f"beam {self.name!r}: a {self.section.shape!r} section needs a "
                             "material (only a 'given' section, whose EA, EI, rhoA are its "
                             "own, goes without)")
        return self


class Rigid(_Strict):
    """A rigid body through named points, with its mass (kg) and inertia about its centre
    (kg m^2); the centre is a named point or the points' centroid."""
    name: Name
    type: Literal["rigid"]
    points: Annotated[list[Name], Field(min_length=1)]
    mass: NonNegative = 0.0
    inertia: NonNegative = 0.0
    center: Name | None = None


class PointMass(_Strict):
    """A lumped mass (kg, optional rotary inertia kg m^2) at a point: a body of its own
    (give it joints) or, with `on`, added to the node of body `on` at that point."""
    name: Name
    type: Literal["mass"]
    at: Name
    mass: NonNegative
    inertia: NonNegative = 0.0
    on: Name | None = None


Body = Annotated[Union[Beam, Rigid, PointMass], Field(discriminator="type")]


class Joint(_Strict):
    """A joint at a point.

    type:
      pin     body to the ground (position fixed, rotation free)
      clamp   body to the ground (position and rotation fixed)
      hinge   two bodies share the point (rotation free)
      weld    two bodies share the point and keep their relative rotation
      slider  body's point moves on the ground line through the point along `axis`; the
              body does not rotate (a prismatic joint on the ground)
      prismatic  bodies = [a, b]: b's point slides along the line through the point with
              direction `axis` (in the initial configuration) fixed in body a, and b keeps
              its rotation relative to a; a = "ground" (or b = "ground") is a slider
    """
    type: Literal["pin", "clamp", "hinge", "weld", "slider", "prismatic"]
    at: Name
    body: Name | None = None
    bodies: Annotated[list[Name], Field(min_length=2, max_length=2)] | None = None
    axis: Pair | None = None
    name: Name | None = None

    @model_validator(mode="after")
    def _who(self):
        two = self.type in ("hinge", "weld", "prismatic")
        if two and self.bodies is None:
            raise ValueError(f"joint type {self.type!r} needs bodies = [a, b]")
        if not two and self.body is None:
            raise ValueError(f"joint type {self.type!r} needs body")
        if two and self.body is not None or not two and self.bodies is not None:
            raise ValueError(f"joint type {self.type!r} takes "
                             f"{'bodies' if two else 'body'}, not {'body' if two else 'bodies'}")
        if self.type in ("slider", "prismatic"):
            why = _direction_error(self.axis)
            if why:
                raise ValueError(f"joint type {self.type!r} needs a non-zero axis = [ax, ay]: "
                                 f"{why}")
        if self.type == "prismatic":
            a, b = self.bodies
            if a == b:
                raise ValueError(f"joint type 'prismatic': bodies = {self.bodies} names body "
                                 f"{a!r} twice; give two different bodies (or \"ground\" and a "
                                 f"body)")
        if self.type not in ("slider", "prismatic") and self.axis is not None:
            raise ValueError(f"joint type {self.type!r} takes no axis")
        return self


class Drive(_Strict):
    """A motor: the rotation of `body` at point `at` (absolute, or relative to body
    `relative_to` at the same point), or its translation along `axis` (from the point's
    initial position)."""
    type: Literal["rotation", "translation"]
    body: Name
    at: Name
    law: Law
    relative_to: Name | None = None
    axis: Pair | None = None
    name: Name | None = None

    @model_validator(mode="after")
    def _kind(self):
        if self.type == "translation":
            why = _direction_error(self.axis)
            if why:
                raise ValueError(f"drive type 'translation' needs a non-zero axis = [ax, ay]: "
                                 f"{why}")
            if self.relative_to is not None:
                raise ValueError("drive type 'translation' takes no relative_to")
        elif self.axis is not None:
            raise ValueError("drive type 'rotation' takes no axis")
        law = self.law
        if law.type == "constant" and law.value != 0.0 and not (
                self.type == "rotation" and law.absolute):
            what = ("the change of angle from the initial one" if self.type == "rotation"
                    else "the displacement along the axis from the initial position")
            fix = ("absolute = true in the law to impose the angle itself, or " if
                   self.type == "rotation" else "")
            raise ValueError(
                f"a constant law (value = {law.value:g}) cannot move this drive: its law is "
                f"{what}, the law's value at t = 0 subtracted, so a constant gives no motion; "
                f"give {fix}a law that changes with time (value = 0 holds the drive at its "
                "initial configuration)")
        return self


class Path(_Strict):
    """The ideal motion of a point, for the rigid reference only: the point `at` of `body`
    follows x(t), y(t); drives whose law is 'reference' take their motion from it."""
    body: Name
    at: Name
    x: Law
    y: Law


class Load(_Strict):
    """A force (N) and moment (N m) at a point of a body, times a law of time if given."""
    body: Name
    at: Name
    fx: Finite = 0.0
    fy: Finite = 0.0
    moment: Finite = 0.0
    law: Law | None = None


class SpringDamper(_Strict):
    """A point-to-point spring-damper between two bodies' points: stiffness (N/m), damping
    (N s/m), free length (m; default: the initial distance)."""
    bodies: Annotated[list[Name], Field(min_length=2, max_length=2)]
    at: Annotated[list[Name], Field(min_length=2, max_length=2)]
    stiffness: NonNegative
    damping: NonNegative = 0.0
    free_length: Positive | None = None


class DesignVariable(_Strict):
    """A sizing variable: bounds, start, and the unit of the values given for it.

    Element-wise: with ``per_element = true`` the variable is an array with one component per
    element of the beams whose section names it (root element first); with ``groups`` (lists
    of 1-based element numbers, every element in exactly one group) one component per group.
    The components are named ``name[1]``, ``name[2]``, ...; each has the variable's bounds and
    start. Beams sharing an element-wise variable must have the same number of elements
    (component k sizes element k of each). ``max_step`` (in the variable's unit) bounds the
    change between neighbouring components, |x[k+1] - x[k]| <= max_step, and
    ``max_step_relative`` = r bounds it relative to each: x[k+1] <= (1 + r) x[k] and
    x[k] <= (1 + r) x[k+1]; both are linear constraints of the sizing problem.
    """
    name: Name
    lower: Positive
    upper: Positive
    start: Positive
    unit: Literal["m", "mm"] = "m"
    description: str | None = None
    per_element: bool | None = None
    groups: Annotated[list[Annotated[list[Annotated[int, NoBool, Field(ge=1)]], Field(min_length=1)]],
                      Field(min_length=1)] | None = None
    max_step: Positive | None = None
    max_step_relative: Positive | None = None

    @model_validator(mode="after")
    def _bounds(self):
        if not self.lower < self.upper:
            raise ValueError(f"design variable {self.name!r}: lower = {self.lower} must be "
                             f"below upper = {self.upper}")
        if not self.lower <= self.start <= self.upper:
            raise ValueError(f"design variable {self.name!r}: start = {self.start} must lie "
                             f"within [{self.lower}, {self.upper}]")
        if self.groups is not None and self.per_element is False:
            raise ValueError(f"design variable {self.name!r}: groups = {self.groups} makes it "
                             f"element-wise, but per_element = false; drop per_element or set "
                             f"it to true")
        if not self.elementwise:
            for key in ("max_step", "max_step_relative"):
                if getattr(self, key) is not None:
                    raise ValueError(f"design variable {self.name!r}: {key} = "
                                     f"{getattr(self, key)} needs an element-wise variable "
                                     f"(per_element = true or groups)")
        if self.groups is not None:
            seen = set()
            for g in self.groups:
                for e in g:
                    if e in seen:
                        raise ValueError(f"design variable {self.name!r}: groups = "
                                         f"{self.groups} lists element {e} twice; every "
                                         f"element belongs to exactly one group")
                    seen.add(e)
        return self

    @property
    def elementwise(self):
        """An array over elements (per_element = true or groups given)."""
        return bool(self.per_element) or self.groups is not None

    @property
    def scale(self):
        """Metres per unit of the variable."""
        return 1e-3 if self.unit == "mm" else 1.0


# ----------------------------------------------------------------------------- responses
class Station(_Strict):
    """A station along a beam: `s`, the fraction (0 to 1) of the beam's reference length from
    its `from` end. It lies in element k = floor(s n) of the n elements (the last one at
    s = 1; at an element boundary the element after it) at xi = 2 (s n - k) - 1, and its
    position, rotation and strains are the element's own interpolation there
    (flexmbs.responses.station)."""
    body: Name
    s: Annotated[float, NoBool, Field(ge=0.0, le=1.0, allow_inf_nan=False)]


class _Located(_Strict):
    """A named point `at` of body `body`, or a station `at = {body, s}` (body then optional)."""
    body: Name | None = None
    at: Union[Name, Station]

    @model_validator(mode="after")
    def _station_body(self):
        if isinstance(self.at, Station):
            if self.body is not None and self.body != self.at.body:
                raise ValueError(f"body = {self.body!r} contradicts at.body = "
                                 f"{self.at.body!r}; give the body once, in at")
            self.body = self.at.body
        elif self.body is None:
            raise ValueError(f"at = {self.at!r} names a point: give its body too (or a "
                             "station, at = {body = ..., s = ...})")
        return self


class PointRef(_Located):
    """A point of a body, or a station along a beam."""


class Term(_Located):
    """One scalar deviation term: component `component` of (the point's flexible position
    minus its position in the rigid reference), or of the same difference for the vector from
    `relative_to` to the point; measured in the ground frame or in the rigid reference's frame
    of body `frame` (axes: x along the body's initial direction, y normal to it).
    component 'angle': the rotation of the point's node minus its rigid rotation (rad).
    The point is a body's named point or a station along a beam (`at = {body, s}`), whose
    position and rotation are interpolated by its element's shape functions."""
    component: Literal["x", "y", "norm", "angle"] = "norm"
    relative_to: PointRef | None = None
    frame: Name = "ground"


class Deviation(_Strict):
    """Deviation from the rigid reference: sqrt(sum of the terms' squares) (a term of
    component 'norm' counts its x and y)."""
    name: Name
    type: Literal["deviation"]
    terms: Annotated[list[Term], Field(min_length=1)]


class Mass(_Strict):
    """Mass (kg) of the beams named in `bodies` (all beams if omitted)."""
    name: Name
    type: Literal["mass"]
    bodies: list[Name] | None = None


class Stress(_Strict):
    """Largest normal stress (Pa) at the extreme fibres of the elements of the beams named
    (`bodies`), or at one station of a beam (`at = {body, s}`): E (|eps| + c |kappa|)."""
    name: Name
    type: Literal["stress"]
    bodies: Annotated[list[Name], Field(min_length=1)] | None = None
    at: Station | None = None

    @model_validator(mode="after")
    def _where(self):
        if (self.bodies is None) == (self.at is None):
            raise ValueError(f"stress {self.name!r} needs exactly one of bodies (the largest "
                             "over their elements) and at (a station {body, s})")
        return self

    @property
    def beams(self):
        """The beams it reads."""
        return self.bodies if self.at is None else [self.at.body]


class Deflection(_Strict):
    """Deflection (m) of a station of a beam from the chord through the beam's end nodes,
    signed: positive on the left of the chord (from its `from` end to its `to` end). Zero in
    the straight initial configuration; the rigid reference plays no part."""
    name: Name
    type: Literal["deflection"]
    at: Station


class Strain(_Strict):
    """A strain measure at a station of a beam, from the reference configuration: 'axial'
    eps (Gamma_1), 'shear' gamma (Gamma_2), both dimensionless, or 'curvature' kappa (1/m)."""
    name: Name
    type: Literal["strain"]
    at: Station
    component: Literal["axial", "shear", "curvature"] = "axial"


class Torque(_Strict):
    """The motor torque (N m) of the rotation drive named `drive`, positive counter-clockwise on
    the driven body (its `body`; a relative drive's `relative_to` body receives the opposite
    torque), or the force (N) of a translation drive along its axis, over time. A bound on its
    absolute value is a constraint with upper = limit and lower = -limit."""
    name: Name
    type: Literal["torque"]
    drive: Name


class Reaction(_Strict):
    """The reaction force (N) of the joint named `joint` over time: the force the joint exerts
    on the node of its (first) body at its point, in the ground frame, component `x`, `y` or
    `magnitude` (of a pin, hinge, clamp and weld: both components; of a slider: the normal
    force, along the normal of its axis; of a prismatic joint between two bodies: only the
    magnitude of its normal force, whose direction turns with the first body)."""
    name: Name
    type: Literal["reaction"]
    joint: Name
    component: Literal["x", "y", "magnitude"] = "magnitude"


Response = Annotated[Union[Deviation, Mass, Stress, Torque, Reaction, Deflection, Strain],
                     Field(discriminator="type")]


class Constraint(_Strict):
    """response <= upper (and/or >= lower) over time: at every step (the paper's local
    constraints), its maximum, a KS or p-norm aggregate (eq. 22), its time integral
    (trapezoid rule on the output grid: the bounds are then in the response's units times
    s), optionally in a window."""
    response: Name
    upper: Finite | None = None
    lower: Finite | None = None
    over: Literal["every_step", "max", "ks", "pnorm", "integral"] = "every_step"
    parameter: Positive | None = None       # KS rho (default 100) or p-norm P (default 50)
    window: Pair | None = None

    @field_validator("parameter")
    @classmethod
    def _parameter_taken(cls, v, info):
        if v is not None and info.data.get("over") == "integral":
            raise ValueError("is not taken by over = 'integral' (the trapezoid rule has no "
                             "parameter; only 'ks' and 'pnorm' take one): remove it")
        return v

    @model_validator(mode="after")
    def _bound(self):
        if self.upper is None and self.lower is None:
            raise ValueError(f"constraint on {self.response!r} needs upper or lower")
        return self


class Objective(_Strict):
    """The response to minimize (a scalar one: mass, or an aggregate of a history: its
    maximum, KS or p-norm, final value or time integral)."""
    response: Name
    over: Literal["max", "ks", "pnorm", "final", "integral"] = "max"


class TimeSettings(_Strict):
    """Generalized-alpha settings: step h (s, or "auto": steps chosen by the error tolerance
    tol / rtol, outputs on the grid of spacing `output`), horizon t_end (s; rounded to a
    whole number of steps, the change reported), spectral radius rho_inf, start 'rest' (the rigid velocity
    field the drives impose) or 'static' (static equilibrium at t = 0, at rest), Newton
    strategy newton ('auto', 'full', 'reuse': see flexmbs.analysis.simulate)."""
    t_end: Positive
    h: Positive | Literal["auto"] = 5e-4
    rho_inf: Annotated[float, NoBool, Field(ge=0.0, le=1.0)] = 0.5
    start: Literal["rest", "static"] = "rest"
    newton: Literal["auto", "full", "reuse"] = "auto"
    reuse_jacobian: bool | None = None      # deprecated: true is newton = "reuse", false "full"
    #: with h = "auto" (error-controlled steps, flexmbs.analysis.adaptive): the spacing (s) of the
    #: response grid the outputs are interpolated onto (default 5e-4; `--set time.h=auto`
    #: keeps the case's h here), the tolerance of the responses' error, absolute `tol` (the
    #: responses' units) and/or relative `rtol` (to each response's largest magnitude), and
    #: the longest step h_max (s; default t_end / 20)
    output: Positive | None = None
    tol: Positive | None = None
    rtol: Positive | None = None
    h_max: Positive | None = None

    @model_validator(mode="after")
    def _adaptive_keys(self):
        keys = [k for k in ("output", "tol", "rtol", "h_max") if getattr(self, k) is not None]
        if not self.adaptive and keys:
            raise ValueError(f"{', '.join(keys)} only with h = \"auto\" (error-controlled "
                             f"steps), got h = {self.h}")
        if self.adaptive and self.tol is None and self.rtol is None:
            raise ValueError('h = "auto" needs a tolerance of the responses\' error: tol '
                             '(absolute, in the responses\' units) and/or rtol (relative)')
        return self

    @property
    def adaptive(self):
        """True with h = "auto": error-controlled steps (flexmbs.analysis.adaptive)."""
        return isinstance(self.h, str)

    @property
    def grid_h(self):
        """The spacing (s) of the response grid t_j = j grid_h: h, or `output` (default 5e-4)
        with h = "auto"."""
        if self.adaptive:
            return self.output if self.output is not None else 5e-4
        return self.h

    @property
    def newton_strategy(self):
        """The Newton strategy that runs: newton, or the one the deprecated reuse_jacobian
        names (true: 'reuse', false: 'full') when newton is left at 'auto'."""
        if self.reuse_jacobian is not None and self.newton == "auto":
            return "reuse" if self.reuse_jacobian else "full"
        return self.newton

    @model_validator(mode="after")
    def _newton_alias(self):
        if self.reuse_jacobian is not None:
            alias = "reuse" if self.reuse_jacobian else "full"
            if self.newton not in ("auto", alias):
                raise ValueError(f"reuse_jacobian = {str(self.reuse_jacobian).lower()} (deprecated: "
                                 f"newton = {alias!r}) contradicts newton = {self.newton!r}: "
                                 "give newton alone")
        return self


class SolverSettings(_Strict):
    """Newton's, the linear solver's and the run's settings, [solver] (the fields of
    flexmbs.analysis.settings.SimulationSettings that [time] does not hold; same defaults):
    Newton tolerance tol, iterations max_iter, step halvings max_cuts, linear_solver ('auto',
    'dense', 'klu'), the scalings kscale and penalty of eq. (1) (default: automatic), polish,
    memory_limit (bytes; default: FLEXMBS_MEMORY_LIMIT, else the memory available), the
    validity checks' mode and limits (unset: flexmbs.analysis.validity.ValidityLimits's)."""
    tol: Positive = 1e-10
    max_iter: Annotated[int, NoBool, Field(ge=1)] = 20
    max_cuts: Annotated[int, NoBool, Field(ge=0)] = 6
    linear_solver: Literal["auto", "dense", "klu"] = "auto"
    kscale: Positive | None = None
    penalty: Positive | None = None
    polish: bool = False
    memory_limit: Positive | None = None
    validity: Literal["warn", "error", "off"] = "warn"
    strain_warn: Positive | None = None
    strain_fail: Positive | None = None
    drift_warn: Positive | None = None
    drift_fail: Positive | None = None
    energy_warn: Positive | None = None
    energy_fail: Positive | None = None

    @model_validator(mode="after")
    def _limits_ordered(self):
        for kind in ("strain", "drift", "energy"):
            warn, fail = getattr(self, f"{kind}_warn"), getattr(self, f"{kind}_fail")
            if warn is not None and fail is not None and warn > fail:
                raise ValueError(f"{kind}_warn = {warn:g} is above {kind}_fail = {fail:g}: "
                                 "the warning limit must not exceed the failure limit")
        return self


#: The fields of an [[initial.beams]] entry given at its stations.
INITIAL_FIELDS = ("deflection", "deflection_rate", "axial", "axial_rate")


class InitialBeam(_Strict):
    """A beam's initial deflection and its rate, given at stations: `deflection` (m) and
    `deflection_rate` (m/s) normal to the beam's axis (positive on its left, from `from` to
    `to`), `axial` (m) and `axial_rate` (m/s) along it (positive towards `to`), at the
    fractions `s` of its length (default: at its nodes, from `from`; then one value per node).
    Between the stations a cubic spline (scipy's CubicSpline, not-a-knot; a line through 2
    stations) gives each node's value and slope: the node moves by the deflection along the
    axis' normal and by the axial value along the axis, and turns by atan(slope of the
    deflection) (its rate by rate' / (1 + slope^2))."""
    body: Name
    s: Annotated[list[Annotated[float, NoBool, Field(ge=0.0, le=1.0, allow_inf_nan=False)]],
                 Field(min_length=2)] | None = None
    deflection: Annotated[list[Finite], Field(min_length=2)] | None = None
    deflection_rate: Annotated[list[Finite], Field(min_length=2)] | None = None
    axial: Annotated[list[Finite], Field(min_length=2)] | None = None
    axial_rate: Annotated[list[Finite], Field(min_length=2)] | None = None

    @model_validator(mode="after")
    def _values(self):
        given = [k for k in INITIAL_FIELDS if getattr(self, k) is not None]
        if not given:
            raise ValueError(f"initial beam {self.body!r}: give deflection, deflection_rate, "
                             "axial and/or axial_rate")
        if self.s is not None:
            if any(b <= a for a, b in zip(self.s, self.s[1:])):
                raise ValueError(f"initial beam {self.body!r}: s = {self.s} must increase "
                                 "strictly")
            for k in given:
                if len(getattr(self, k)) != len(self.s):
                    raise ValueError(f"initial beam {self.body!r}: {k} has "
                                     f"{len(getattr(self, k))} values for {len(self.s)} "
                                     "stations s")
        return self


class InitialState(_Strict):
    """An initial elastic deformation and velocity, on top of the assembled configuration
    and of the rigid velocity field the drives impose (the 'rest' start):

    static_loads  the static equilibrium at t = 0 under these loads (and gravity), with the
                  drives at their initial positions, instead of the case's loads: the
                  deformation a preload leaves, released at t = 0 (its law, if any, is
                  taken at t = 0). It depends on the design: design gradients are refused.
    beams         given deflections and rates of beams (InitialBeam), independent of the
                  design: design gradients stay exact.
    The deformed state must satisfy the joints (a clamped end neither moves nor turns)."""
    static_loads: Annotated[list[Load], Field(min_length=1)] | None = None
    beams: list[InitialBeam] = []

    @model_validator(mode="after")
    def _something(self):
        if self.static_loads is None and not self.beams:
            raise ValueError("[initial] needs static_loads or beams")
        if self.static_loads is not None and any(b.deflection is not None or b.axial is not None
                                                 for b in self.beams):
            raise ValueError("[initial]: the deformation comes either from static_loads or from "
                             "beams' deflection and axial, not both (beams may add "
                             "deflection_rate and axial_rate)")
        return self


class CaseInfo(_Strict):
    name: Name = "mechanism"
    description: str | None = None
    source: str | None = None


# ----------------------------------------------------------------------------- the whole
class Description(_Strict):
    """A mechanism and its sizing problem; see the module docstring and docs/case-format.md."""
    case: CaseInfo = CaseInfo()
    points: dict[Name, Pair]
    materials: dict[Name, MaterialSpec] = {}
    design: list[DesignVariable] = []
    bodies: Annotated[list[Body], Field(min_length=1)]
    joints: list[Joint] = []
    drives: list[Drive] = []
    paths: list[Path] = []
    loads: list[Load] = []
    springs: list[SpringDamper] = []
    gravity: Pair = [0.0, 0.0]
    responses: list[Response] = []
    objective: Objective | None = None
    constraints: list[Constraint] = []
    time: TimeSettings
    solver: SolverSettings = SolverSettings()
    initial: InitialState | None = None
    #: [optimize]: the method, optimizer and options of `flexmbs optimize` and the
    #: Problem-level entry points when not told otherwise (flexmbs.model.options)
    optimize: OptimizeSection | None = None

    @field_validator("points")
    @classmethod
    def _some_points(cls, v):
        if not v:
            raise ValueError("at least one point is needed")
        return v

    @model_validator(mode="after")
    def check_references(self):
        """Every name used is defined, once."""
        def unique(kind, names):
            seen = set()
            for n in names:
                if n in seen:
                    raise ValueError(f"two {kind} are called {n!r}")
                seen.add(n)
            return seen
        bodies = {b.name: b for b in self.bodies}
        unique("bodies", [b.name for b in self.bodies])
        if GROUND in bodies:
            raise ValueError(f"body name {GROUND!r} is reserved for the ground (joints and "
                             f"frames name it); rename the body")
        if not self.joints and not self.drives and not any(
                isinstance(b, Rigid) for b in self.bodies):
            raise ValueError("the case has no [[joints]], no [[drives]] and no rigid body: "
                             "nothing holds or moves its bodies (the constraint equations "
                             "are empty); give [[joints]] (e.g. a pin to the ground) or "
                             "[[drives]]")
        dvars = unique("design variables", [v.name for v in self.design])
        responses = unique("responses", [r.name for r in self.responses])
        joints = unique("joints", [j.name for j in self.joints if j.name is not None])
        drives = unique("drives", [d.name for d in self.drives if d.name is not None])
        pts = set(self.points)

        def point(where, p):
            if p not in pts:
                raise ValueError(f"{where}: unknown point {p!r} (points: {', '.join(sorted(pts))})")

        def body_point(where, b, p, beam_only=False):
            if isinstance(p, Station):
                beam_only = True
            if b not in bodies:
                raise ValueError(f"{where}: unknown body {b!r} (bodies: {', '.join(bodies)})")
            if beam_only and not isinstance(bodies[b], Beam):
                raise ValueError(f"{where}: body {b!r} is not a beam")
            if isinstance(p, Station):
                return
            point(where, p)
            if p not in body_points(bodies[b]):
                raise ValueError(f"{where}: body {b!r} has no point {p!r} (its points: "
                                 f"{', '.join(body_points(bodies[b]))})")

        for b in self.bodies:
            where = f"body {b.name!r}"
            if isinstance(b, Beam):
                point(where, b.start)
                point(where, b.end)
                if b.start == b.end:
                    raise ValueError(f"{where}: from and to are the same point {b.start!r}")
                if b.material is not None and b.material not in self.materials:
                    raise ValueError(f"{where}: unknown material {b.material!r} (materials: "
                                     f"{', '.join(self.materials) or 'none defined'})")
                for dim, v in b.section.dimensions().items():
                    for item in (v if isinstance(v, list) else [v]):
                        if isinstance(item, str) and item not in dvars:
                            raise ValueError(f"{where}: section {dim} = {item!r} is not a design "
                                             f"variable (design variables: "
                                             f"{', '.join(sorted(dvars)) or 'none'})")
                    if isinstance(v, list) and not 1 <= len(v) <= b.elements \
                            or isinstance(v, list) and b.elements % len(v):
                        raise ValueError(f"{where}: section {dim} has {len(v)} entries; give one "
                                         f"per element or per equal group ({b.elements} elements)")
            elif isinstance(b, Rigid):
                for p in b.points:
                    point(where, p)
                if b.center is not None:
                    point(where, b.center)
            else:
                point(where, b.at)
                if b.on is not None:
                    body_point(where, b.on, b.at)
        for k, j in enumerate(self.joints):
            where = f"joint {j.name or k + 1} ({j.type})"
            for b in (j.bodies or [j.body]):
                if j.type == "prismatic" and b == GROUND:
                    point(where, j.at)
                    continue
                body_point(where, b, j.at)
        for k, d in enumerate(self.drives):
            where = f"drive {d.name or k + 1}"
            body_point(where, d.body, d.at)
            if d.relative_to is not None:
                body_point(where, d.relative_to, d.at)
            if d.law.type == "reference" and not self.paths:
                raise ValueError(f"{where}: law 'reference' needs [[paths]] for the rigid reference")
        for b in self.bodies:
            if isinstance(b, PointMass) and b.on is None and b.inertia == 0.0:
                held = any(j.type in ("clamp", "weld", "slider", "prismatic")
                           and b.name in ([j.body] if j.body is not None else j.bodies)
                           for j in self.joints) or any(
                    d.type == "rotation" and b.name in (d.body, d.relative_to)
                    for d in self.drives)
                if not held:
                    raise ValueError(
                        f"body {b.name!r}: a point mass of its own (no on) with inertia = 0 "
                        f"has a rotation that no mass and no joint holds (a pin or a hinge "
                        f"leaves it free); give inertia > 0 (kg m^2), or on = BODY to add the "
                        f"mass to that body's node at {b.at!r}, or a weld")
        xs, ys = [v[0] for v in self.points.values()], [v[1] for v in self.points.values()]
        size = math.hypot(max(xs) - min(xs), max(ys) - min(ys)) if xs else 0.0
        size = size if 0.0 < size < math.inf else 1.0
        # beyond the core's step count, Mechanism refuses the horizon itself (naming t_end, h)
        steps_fit = self.time.t_end / self.time.grid_h <= MAX_STEPS
        for k, p in enumerate(self.paths):
            body_point(f"path {k + 1}", p.body, p.at)
            for key in ("x", "y") if steps_fit else ():
                try:
                    reach = law_bound(getattr(p, key), self.time.t_end)
                except OverflowError:       # a power of t_end beyond double precision
                    reach = math.inf
                if not reach <= PATH_REACH * size:
                    raise ValueError(
                        f"path {k + 1}: {key} moves the point by up to {reach:.3g} m "
                        f"over t_end = {self.time.t_end:g} s, more than {PATH_REACH:g} times "
                        f"the mechanism's size ({size:.3g} m, the diagonal of its points' box); "
                        f"give a motion within {PATH_REACH * size:.3g} m")
        for k, ld in enumerate(self.loads):
            body_point(f"load {k + 1}", ld.body, ld.at)
        if self.initial is not None:
            if self.time.start != "rest":
                raise ValueError(f"[initial] gives the initial state: it goes with time.start "
                                 f"= 'rest' (the default), not {self.time.start!r}")
            for k, ld in enumerate(self.initial.static_loads or []):
                body_point(f"initial.static_loads {k + 1}", ld.body, ld.at)
            seen = set()
            for b in self.initial.beams:
                where = f"initial beam {b.body!r}"
                if b.body not in bodies or not isinstance(bodies[b.body], Beam):
                    beams = [n for n, x in bodies.items() if isinstance(x, Beam)]
                    raise ValueError(f"{where}: not a beam (beams: {', '.join(beams)})")
                if b.body in seen:
                    raise ValueError(f"{where}: given twice")
                seen.add(b.body)
                nodes = bodies[b.body].elements * bodies[b.body].order + 1
                for key in INITIAL_FIELDS:
                    v = getattr(b, key)
                    if b.s is None and v is not None and len(v) != nodes:
                        raise ValueError(f"{where}: {key} has {len(v)} values; without s it "
                                         f"needs one per node ({nodes}: "
                                         f"{bodies[b.body].elements} elements of order "
                                         f"{bodies[b.body].order})")
        for k, s in enumerate(self.springs):
            for b, p in zip(s.bodies, s.at):
                body_point(f"spring {k + 1}", b, p)
        for r in self.responses:
            where = f"response {r.name!r}"
            if isinstance(r, Deviation):
                for t in r.terms:
                    body_point(where, t.body, t.at)
                    if t.relative_to is not None:
                        body_point(where, t.relative_to.body, t.relative_to.at)
                    if t.frame != "ground" and t.frame not in bodies:
                        raise ValueError(f"{where}: frame {t.frame!r} is neither 'ground' nor a body")
            elif isinstance(r, Torque):
                if r.drive not in drives:
                    raise ValueError(f"{where}: unknown drive {r.drive!r} (named drives: "
                                     f"{', '.join(sorted(drives)) or 'none'})")
            elif isinstance(r, Reaction):
                if r.joint not in joints:
                    raise ValueError(f"{where}: unknown joint {r.joint!r} (named joints: "
                                     f"{', '.join(sorted(joints)) or 'none'})")
                j = next(j for j in self.joints if j.name == r.joint)
                if j.type == "prismatic" and GROUND not in j.bodies and r.component != "magnitude":
                    raise ValueError(f"{where}: component = {r.component!r} of the reaction of "
                                     f"prismatic joint {r.joint!r} between two bodies is not "
                                     f"available (its normal turns with body {j.bodies[0]!r}); "
                                     f"use component = 'magnitude' (the normal force)")
            elif isinstance(r, (Deflection, Strain)) or getattr(r, "at", None) is not None:
                body_point(where, r.at.body, r.at)
            else:
                for b in (r.bodies or []):
                    if b not in bodies or not isinstance(bodies[b], Beam):
                        raise ValueError(f"{where}: {b!r} is not a beam")
        layout = design_layout(self)   # element-wise variables: their beams and groups agree
        self._check_start_range(layout)
        if self.objective is not None and self.objective.response not in responses:
            raise ValueError(f"objective: unknown response {self.objective.response!r} "
                             f"(responses: {', '.join(sorted(responses)) or 'none'})")
        for c in self.constraints:
            if c.response not in responses:
                raise ValueError(f"constraint: unknown response {c.response!r} "
                                 f"(responses: {', '.join(sorted(responses)) or 'none'})")
        return self

    def _check_start_range(self, layout):
        """[optimize.multistart] start_range: one value per design variable (an element-wise
        variable is one per element or group: `layout`, design_layout's)."""
        rng = None if self.optimize is None else self.optimize.multistart.start_range
        if rng is None:
            return
        n = sum(layout[v.name][0] for v in self.design)
        if len(rng[0]) != n:
            names = ", ".join(v.name if layout[v.name][0] == 1 else
                              f"{v.name} x {layout[v.name][0]}" for v in self.design)
            raise ValueError(f"optimize.multistart.start_range: the lower and the upper design "
                             f"must have one value per design variable ({n}: {names}), got "
                             f"{len(rng[0])}")


def design_layout(description):
    """How each design variable maps onto the elements: {name: (components, {beam: [component
    of each element (0-based)]})}. A scalar variable has one component; an element-wise one
    (`DesignVariable.elementwise`) one per element of the beams naming it, or one per group.
    ValueError, naming the variable, the key and the beams, when an element-wise variable is
    named by no beam, inside a list of per-element entries, by beams with different numbers of
    elements, or has groups that do not cover the elements exactly once."""
    users = {v.name: [] for v in description.design}
    listed = {}
    for b in description.bodies:
        if not isinstance(b, Beam):
            continue
        for dim, spec in b.section.dimensions().items():
            if isinstance(spec, str) and spec in users:
                if all(u.name != b.name for u in users[spec]):
                    users[spec].append(b)
            elif isinstance(spec, list):
                for item in spec:
                    if isinstance(item, str):
                        listed.setdefault(item, (b.name, dim))
    out = {}
    for v in description.design:
        beams = users[v.name]
        if not v.elementwise:
            out[v.name] = (1, {b.name: [0] * b.elements for b in beams})
            continue
        where = f"design variable {v.name!r} ({'groups' if v.groups is not None else 'per_element'})"
        if v.name in listed:
            b, dim = listed[v.name]
            raise ValueError(f"{where}: body {b!r} names it inside the list section.{dim}; an "
                             f"element-wise variable sizes the whole beam: write {dim} = "
                             f"\"{v.name}\"")
        if not beams:
            raise ValueError(f"{where}: no beam section names it, so its number of components "
                             f"is unknown; name it in a beam's section (e.g. diameter = "
                             f"\"{v.name}\") or drop per_element/groups")
        counts = {b.name: b.elements for b in beams}
        if len(set(counts.values())) > 1:
            raise ValueError(f"{where}: the beams sharing it have different numbers of elements ("
                             + ", ".join(f"{k!r}: {n}" for k, n in counts.items())
                             + "); an element-wise variable links beams element by element: give "
                             "them the same elements or use one variable per beam")
        n = beams[0].elements
        if v.groups is None:
            comp = list(range(n))
            ncomp = n
        else:
            comp = [-1] * n
            for k, g in enumerate(v.groups):
                for e in g:
                    if e > n:
                        raise ValueError(f"{where}: groups = {v.groups} names element {e}, but "
                                         f"body {beams[0].name!r} has {n} elements (numbered 1 "
                                         f"to {n} from its 'from' end)")
                    comp[e - 1] = k
            missing = [e + 1 for e in range(n) if comp[e] < 0]
            if missing:
                raise ValueError(f"{where}: groups = {v.groups} leave element(s) "
                                 f"{missing} of body {beams[0].name!r} ({n} elements) in no "
                                 f"group; every element belongs to exactly one group")
            ncomp = len(v.groups)
        out[v.name] = (ncomp, {b.name: list(comp) for b in beams})
    return out


def body_points(body):
    """The named points a body has a node at."""
    if isinstance(body, Beam):
        return [body.start, body.end]
    if isinstance(body, Rigid):
        pts = list(body.points)
        if body.center is not None and body.center not in pts:
            pts.insert(0, body.center)
        return pts
    return [body.at]
