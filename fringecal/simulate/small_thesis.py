"""The small simulated thesis rig that tests and benchmarks share.

A subset of the thesis experiment that runs end to end in well under a minute: some of
the twelve poses of table 6-1, some ball-bar positions of table 6-9, cameras resampled
to ``width`` px and a short fringe sequence (counts 32 ... 16, five steps), every clean
sphere pixel a control point. :func:`write_small_thesis_config` writes its rig YAML,
pose and position tables and run config into a folder.
"""

from __future__ import annotations

from pathlib import Path

from fringecal.config import thesis_dir

__all__ = ["write_small_thesis_config"]


def write_small_thesis_config(d: Path, width: int = 320, poses=(1, 5, 9, 12), positions=(1, 4, 9),
                              name: str = "small", acceptance: dict | None = None) -> Path:
    """Write the small rig's files into folder ``d``; returns the run config's path.

    ``poses`` are measurements of table 6-1, ``positions`` of table 6-9. Four poses are
    the tests' default (four stand-offs); cross-validation needs at least three
    measurements of every scanner in each half, which eight poses give
    (``benchmarks/length_coverage.py``).
    """
    import pandas as pd
    import yaml

    thesis = thesis_dir()
    table = pd.read_csv(thesis / "poses_scanner1_table6-1.csv")
    table[table.measurement.isin(list(poses))].to_csv(d / "poses.csv", index=False)
    bb = pd.read_csv(thesis / "ballbar_verification_table6-9.csv")
    bb[bb.measurement.isin(list(positions))].to_csv(d / "ballbar_positions.csv", index=False)
    rig = yaml.safe_load((thesis / "rig.yaml").read_text())
    for k in ("sensors", "sensors_initial", "artefact", "rods", "ballbar", "materials"):
        rig[k] = str(thesis / rig[k])
    rig["artefact_poses"] = str(d / "poses.csv")
    (d / "rig.yaml").write_text(yaml.safe_dump(rig))
    cfg = {
        "name": name,
        "simulate": {"rig": str(d / "rig.yaml"),
                     "acquisition": {"camera_width_px": width, "seed": 11,
                                     "sequence": {"fringe_counts": [32, 31, 30, 28, 24, 16], "n_steps": 5}},
                     "verification": {"positions": str(d / "ballbar_positions.csv"), "camera_width_px": width},
                     "acceptance": {"enabled": False} if acceptance is None else acceptance},
        "control_points": {"spacing_px": 1},
    }
    path = d / "run.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path
