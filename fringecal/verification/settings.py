"""The ``verification:`` section of a run configuration: how the ball-bar lengths are
evaluated and what each length's uncertainty takes from outside the data."""

from __future__ import annotations

from pydantic import Field

from fringecal.config import StrictModel

__all__ = ["VerificationConfig", "LengthUncertaintyConfig"]


class LengthUncertaintyConfig(StrictModel):
    """What the task-specific uncertainty of every measured length takes from outside
    the data (:mod:`fringecal.verification.budget`): the artefact's and the bar's
    temperature uncertainty and expansion coefficients, the coverage factor of the
    expanded uncertainty, and the Monte Carlo check (JCGM 101; 0 draws turns it off).

    Defaults: the thesis's carbon-fibre rods expand by 1.9e-6 /K (section 3.4.1, the
    heated ball-bar) and its laboratory held the temperature to about +-0.5 K, taken
    here as a standard uncertainty of 0.5 K (a rectangular +-0.5 K would be 0.29 K;
    0.5 K allows for the artefact lagging the air). ``artefact_u_factor`` multiplies the
    artefact table's own ``u_mm`` (the CMM's standard uncertainty per coordinate); the
    budget states the world it is made for, so a simulation whose artefact is exactly
    its table at 20 C (the ideal profile) is described by a factor and temperature
    uncertainties of 0.
    """

    artefact_u_factor: float = Field(1.0, ge=0)
    artefact_temperature_u_c: float = Field(0.5, ge=0)
    artefact_cte_per_c: float = Field(1.9e-6, ge=-1e-4, le=1e-4)
    ballbar_temperature_u_c: float = Field(0.5, ge=0)
    ballbar_cte_per_c: float = Field(1.9e-6, ge=-1e-4, le=1e-4)
    coverage_factor: float = Field(2.0, gt=0)
    monte_carlo_draws: int = Field(1000, ge=0)
    seed: int = 0
    #: scale each sphere fit's uncertainty by its scanner's scatter of centres between
    #: spheres in the calibration's views, max(1, kappa) (fringecal.spheres.dispersion)
    sphere_scatter: bool = True


class VerificationConfig(StrictModel):
    """Evaluation of the ball-bar lengths (thesis 6.9.3; VDI/VDE 2634): limit, the
    GUM statement of the certified length, and each length's own uncertainty."""

    mpe_mm: float = Field(0.1, gt=0)
    certificate_u_mm: float = Field(0.0004, ge=0)
    certificate_k: float = Field(2.0, gt=0)
    coverage_factor: float = Field(1.96, gt=0)
    uncertainty: LengthUncertaintyConfig = Field(default_factory=LengthUncertaintyConfig)
