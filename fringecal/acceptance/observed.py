"""Where the acceptance test's objects were measured on the calibration's image planes:
per object position, the share of its fits' pixels outside the calibration's observed
region (``acceptance.json`` ``observed_region``).

A calibration is tested only where its control points lay
(:mod:`fringecal.lens.observed_region`); an acceptance object measured beyond that
region tests the sensor model's extrapolation. The count is the ball-bar's
(:func:`fringecal.verification.measure.positions_outside`): a pixel is outside when its
camera pixel or its projector phases lie outside the observed region of that camera or
projector. Which pixels count:

- **sphere, flat**: the camera pixels of the points the P_F, P_S or F fit kept (the
  guideline's exclusion applied; :attr:`fringecal.acceptance.measure.SphereMeasurement.pixels`);
- **dumbbell**: the pixels both spheres' refits kept, as for a ball-bar position;
- **ball-bar (E)**: copied from the verification (``verification.json``
  ``calibrated.observed_region``), which counted them.

A calibration without observed regions (a file written before they existed, or a rig of
black boxes only) gives ``known: false`` and every share ``null``: not known, never 0.
The objects measured in a black box's clouds have no image plane and are not listed.
"""

from __future__ import annotations

from fringecal.rig import Rig
from fringecal.verification.measure import positions_outside

__all__ = ["objects_outside", "partly_outside", "outside_counts", "MEASURED_TESTS", "COUNTED_TESTS"]

#: The tests whose objects the acceptance step measures itself (the ball-bar's E comes
#: from the verification, which counts and warns about its positions).
MEASURED_TESTS = ("sphere", "flat", "dumbbell")
#: The tests :func:`outside_counts` counts, in its order: the acceptance objects and E's
#: ball-bar positions.
COUNTED_TESTS = (*MEASURED_TESTS, "ballbar")

WHAT = ("per object position, the camera pixels its fits kept and how many of them lie outside the calibration's "
        "observed region of the camera or the projector that saw them (calibration.json observed_region); "
        "null: not known")


def _unknown(pixels: dict) -> dict:
    """position -> the pixels counted, nothing known about the region."""
    out: dict = {}
    for (position, scanner, _), (rows, _cols) in sorted(pixels.items()):
        entry = out.setdefault(position, {"points": 0, "outside": None, "fraction": None, "scanners": {}})
        mine = entry["scanners"].setdefault(scanner, {"points": 0, "outside": None})
        entry["points"] += len(rows)
        mine["points"] += len(rows)
    return out


def _ballbar(verification: dict | None) -> list[dict]:
    """E's positions with the verification's count (not known where it has none)."""
    if verification is None:
        return []
    calibrated = verification.get("calibrated") or {}
    counted = calibrated.get("observed_region")
    if counted is not None:
        return [{"test": "ballbar", "position": str(p), **e} for p, e in counted.items()]
    return [{"test": "ballbar", "position": str(p["measurement"]), "points": None, "outside": None,
             "fraction": None, "scanners": {}} for p in calibrated.get("positions", [])]


def objects_outside(stores: dict, rig: Rig | None, kept: dict, regions: dict | None,
                    verification: dict | None = None) -> dict:
    """``acceptance.json``'s ``observed_region``.

    Parameters
    ----------
    stores : kind -> position -> scanner -> store path of the modelled scanners
    rig : the rig the objects were measured with (None: black boxes only)
    kept : kind -> {(position, scanner, sphere id or kind): (rows, cols)}, the pixels
        each fit kept (:func:`fringecal.acceptance.document.measure_acceptance` with
        ``pixels``)
    regions : sensor name -> :class:`~fringecal.lens.observed_region.ObservedRegion`
        (``calibration.json``); None or empty: not known
    verification : ``verification.json``, whose ball-bar positions are E's

    Returns
    -------
    {"known": bool, "what": str, "objects": [{"test", "position", "points", "outside",
    "fraction", "scanners": scanner -> {"points", "outside"}}, ...]}, the objects in
    the order sphere, flat, dumbbell, ball-bar; ``outside`` and ``fraction`` None when
    not known.
    """
    known = bool(regions) and rig is not None
    objects = []
    for kind in MEASURED_TESTS:
        pixels = kept.get(kind) or {}
        if not pixels:
            continue
        counted = positions_outside(stores[kind], rig, pixels, regions) if known else _unknown(pixels)
        objects += [{"test": kind, "position": p, **e} for p, e in counted.items()]
    return {"known": known, "what": WHAT, "objects": objects + _ballbar(verification)}


