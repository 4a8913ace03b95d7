"""fringecal: calibrate several fringe-projection scanners into one global frame.

``fringecal`` is the pure computational core (numerics, I/O, tables); it never
imports Prefect. ``tasks`` adapt it to Prefect tasks and ``flows`` wire them.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("fringecal")
except PackageNotFoundError:  # running from a checkout without installation
    __version__ = "0.0.0+checkout"

__all__ = ["__version__"]
