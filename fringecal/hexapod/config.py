"""Hexapod configuration (``configs/hexapod/*.yaml``), loaded into strict pydantic models.

Lengths in mm, platform angles in degrees in the file (rad in code), rigid frames in
the project convention (``x_world = R^T x_local + t``, R of eq. 2-6, angles in rad).

Leg length and stroke: ``L = retracted_length_mm + stroke``, where ``L`` is the
distance between the joint centres (eq. 4-14) and ``stroke`` runs from 0 (fully
retracted) to ``stroke_mm``. Encoder counts are ``round(stroke * counts_per_mm)``, so
counts are zero at stroke zero (section 4.5.1).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
from pydantic import Field, model_validator

from fringecal.config import StrictModel, configs_dir, load_yaml_model
from fringecal.frames import Frame
from fringecal.hexapod.kinematics import PlatformGeometry, inverse_kinematics

__all__ = [
    "GeometryConfig",
    "ActuatorConfig",
    "JointLimitsConfig",
    "PlatformPoseConfig",
    "FrameConfig",
    "SerialConfig",
    "HexapodConfig",
    "default_hexapod_config_path",
    "load_hexapod_config",
]


class GeometryConfig(StrictModel):
    """Figures 4-4/4-5: top triangle side parameter a, base hexagon parameters b, d."""

    a_mm: float = Field(gt=0)
    b_mm: float = Field(gt=0)
    d_mm: float = Field(gt=0)


class ActuatorConfig(StrictModel):
    """One linear actuator with its two joints (all six are alike)."""

    stroke_mm: float = Field(gt=0)
    retracted_length_mm: float = Field(gt=0, description="joint centre to joint centre at stroke zero")
    counts_per_mm: float = Field(gt=0)
    speed_mm_s: float = Field(gt=0)
    position_tolerance_counts: int = Field(ge=0, description="largest |encoder - target| accepted after a move")

    @property
    def max_counts(self) -> int:
        return int(np.floor(self.stroke_mm * self.counts_per_mm + 1e-9))


class JointLimitsConfig(StrictModel):
    """Largest angle between a leg and its joint's neutral axis (the leg direction at
    the home pose, fixed in BASE for base joints and in TOP for top joints)."""

    base_max_deg: float = Field(gt=0, lt=90)
    top_max_deg: float = Field(gt=0, lt=90)


class PlatformPoseConfig(StrictModel):
    """A platform pose: TOP origin in BASE (mm) and the eq. 4-3 angles (degrees)."""

    px_mm: float
    py_mm: float
    pz_mm: float
    alpha_deg: float = 0.0
    beta_deg: float = 0.0
    gamma_deg: float = 0.0

    @property
    def vector(self) -> np.ndarray:
        """(px, py, pz, alpha, beta, gamma) in mm and rad, shape (6,)."""
        return np.array([self.px_mm, self.py_mm, self.pz_mm,
                         *np.radians([self.alpha_deg, self.beta_deg, self.gamma_deg])])


class FrameConfig(StrictModel):
    """A rigid frame T_a_b: origin of b in a (mm) and eq. 2-6 angles (rad)."""

    tx_mm: float
    ty_mm: float
    tz_mm: float
    omega_rad: float
    phi_rad: float
    kappa_rad: float

    @property
    def frame(self) -> Frame:
        return Frame.from_params([self.tx_mm, self.ty_mm, self.tz_mm,
                                  self.omega_rad, self.phi_rad, self.kappa_rad])

    @classmethod
    def from_frame(cls, frame: Frame, decimals: int = 6) -> "FrameConfig":
        p = np.round(frame.params, decimals)
        return cls(tx_mm=p[0], ty_mm=p[1], tz_mm=p[2], omega_rad=p[3], phi_rad=p[4], kappa_rad=p[5])


class SerialConfig(StrictModel):
    """Link to the control box and the driver's watchdogs."""

    baudrate: int = Field(default=115200, gt=0)
    reply_timeout_s: float = Field(default=1.0, gt=0, description="longest wait for one reply line")
    poll_interval_s: float = Field(default=0.2, ge=0, description="pause between POS? polls while moving")
    move_timeout_margin_s: float = Field(default=10.0, ge=0,
                                         description="added to the travel time at full speed before a move times out")
    stall_polls: int = Field(default=25, ge=2,
                             description="consecutive polls without encoder progress that count as a stall")
    path_checks: int = Field(default=8, ge=1,
                             description="intermediate poses checked against the workspace along each move")


class HexapodConfig(StrictModel):
    """A Stewart platform, its actuators, its placement in a rig and its serial link."""

    name: str
    geometry: GeometryConfig
    actuator: ActuatorConfig
    joints: JointLimitsConfig
    home_pose: PlatformPoseConfig
    T_top_artefact: FrameConfig
    T_world_base: FrameConfig
    serial: SerialConfig = SerialConfig()
    notes: Optional[str] = None

    @model_validator(mode="after")
    def _home_in_stroke(self):
        lengths = inverse_kinematics(self.platform, self.home_pose.vector)
        stroke = lengths - self.actuator.retracted_length_mm
        if np.any(stroke < 0) or np.any(stroke > self.actuator.stroke_mm):
            raise ValueError(f"home_pose needs strokes {np.round(stroke, 3).tolist()} mm, outside "
                             f"0..{self.actuator.stroke_mm} mm")
        return self

    @property
    def platform(self) -> PlatformGeometry:
        g = self.geometry
        return PlatformGeometry(a_mm=g.a_mm, b_mm=g.b_mm, d_mm=g.d_mm)


def default_hexapod_config_path() -> Path:
    return configs_dir() / "hexapod" / "thesis_platform.yaml"


def load_hexapod_config(path=None) -> HexapodConfig:
    """Load a hexapod YAML (default: the thesis platform); raises ConfigError naming file and key."""
    return load_yaml_model(path or default_hexapod_config_path(), HexapodConfig)
