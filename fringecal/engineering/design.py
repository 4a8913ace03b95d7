"""The design geometry of the thesis artefact: a chain of regular octahedra.

The artefact (section 3.4, figure 3-2) is built from vertical equilateral triangles
of spheres, alternately apex-up and apex-down, each pair of neighbours joined by six
rods into a regular octahedron; with all rods equal (600 mm centre to centre) the
triangle planes are ``edge * sqrt(2/3)`` (489.9 mm) apart. The thesis's 15 spheres
form five triangles (7, 8, 9), (4, 5, 6), (1, 2, 3), (13, 14, 15), (10, 11, 12) in
that order along the long axis, which matches both the CMM coordinates of table 3-13
and the 39 member connections of table 3-3.

The frame is that of the CMM coordinates: sphere 7 at the origin, y along the long
axis, z up (the apex of triangle 7-8-9 is sphere 8, above), the first corner of
each triangle at x = 0 and the last at x = -edge. Figure 3-10 of the thesis puts
the origin at node 10 instead; a translation changes no force or displacement.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact

__all__ = ["THESIS_TRIANGLES", "octahedral_chain"]

#: Sphere ids of the thesis artefact's triangles, in order along +y; the middle
#: id of each is the apex (up for the 1st, 3rd, 5th).
THESIS_TRIANGLES = (("7", "8", "9"), ("4", "5", "6"), ("1", "2", "3"), ("13", "14", "15"), ("10", "11", "12"))


def octahedral_chain(triangles=THESIS_TRIANGLES, edge_mm: float = 600.0, diameter_mm: float = 50.0,
                     name: str = "design") -> tuple[Artefact, pd.DataFrame]:
    """Ideal coordinates and rods of a chain of regular octahedra.

    Parameters
    ----------
    triangles : sequence of 3-tuples of str
        Sphere ids per triangle along +y: (corner at x = 0, apex, corner at x = -edge).
    edge_mm : float
        Every rod's centre-to-centre length.
    diameter_mm : float

    Returns
    -------
    Artefact
        Design coordinates, u = 0.
    DataFrame
        Rods ``rod_id, sphere_a, sphere_b, length_mm``: the triangles' sides and the
        six rods between neighbouring triangles (3 + 9 per added triangle).

    >>> art, rods = octahedral_chain()
    >>> len(art), len(rods), sorted(set(rods.length_mm.round(9)))
    (15, 39, [600.0])
    """
    a = float(edge_mm)
    h = a * np.sqrt(3) / 2
    gap = a * np.sqrt(2 / 3)
    ids, pts = [], []
    for k, tri in enumerate(triangles):
        y = k * gap
        z = [0.0, h, 0.0] if k % 2 == 0 else [2 * h / 3, -h / 3, 2 * h / 3]
        for sid, x, zz in zip(tri, (0.0, -a / 2, -a), z):
            ids.append(str(sid))
            pts.append((x, y, zz))
    X = np.array(pts)
    rods = []
    n = len(triangles)
    for k in range(n):
        own = range(3 * k, 3 * k + 3)
        nxt = range(3 * k + 3, 3 * k + 6) if k + 1 < n else range(0)
        for i in own:
            for j in [jj for jj in own if jj > i] + list(nxt):
                if abs(np.linalg.norm(X[j] - X[i]) - a) < 1e-9 * a:
                    rods.append((ids[i], ids[j]))
    table = pd.DataFrame({"rod_id": [str(i + 1) for i in range(len(rods))],
                          "sphere_a": [r[0] for r in rods], "sphere_b": [r[1] for r in rods],
                          "length_mm": a})
    art = Artefact(tuple(ids), X, np.full(len(ids), float(diameter_mm)), np.zeros(len(ids)), name)
    return art, table
