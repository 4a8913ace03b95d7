"""How the report writes numbers: lengths in µm or mm, angles in µrad, times, ``value ± u``.

Every function returns plain text (escaped by the templates) except
:func:`plus_minus` and the parameter labels, which are :class:`~markupsafe.Markup`
built here from numbers only.
"""

from __future__ import annotations

import math
import re

import numpy as np
from markupsafe import Markup

__all__ = ["PARAM_LABELS", "PARAM_UNITS", "finite", "length", "natural", "num", "parts", "percent", "plus_minus",
           "secs", "truthy", "um", "urad"]

#: Symbol of each sensor parameter (thesis notation).
PARAM_LABELS = {name: Markup(label) for name, label in {
    "x0": "x<sub>0</sub>", "y0": "y<sub>0</sub>", "z0": "z<sub>0</sub>", "omega": "&omega;", "phi": "&phi;",
    "kappa": "&kappa;", "xi_h": "&xi;<sub>H</sub>", "eta_h": "&eta;<sub>H</sub>", "c": "c", "k1": "k<sub>1</sub>",
    "k2": "k<sub>2</sub>", "k3": "k<sub>3</sub>", "p1": "p<sub>1</sub>", "p2": "p<sub>2</sub>"}.items()}

#: Unit of each sensor parameter.
PARAM_UNITS = {name: Markup(unit) for name, unit in {
    "x0": "mm", "y0": "mm", "z0": "mm", "omega": "rad", "phi": "rad", "kappa": "rad", "xi_h": "mm", "eta_h": "mm",
    "c": "mm", "k1": "mm<sup>-2</sup>", "k2": "mm<sup>-4</sup>", "k3": "mm<sup>-6</sup>", "p1": "mm<sup>-1</sup>",
    "p2": "mm<sup>-1</sup>"}.items()}


def finite(x) -> bool:
    """Whether ``x`` is a finite real number (not a bool, a string or None).

    >>> finite(1.5), finite(float("nan")), finite(True), finite("1")
    (True, False, False, False)
    """
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and math.isfinite(x)


def num(x, fmt: str = ".4g", unit: str = "") -> str:
    """``x`` formatted (``"n/a"`` unless finite), never as ``-0``.

    >>> num(-0.00001, ".2f", "mm"), num(None)
    ('0.00 mm', 'n/a')
    """
    if not finite(x):
        return "n/a"
    text = f"{x:{fmt}}"
    if text.startswith("-") and not text.strip("-0.,"):
        text = text[1:]
    return text + (f" {unit}" if unit else "")


def um(mm, digits: int = 1) -> str:
    """A length given in mm, written in µm.

    >>> um(0.0471), um(0.00123, 2)
    ('47.1 µm', '1.23 µm')
    """
    return num(mm * 1000 if finite(mm) else mm, f".{digits}f", "µm")


def length(mm) -> str:
    """A length in µm below 1 mm, else in mm.

    >>> length(0.25), length(3.14159)
    ('250.0 µm', '3.142 mm')
    """
    if not finite(mm):
        return "n/a"
    return um(mm) if abs(mm) < 1 else num(mm, ".3f", "mm")


def urad(rad) -> str:
    """An angle given in rad, written in µrad.

    >>> urad(2.1e-4)
    '210.0 µrad'
    """
    return num(rad * 1e6 if finite(rad) else rad, ".1f", "µrad")


def parts(n) -> str:
    """``1 part in N``.

    >>> parts(61234.4), parts(None)
    ('1 part in 61,234', 'n/a')
    """
    return f"1 part in {n:,.0f}" if finite(n) else "n/a"


def secs(s) -> str:
    """A wall time; a minute or more also in minutes and seconds.

    >>> secs(0.354), secs(30.5), secs(118.25)
    ('0.35 s', '30.5 s', '118.2 s (1 min 58 s)')
    """
    if not finite(s):
        return "n/a"
    if s < 60:
        return f"{s:.2f} s" if s < 10 else f"{s:.1f} s"
    minutes, seconds = divmod(round(s), 60)
    return f"{s:.1f} s ({minutes} min {seconds} s)"


def percent(fraction) -> str:
    """A fraction as a percentage.

    >>> percent(0.003), percent(None)
    ('0.3 %', 'n/a')
    """
    return num(100 * fraction if finite(fraction) else fraction, ".3g", "%")


def truthy(v) -> bool:
    """A flag as a table or JSON file holds it: a bool, or text such as ``"True"``.

    >>> truthy(True), truthy("true"), truthy("PASS"), truthy("0")
    (True, True, True, False)
    """
    return v if isinstance(v, bool) else str(v).strip().lower() in ("true", "1", "yes", "pass")


def plus_minus(value: float, u) -> Markup:
    """``value ± u`` with u to two significant digits (common power of ten when tiny or huge).

    >>> [str(plus_minus(*a)) for a in ((52.69678, 0.0121), (-2.3125e-05, 4.955e-06), (694.018, 0.0))]
    ['52.697 ± 0.012', '(-2.31 ± 0.50) × 10<sup>-5</sup>', '694.018']
    """
    if not (finite(u) and u > 0):
        return Markup.escape(f"{value:.7g}")
    big = max(abs(value), u)
    power = int(math.floor(math.log10(big)))
    exponent = power if (power < -3 or power > 5) else 0
    scale = 10.0 ** exponent
    digits = max(0, 1 - int(math.floor(math.log10(u / scale))))
    text = f"{value / scale:.{digits}f} ± {u / scale:.{digits}f}"
    return Markup(f"({text}) × 10<sup>{exponent}</sup>" if exponent else text)


def natural(s) -> list:
    """Sort key putting measurement "2" before "10".

    >>> sorted(["10", "2", "bb01"], key=natural)
    ['2', '10', 'bb01']
    """
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(s))]
