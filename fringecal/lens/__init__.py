"""What a sensor's optics do beyond the pinhole: the Brown model's compiled inversion
(:mod:`.inversion`), the smooth correction field over the image plane (:mod:`.field`) and
the part of the image plane a calibration observed (:mod:`.observed_region`).

Kept light: importing :mod:`.field` does not compile or import numba.
"""
