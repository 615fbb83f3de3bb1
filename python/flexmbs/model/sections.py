"""Materials and cross sections: EA, kGA, EI, rhoA, rhoI and their derivatives.

Shear correction factors are Cowper's (J. Appl. Mech. 33, 1966): solid circle
6(1+nu)/(7+6nu), hollow circle 6(1+nu)(1+m^2)^2/((7+6nu)(1+m^2)^2+(20+12nu)m^2)
with m = inner/outer diameter, rectangle 10(1+nu)/(12+11nu).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flexmbs.errors import ModelError

__all__ = ["Material", "Section", "Circle", "Tube", "Rectangle", "GivenSection",
           "section_properties", "real_number", "whole_number", "has_complex"]


def _is_real(value):
    """True for an int, a float or a numpy real scalar (0-d array too); False for a bool."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, np.ndarray) and value.ndim == 0 and value.dtype.kind in "iuf":
        return True
    return isinstance(value, (int, float, np.integer, np.floating))


def has_complex(value):
    """True when `value` (a number or an array-like) holds a complex number, even with a zero
    imaginary part: numpy would cast it to float with a warning only, dropping the
    imaginary part."""
    if isinstance(value, (complex, np.complexfloating)):
        return True
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        return False
    if a.dtype.kind == "c":
        return True
    if a.dtype == object:
        return any(isinstance(v, (complex, np.complexfloating)) or
                   (isinstance(v, np.ndarray) and v.dtype.kind == "c") for v in a.ravel())
    return False


def real_number(name, value, *, positive=False, nonnegative=False):
    """`value` as a finite float, or a ModelError naming `name`, the value and what is allowed.

    Accepts int, float and numpy real scalars; refuses bools, strings, None, arrays, NaN and
    infinities (and values <= 0 with positive=True, < 0 with nonnegative=True).
    """
    want = ("a positive finite number" if positive else
            "a finite number >= 0" if nonnegative else "a finite number")
    if not _is_real(value):
        raise ModelError(f"{name} must be {want}, got {value!r} ({type(value).__name__})")
    v = float(value)
    if not math.isfinite(v) or (positive and v <= 0) or (nonnegative and v < 0):
        raise ModelError(f"{name} must be {want}, got {value!r}")
    return v


