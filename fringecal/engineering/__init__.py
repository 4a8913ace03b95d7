"""Artefact engineering (thesis chapter 3): is the artefact rigid, how much does it
sag, expand with heat and swell with moisture, and how reproducible are its lengths.

Modules
-------
truss
    Stiffness-matrix analysis of a space truss (section 3.4.1): displacements,
    member forces and stresses, reactions, mechanisms reported with their free motion.
supports
    3-2-1 (or any) support constraints, ``5:xyz,1:yz,14:z``.
loads
    Gravity loads from the parts' masses, or prescribed per node / rod end.
rigidity
    Maxwell-Laman count, infinitesimal and generic rigidity, redundant rods, flexes.
sag
    Gravity sag between the CMM support condition and the use condition.
thermal
    CTE from a cooling log (section 3.6.1); temperature compensation.
moisture
    Diffusion coefficient and equilibrium uptake (eqs. 3-19..3-24), CME (eq. 3-17).
consistency
    Rod lengths singly vs assembled vs from coordinates (section 3.7).
design
    Design (ideal) geometry of the thesis artefact.
corrections
    Sag and thermal corrections as an optional calibration-config block.
materials
    ``materials.yaml`` (table 3-1 and the hardware).
"""

from fringecal.engineering.consistency import ConsistencyReport, artefact_from_rod_lengths, rod_length_consistency
from fringecal.engineering.corrections import ArtefactCorrections, apply_corrections
from fringecal.engineering.design import THESIS_TRIANGLES, octahedral_chain
from fringecal.engineering.errors import EngineeringInputError, MechanismError, SupportError, TrussError
from fringecal.engineering.loads import GravityLoads, mass_loads, uniform_loads
from fringecal.engineering.materials import Materials, load_materials
from fringecal.engineering.moisture import (
                       EarlyTimeDiffusion,
                       FickianFit,
                       LengthChange,
                       fickian_fraction,
                       moisture_content_pct,
                       moisture_expansion_coefficient,
)
from fringecal.engineering.rigidity import RigidityReport, analyse_rigidity, rigidity_matrix
from fringecal.engineering.sag import SagCorrection, SupportCondition, gravity_in_artefact_frame, gravity_sag_correction
from fringecal.engineering.supports import Supports, parse_supports
from fringecal.engineering.thermal import CteFit, compensate_temperature
from fringecal.engineering.truss import Truss, TrussSolution, free_motions, solve_truss

__all__ = [
    "ArtefactCorrections", "ConsistencyReport", "CteFit", "EarlyTimeDiffusion", "EngineeringInputError",
    "FickianFit", "GravityLoads", "LengthChange", "Materials", "MechanismError", "RigidityReport",
    "SagCorrection", "SupportCondition", "SupportError", "Supports", "THESIS_TRIANGLES", "Truss",
    "TrussError", "TrussSolution", "analyse_rigidity", "apply_corrections", "artefact_from_rod_lengths",
    "compensate_temperature", "fickian_fraction", "free_motions", "gravity_in_artefact_frame",
    "gravity_sag_correction", "load_materials", "mass_loads", "moisture_content_pct",
    "moisture_expansion_coefficient", "octahedral_chain", "parse_supports", "rigidity_matrix",
    "rod_length_consistency", "solve_truss", "uniform_loads",
]
