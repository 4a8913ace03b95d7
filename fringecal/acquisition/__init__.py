"""Live acquisition: a real hexapod carries the artefact through the planned poses and
the scanners' own capture commands record each pose into a data set
(``fringecal acquire``; :mod:`.live`). The simulated source is :mod:`fringecal.simulate`.
"""
