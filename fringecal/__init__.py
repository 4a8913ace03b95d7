"""fringecal: calibrate several fringe-projection scanners into one global frame.

The layers, from the top: ``fringecal.flows`` (the command line and the Prefect flows),
``fringecal.tasks`` (the thin Prefect adapter), :mod:`fringecal.run`, :mod:`fringecal.steps`,
then the pure domain packages; ``fringecal.schemas`` holds the table contracts. Everything
below ``fringecal.tasks`` never imports Prefect. docs/architecture.md draws the whole.
"""

from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

try:
    __version__ = version("fringecal")
except PackageNotFoundError:  # running from a checkout without installation
    __version__ = "0.0.0+checkout"

# The repository keeps flows/, tasks/, schemas/ and configs/ beside this folder; the
# installed distribution maps them into the package (pyproject.toml, package-dir). In a
# source checkout (tests, git worktrees) they are found here, beside the package.
_checkout = Path(__file__).resolve().parent.parent
if (_checkout / "pyproject.toml").is_file() and (_checkout / "flows" / "__init__.py").is_file():
    __path__.append(str(_checkout))  # noqa: F821 (a package's __path__)

__all__ = ["__version__"]