def whole_number(name, value, minimum=None):
    """`value` as an int (int or numpy integer, not a bool, not 2.5 or "5"), >= minimum."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ModelError(f"{name} must be an integer{'' if minimum is None else f' >= {minimum}'}, "
                         f"got {value!r} ({type(value).__name__})")
    if minimum is not None and value < minimum:
        raise ModelError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _positive(name, value):
    if _is_real(value) and not (math.isfinite(float(value)) and float(value) > 0):
        raise ModelError(f"{name} must be positive and finite, got {value!r}")
    return real_number(name, value, positive=True)


@dataclass(frozen=True)
class Material:
    """Linear elastic isotropic material (SI units), optionally with Kelvin–Voigt damping.

    Parameters
    ----------
    E : Young's modulus (Pa).
    nu : Poisson's ratio.
    rho : density (kg/m^3).
    damping_time : the Kelvin–Voigt (retardation) time eta (s), default 0 (undamped):
        every stress resultant of a beam gets a viscous part eta D dGamma/dt (D = EA, kGA,
        EI; fortran/beam2d.f90), stiffness-proportional damping whose modal damping ratio
        at the circular frequency omega is zeta = eta omega / 2.
    damping_ratio, damping_frequency : the alternative to `damping_time`: the damping
        ratio zeta (e.g. 0.02) at the frequency f (Hz, e.g. a beam's first bending
        frequency), giving eta = 2 zeta / (2 pi f). Both or neither, and not with
        `damping_time`.

    Notes
    -----
    Damping has no static effect (the forces depend on the strain rates) and does not
    change the stress responses, which are the elastic D Gamma.
    """
    E: float
    nu: float
    rho: float
    damping_time: float = 0.0
    damping_ratio: float | None = None
    damping_frequency: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "E", _positive("Material.E", self.E))
        object.__setattr__(self, "rho", _positive("Material.rho", self.rho))
        nu = real_number("Material.nu", self.nu)
        if not (-1.0 < nu < 0.5):
            raise ModelError(f"Material.nu must lie in (-1, 0.5), got {self.nu!r}")
        object.__setattr__(self, "nu", nu)
        eta = real_number("Material.damping_time", self.damping_time, nonnegative=True)
        if (self.damping_ratio is None) != (self.damping_frequency is None):
            raise ModelError(f"Material: give damping_ratio and damping_frequency together, got "
                             f"damping_ratio={self.damping_ratio!r}, "
                             f"damping_frequency={self.damping_frequency!r}")
        if self.damping_ratio is not None:
            if eta != 0.0:
                raise ModelError(f"Material: give either damping_time (got {self.damping_time!r}) "
                                 "or damping_ratio with damping_frequency, not both")
            zeta = real_number("Material.damping_ratio", self.damping_ratio, nonnegative=True)
            freq = _positive("Material.damping_frequency (Hz)", self.damping_frequency)
            object.__setattr__(self, "damping_ratio", zeta)
            object.__setattr__(self, "damping_frequency", freq)
            eta = 2.0 * zeta / (2.0 * math.pi * freq)
        object.__setattr__(self, "damping_time", eta)

    @property
    def G(self):
        """Shear modulus E / (2 (1 + nu))."""
        return self.E / (2.0 * (1.0 + self.nu))


#: Sizes (m) of a section whose second moment of area (size^4) and its products with a
#: material's E or rho are normal doubles, roughly.
SIZE_RANGE = (1e-70, 1e70)


class Section:
    """A cross section; `properties(material)` gives EA, kGA, EI, rhoA, rhoI."""

    #: names of the section's size parameters (design variables may refer to them)
    parameters: tuple = ()

    def area_inertia_shear(self, nu):
        """Return (A, I, k) and their derivatives d/dparam, arrays of shape (nparam,)."""
        raise NotImplementedError

    def _values(self, nu):
        """`area_inertia_shear`, or a ModelError naming the section when its sizes overflow
        (1e308) or underflow (1e-300) double precision on the way."""
        try:
            with np.errstate(over="raise", divide="raise", invalid="raise"):
                return self.area_inertia_shear(nu)
        except (OverflowError, ZeroDivisionError, FloatingPointError):
            raise ModelError(self._out_of_range()) from None

    def _out_of_range(self, values=None):
        shown = "" if values is None else (
            ": [EA, kGA, EI, rhoA, rhoI] = [" + ", ".join(f"{v:.3g}" for v in values) + "]")
        return (f"{self!r}: its sizes overflow or underflow double precision (area, second "
                f"moment of area and their derivatives must be positive finite numbers{shown}); "
                f"sizes must lie roughly between {SIZE_RANGE[0]:g} and {SIZE_RANGE[1]:g} m")

    def _checked(self, values):
        """`values` ([EA, kGA, EI, rhoA, rhoI], or their derivatives: 2-d) when finite, and
        for the values themselves positive; else ModelError naming the section."""
        values = np.asarray(values, float)
        bad = not np.all(np.isfinite(values))
        if values.ndim == 1:
            bad = bad or bool(np.any(values <= 0.0))
        if bad:
            raise ModelError(self._out_of_range(values if values.ndim == 1 else None))
        return values

    def properties(self, material: Material):
        """Stiffness and inertia per unit length: array [EA, kGA, EI, rhoA, rhoI]; ModelError
        when a size overflows or underflows (they must be positive and finite)."""
        a, i, k, _, _, _ = self._values(material.nu)
        with np.errstate(over="ignore", under="ignore"):
            return self._checked([material.E * a, k * material.G * a, material.E * i,
                                  material.rho * a, material.rho * i])

    def property_derivatives(self, material: Material):
        """d[EA, kGA, EI, rhoA, rhoI]/d(param), shape (5, nparam); ModelError as
        `properties` when the section's sizes overflow or underflow."""
        self.properties(material)
        a, i, k, da, di, dk = self._values(material.nu)
        E, G, rho = material.E, material.G, material.rho
        with np.errstate(over="ignore", invalid="ignore", under="ignore"):
            return self._checked(np.array([E * da, G * (dk * a + k * da), E * di, rho * da,
                                           rho * di]))


@dataclass(frozen=True)
class Circle(Section):
    """Solid circle of diameter d (m)."""
    d: float
    parameters = ("d",)

    def __post_init__(self):
        object.__setattr__(self, "d", _positive("Circle diameter d", self.d))

    def area_inertia_shear(self, nu):
        d = self.d
        k = 6 * (1 + nu) / (7 + 6 * nu)
        a = math.pi / 4 * d * d
        i = math.pi / 64 * d ** 4
        return a, i, k, np.array([math.pi / 2 * d]), np.array([math.pi / 16 * d ** 3]), np.zeros(1)