def partly_outside(doc: dict | None, tests=MEASURED_TESTS) -> list[str]:
    """Per test of ``tests`` with any position partly outside the observed region,
    ``"<test>: <k> of <n> positions, up to <share> %"``, from an ``observed_region``
    document (:func:`objects_outside`); empty when none is (or none is known).

    >>> partly_outside({"objects": [{"test": "sphere", "position": "s1", "outside": 3, "fraction": 0.125},
    ...                             {"test": "sphere", "position": "s2", "outside": 1, "fraction": 0.02},
    ...                             {"test": "flat", "position": "f1", "outside": 0, "fraction": 0.0},
    ...                             {"test": "ballbar", "position": "bb1", "outside": 9, "fraction": 0.5},
    ...                             {"test": "dumbbell", "position": "d1", "outside": None, "fraction": None}]})
    ['sphere: 2 of 2 positions, up to 12 %']
    """
    out = []
    for test in tests:
        mine = [o for o in (doc or {}).get("objects", []) if o["test"] == test]
        hit = [o for o in mine if o.get("outside")]
        if hit:
            out.append(f"{test}: {len(hit)} of {len(mine)} positions, up to "
                       f"{100 * max(o['fraction'] for o in hit):.0f} %")
    return out


def outside_counts(doc: dict | None) -> dict:
    """How many positions of each test lie outside the observed region: the counts of
    ``summary.json`` (``acceptance.outside_observed_region``) and the certificate page.

    Parameters
    ----------
    doc : an ``observed_region`` document (:func:`objects_outside`); None: an
        ``acceptance.json`` written before it had one

    Returns
    -------
    {"known": bool, "tests": test -> {"positions", "partly_outside", "wholly_outside",
    "max_fraction"}} for each test of :data:`COUNTED_TESTS` with a position:
    ``partly_outside`` counts positions with any pixel outside (the wholly outside
    among them), ``wholly_outside`` those with every pixel outside, ``max_fraction`` the
    largest share. Where the region is not known (no document, ``known: false``, or a
    position without a count) the three are None: not known, never 0.

    >>> outside_counts({"known": True, "objects": [
    ...     {"test": "sphere", "position": "s1", "points": 40, "outside": 40, "fraction": 1.0},
    ...     {"test": "sphere", "position": "s2", "points": 50, "outside": 5, "fraction": 0.1},
    ...     {"test": "sphere", "position": "s3", "points": 30, "outside": 0, "fraction": 0.0},
    ...     {"test": "ballbar", "position": "bb01", "points": None, "outside": None, "fraction": None}]})["tests"]
    ... # doctest: +NORMALIZE_WHITESPACE
    {'sphere': {'positions': 3, 'partly_outside': 2, 'wholly_outside': 1, 'max_fraction': 1.0},
     'ballbar': {'positions': 1, 'partly_outside': None, 'wholly_outside': None, 'max_fraction': None}}
    >>> outside_counts(None)
    {'known': False, 'tests': {}}
    """
    known = bool((doc or {}).get("known"))
    tests = {}
    for test in COUNTED_TESTS:
        mine = [o for o in (doc or {}).get("objects", []) if o.get("test") == test]
        if not mine:
            continue
        if not known or any(o.get("outside") is None for o in mine):
            tests[test] = {"positions": len(mine), "partly_outside": None, "wholly_outside": None,
                           "max_fraction": None}
            continue
        tests[test] = {"positions": len(mine), "partly_outside": sum(o["outside"] > 0 for o in mine),
                       "wholly_outside": sum(0 < o["points"] == o["outside"] for o in mine),
                       "max_fraction": max(float(o["fraction"] or 0.0) for o in mine)}
    return {"known": known, "tests": tests}
