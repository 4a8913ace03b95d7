"""Materials and hardware of an artefact (thesis table 3-1, sections 3.4.2, 3.5, 3.6).

``configs/thesis/materials.yaml`` is the default. Units follow the file's keys
(GPa, kg/m^3, mm, g); the derived quantities here are in mm, N/mm^2 (MPa), N and kg.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
from pydantic import Field, model_validator

from fringecal.config import StrictModel, load_yaml_model, thesis_dir

__all__ = ["Material", "Materials", "load_materials", "KG_PER_MM3"]

#: kg/m^3 to kg/mm^3
KG_PER_MM3 = 1e-9


class Material(StrictModel):
    elastic_modulus_gpa: float = Field(gt=0)
    density_kg_m3: float = Field(gt=0)
    cte_per_c: float

    @property
    def elastic_modulus_mpa(self) -> float:
        return self.elastic_modulus_gpa * 1e3


class Tube(StrictModel):
    material: str
    outer_diameter_mm: float = Field(gt=0)
    wall_mm: float = Field(gt=0)
    nominal_length_mm: float = Field(gt=0)
    nominal_centre_spacing_mm: float = Field(gt=0)

    @model_validator(mode="after")
    def _wall_fits(self):
        if 2 * self.wall_mm > self.outer_diameter_mm:
            raise ValueError(f"tube wall {self.wall_mm} mm is more than half the outer diameter "
                             f"{self.outer_diameter_mm} mm")
        return self

    @property
    def area_mm2(self) -> float:
        """Cross-section of the tube wall, mm^2."""
        inner = self.outer_diameter_mm - 2 * self.wall_mm
        return float(np.pi / 4 * (self.outer_diameter_mm ** 2 - inner ** 2))


class Sphere(StrictModel):
    material: str
    nominal_diameter_mm: float = Field(gt=0)


class EndCap(StrictModel):
    material: str
    outer_diameter_mm: float = Field(gt=0)
    length_mm: float = Field(ge=0)
    bore_diameter_mm: float = Field(ge=0)

    @property
    def volume_mm3(self) -> float:
        return float(np.pi / 4 * (self.outer_diameter_mm ** 2 - self.bore_diameter_mm ** 2) * self.length_mm)


class Magnet(StrictModel):
    model: str
    diameter_mm: float = Field(gt=0)
    length_mm: float = Field(gt=0)
    mass_g: float = Field(ge=0)
    pull_off_rating_n: float = Field(gt=0)
    pull_off_measured_n: Optional[float] = None
    pull_off_measured_sd_n: Optional[float] = None


class Thermal(StrictModel):
    effective_cte_per_c: float
    reference_temperature_c: float


class Hygral(StrictModel):
    diffusion_m2_s: dict[str, float] = {}
    cme_per_percent: Optional[float] = None


class Cmm(StrictModel):
    artefact_uncertainty_mm: float = Field(ge=0)
    rod_uncertainty_mm: float = Field(ge=0)


class Materials(StrictModel):
    """The whole ``materials.yaml``: named materials and the parts made from them."""

    materials: dict[str, Material]
    tube: Tube
    sphere: Sphere
    end_cap: EndCap
    magnet: Magnet
    thermal: Thermal
    hygral: Optional[Hygral] = None
    cmm: Optional[Cmm] = None

    @model_validator(mode="after")
    def _materials_exist(self):
        for part in ("tube", "sphere", "end_cap"):
            name = getattr(self, part).material
            if name not in self.materials:
                raise ValueError(f"{part}.material {name!r} is not one of the materials "
                                 f"{sorted(self.materials)}")
        return self

    def material_of(self, part: str) -> Material:
        return self.materials[getattr(self, part).material]

    @property
    def tube_ea_n(self) -> float:
        """Axial stiffness E*A of a tube, N."""
        return self.material_of("tube").elastic_modulus_mpa * self.tube.area_mm2

    def sphere_mass_kg(self, diameters_mm) -> np.ndarray:
        """Mass of solid spheres, kg; ``diameters_mm`` any shape."""
        d = np.asarray(diameters_mm, float)
        return self.material_of("sphere").density_kg_m3 * KG_PER_MM3 * np.pi / 6 * d ** 3

    def tube_mass_kg(self, lengths_mm) -> np.ndarray:
        """Mass of tubes of the given lengths, kg."""
        rho = self.material_of("tube").density_kg_m3 * KG_PER_MM3
        return rho * self.tube.area_mm2 * np.asarray(lengths_mm, float)

    @property
    def end_cap_mass_kg(self) -> float:
        return self.material_of("end_cap").density_kg_m3 * KG_PER_MM3 * self.end_cap.volume_mm3

    @property
    def magnet_mass_kg(self) -> float:
        return self.magnet.mass_g * 1e-3


def load_materials(path=None) -> Materials:
    """Read a materials YAML (default: the thesis's ``configs/thesis/materials.yaml``).

    >>> m = load_materials()
    >>> round(m.tube.area_mm2, 2), round(m.tube_ea_n / 1e6, 3)
    (89.72, 14.356)
    """
    return load_yaml_model(Path(path) if path is not None else thesis_dir() / "materials.yaml", Materials)
