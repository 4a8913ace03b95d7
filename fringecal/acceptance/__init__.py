"""The acceptance test of a calibrated cell per VDI/VDE 2634 parts 2 and 3: probing
errors P_F and P_S on a sphere, sphere-spacing error SD with a dumbbell inside each
scanner's volume, length measurement error E with the ball-bar across scanners and
flatness measurement error F on a flat, each against its limit with its expanded
uncertainty and the ISO 14253-1 decision rule.

Modules: :mod:`~fringecal.acceptance.standards` (the objects' certificates and the
settings), :mod:`~fringecal.acceptance.plan` (positions from measurement volumes),
:mod:`~fringecal.acceptance.measure` (the values of one measurement),
:mod:`~fringecal.acceptance.evaluate` (parameters, limits, verdicts).
"""
