"""The report's sections, in page order: each a module whose ``build`` reads the run
directory into the context of its template ``templates/<anchor>.html.j2``."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["SECTIONS", "Section"]


@dataclass(frozen=True)
class Section:
    """One section of the page: its anchor (also its module and template name) and title."""

    anchor: str
    title: str

    @property
    def template(self) -> str:
        return f"{self.anchor}.html.j2"


SECTIONS = (Section("rig", "Rig and artefact"), Section("timing", "Timing"),
            Section("results", "Calibration results"), Section("scanners", "Scanners"),
            Section("residuals", "Residuals"), Section("crossval", "Cross-validation"),
            Section("verification", "Verification (ball-bar)"),
            Section("acceptance", "Acceptance test (VDI/VDE 2634 parts 2 and 3)"),
            Section("truth", "Simulation truth"), Section("provenance", "Provenance"))
