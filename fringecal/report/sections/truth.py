"""Simulation truth: the calibrated sensors against the simulator's true ones (``evaluation.json``)."""

from __future__ import annotations

from fringecal.report.formatting import finite, length, num, um, urad
from fringecal.report.rundata import RunData
from fringecal.report.tables import table

__all__ = ["build"]


def build(run: RunData) -> dict:
    """The largest sensor errors, the residual floor and the per-sensor errors against their u."""
    ev = run.evaluation()
    after = (run.maybe_json(run.rd.bundle_summary) or {}).get("after") or {}
    true_bar = ev.get("verification_true_params")
    floor = true_bar.get("max_abs_error_mm") if isinstance(true_bar, dict) else None
    rows = [[s.get("sensor"), um(s.get("position_error_mm")), urad(s.get("angle_error_rad")),
             um(s.get("c_error_mm")), num(s.get("max_sigma_ratio_position_angles_c"), ".2f")]
            for s in ev.get("sensors", [])]
    return {"position": um(ev.get("max_position_error_mm")), "angle": urad(ev.get("max_angle_error_rad")),
            "f": f"{length(after.get('rms_f_mm'))} / {length(ev.get('rms_f_mm_true_params'))}",
            "eps1": f"{um(after.get('rms_eps1_mm'))} / {um(ev.get('rms_eps1_mm_true_params'))}",
            "eps2": f"{um(after.get('rms_eps2_mm'))} / {um(ev.get('rms_eps2_mm_true_params'))}",
            "ballbar": um(floor) if finite(floor) else None,
            "sensors": table(["Sensor", "Position error", "Max angle error", "c error",
                              "max |error| / u (position, angles, c)"], rows) if rows else None}
