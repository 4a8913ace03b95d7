"""Simulated rigs beyond the thesis's: a row of scanners and a ring around the artefact.

Both are built from the thesis's two scanner designs (table 6-8: camera and projector
about 0.9 m apart, fields about 0.95 m wide at 3.3 m) carried rigidly to new places,
in the thesis's world, so that the artefact, its hexapod and the twelve poses of
table 6-1 stay where they were (every pose is reachable by the same platform):

- :func:`row_rig`: ``n`` copies of scanner one side by side along world x,
  ``spacing_mm`` apart. With the default 750 mm the 0.95 m camera fields overlap by
  about 0.2 m at the artefact's depth, so that each of the three scanners sees 3-6
  whole spheres of the 2 m artefact despite the rods (at 950 mm the fields touch,
  but the end scanners then see only two whole spheres in many poses).
- :func:`ring_rig`: ``n`` scanners (alternately designs one and two) on a ring about
  the vertical (world y) through the artefact's mean position, looking inward and 15
  deg down from all sides as around a car body; each camera axis passes through the
  ring's centre at the thesis's working distance. The first scanner is turned 30 deg
  from the thesis's view: with six scanners none then looks square at the artefact's
  side, where the nearer spheres hide the farther ones (at 0 deg two scanners see only
  two whole spheres in some poses; looking down, fewer are hidden).

``python -m fringecal.simulate.rigs`` writes the sensor tables the configs use
(``configs/row3/sensors.csv``, ``configs/ring6/sensors.csv``); a test checks that
they are what these functions give.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from fringecal.config import configs_dir, thesis_dir
from fringecal.frames import Frame
from fringecal.rig import Rig, Scanner, load_rig
from fringecal.rotation import angles_from_matrix, rotation_matrix
from fringecal.sensor import Sensor

__all__ = ["carried_scanner", "row_rig", "ring_rig", "RIG_TABLES", "write_rig_tables"]

#: the artefact's mean sphere position over the 12 poses of table 6-1 (world, mm)
ARTEFACT_CENTRE = np.array([-780.0, 82.0, -279.0])


def _carried_sensor(sensor: Sensor, name: str, T: Frame) -> Sensor:
    params = np.array(sensor.params, copy=True)
    params[:3] = T.to_world(sensor.pinhole[None])[0]
    params[3:6] = angles_from_matrix(sensor.R @ T.R, near=sensor.angles)
    return replace(sensor, name=name, params=params)


def carried_scanner(scanner: Scanner, T: Frame, index: int) -> Scanner:
    """``scanner`` moved rigidly by ``T`` (world -> world), named ``scanner{index}``
    with sensors ``C{index}`` and ``P{index}``."""
    return Scanner(f"scanner{index}", _carried_sensor(scanner.camera, f"C{index}", T),
                   _carried_sensor(scanner.projector, f"P{index}", T))


def _thesis_scanners() -> tuple[Scanner, Scanner]:
    return load_rig(thesis_dir() / "sensors_refined_table6-8.csv").scanners


def row_rig(n: int = 3, spacing_mm: float = 750.0, offset_mm: float = 150.0) -> Rig:
    """``n`` copies of thesis scanner one, the first moved ``offset_mm`` along world +x,
    each next one ``spacing_mm`` further along -x. Reference: scanner1."""
    s1, _ = _thesis_scanners()
    scanners = [carried_scanner(s1, Frame([offset_mm - i * spacing_mm, 0.0, 0.0], [0.0, 0.0, 0.0]), i + 1)
                for i in range(n)]
    return Rig(tuple(scanners), "scanner1")


def _axis_point(sensor: Sensor, z: float) -> np.ndarray:
    d = sensor.R[2]
    return sensor.pinhole + d * (z - sensor.pinhole[2]) / d[2]


def ring_rig(n: int = 6, centre=ARTEFACT_CENTRE, start_rad: float = np.pi / 6, elevation_rad: float = np.radians(15.0)) -> Rig:
    """``n`` scanners on a ring about the vertical through ``centre``, scanner k turned
    by ``start_rad + 2 pi (k - 1) / n`` from the thesis's viewing direction (world -z),
    each raised by ``elevation_rad`` to look down at the centre. Reference: scanner1."""
    designs = _thesis_scanners()
    centre = np.asarray(centre, float)
    scanners = []
    for k in range(n):
        src = designs[k % 2]
        aimed = carried_scanner(src, Frame(centre - _axis_point(src.camera, centre[2]), [0.0, 0.0, 0.0]), k + 1)
        raise_ = Frame(centre - rotation_matrix(-elevation_rad, 0.0, 0.0).T @ centre, [-elevation_rad, 0.0, 0.0])
        aimed = carried_scanner(aimed, raise_, k + 1)
        a = start_rad + 2 * np.pi * k / n
        turn = Frame(centre - rotation_matrix(0.0, a, 0.0).T @ centre, [0.0, a, 0.0])
        scanners.append(carried_scanner(aimed, turn, k + 1))
    return Rig(tuple(scanners), "scanner1")


#: config folder -> the rig its sensors.csv holds
RIG_TABLES = {"row3": row_rig, "ring6": ring_rig}


def write_rig_tables(root: Path | None = None) -> list[Path]:
    """Write ``configs/<name>/sensors.csv`` for every rig of :data:`RIG_TABLES`."""
    root = Path(root) if root is not None else configs_dir()
    out = []
    for name, build in RIG_TABLES.items():
        path = root / name / "sensors.csv"
        path.parent.mkdir(parents=True, exist_ok=True)
        build().to_frame().to_csv(path, index=False, float_format="%.9g")
        out.append(path)
    return out


if __name__ == "__main__":  # pragma: no cover
    for p in write_rig_tables(Path(sys.argv[1]) if len(sys.argv) > 1 else None):
        print(p)