@dataclass(frozen=True)
class Tube(Section):
    """Hollow circle: outer diameter d (m) and wall thickness t (m), 0 < t <= d/2.

    `Tube.with_wall_ratio(d, 0.1)` gives the paper's robot tube (t = 0.1 d); its
    single parameter is then d, with the wall following it.
    """
    d: float
    t: float
    wall_ratio: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "d", _positive("Tube outer diameter d", self.d))
        object.__setattr__(self, "t", _positive("Tube wall thickness t", self.t))
        if self.wall_ratio is not None:
            object.__setattr__(self, "wall_ratio", real_number("Tube wall ratio", self.wall_ratio))
        if self.t > 0.5 * self.d:
            raise ModelError(f"Tube wall thickness t = {self.t} is larger than the radius {0.5 * self.d}")

    @property
    def parameters(self):
        return ("d",) if self.wall_ratio is not None else ("d", "t")

    @classmethod
    def with_wall_ratio(cls, d, ratio):
        """Tube whose wall is `ratio` times the outer diameter."""
        d = _positive("Tube outer diameter d", d)
        if not (_is_real(ratio) and 0 < ratio <= 0.5):
            raise ModelError(f"Tube wall ratio must lie in (0, 0.5], got {ratio!r}")
        ratio = float(ratio)
        return cls(d=d, t=ratio * d, wall_ratio=ratio)

    def area_inertia_shear(self, nu):
        d, t = self.d, self.t
        di = d - 2 * t
        m = di / d
        a = math.pi / 4 * (d * d - di * di)
        i = math.pi / 64 * (d ** 4 - di ** 4)
        s = (1 + m * m) ** 2
        num = 6 * (1 + nu) * s
        den = (7 + 6 * nu) * s + (20 + 12 * nu) * m * m
        k = num / den
        # derivatives with respect to (d, t) at fixed t / fixed d
        dm_dd = 2 * t / d ** 2
        dm_dt = -2 / d
        ds_dm = 4 * m * (1 + m * m)
        dk_dm = (6 * (1 + nu) * ds_dm * den - num * ((7 + 6 * nu) * ds_dm + 2 * (20 + 12 * nu) * m)) / den ** 2
        da = np.array([math.pi / 2 * (d - di), math.pi * di])
        dI = np.array([math.pi / 16 * (d ** 3 - di ** 3), math.pi / 8 * di ** 3])
        dk = np.array([dk_dm * dm_dd, dk_dm * dm_dt])
        if self.wall_ratio is not None:
            # t = ratio d: total derivative along d (m is then constant, dk = 0)
            r = self.wall_ratio
            da = np.array([da[0] + r * da[1]])
            dI = np.array([dI[0] + r * dI[1]])
            dk = np.array([dk[0] + r * dk[1]])
        return a, i, k, da, dI, dk


@dataclass(frozen=True)
class Rectangle(Section):
    """Solid rectangle: width b (out of plane) and height h (in the plane of bending), m."""
    b: float
    h: float
    parameters = ("b", "h")

    def __post_init__(self):
        object.__setattr__(self, "b", _positive("Rectangle width b", self.b))
        object.__setattr__(self, "h", _positive("Rectangle height h", self.h))

    def area_inertia_shear(self, nu):
        b, h = self.b, self.h
        k = 10 * (1 + nu) / (12 + 11 * nu)
        return (b * h, b * h ** 3 / 12, k, np.array([h, b]), np.array([h ** 3 / 12, b * h * h / 4]),
                np.zeros(2))


@dataclass(frozen=True)
class GivenSection(Section):
    """Section given by its values per unit length: EA, kGA, EI (N, N, N m^2), rhoA (kg/m), rhoI (kg m)."""
    EA: float
    kGA: float
    EI: float
    rhoA: float
    rhoI: float = 0.0
    parameters = ()

    def __post_init__(self):
        for name in ("EA", "kGA", "EI", "rhoA"):
            object.__setattr__(self, name, _positive(f"GivenSection.{name}", getattr(self, name)))
        object.__setattr__(self, "rhoI", real_number("GivenSection.rhoI", self.rhoI, nonnegative=True))

    def properties(self, material=None):
        return np.array([self.EA, self.kGA, self.EI, self.rhoA, self.rhoI], dtype=float)

    def property_derivatives(self, material=None):
        return np.zeros((5, 0))


def section_properties(section: Section, material: Material | None):
    """[EA, kGA, EI, rhoA, rhoI] of a section made of a material."""
    if not isinstance(section, Section):
        raise ModelError(f"section must be a flexmbs Section (Circle, Tube, Rectangle, "
                         f"GivenSection), got {section!r}")
    if isinstance(section, GivenSection):
        return section.properties()
    if material is None:
        raise ModelError(f"section {section!r} needs a material")
    if not isinstance(material, Material):
        raise ModelError(f"material must be a flexmbs Material, got {material!r}")
    return section.properties(material)
