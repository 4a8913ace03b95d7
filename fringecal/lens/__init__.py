"""What a sensor's optics do beyond the pinhole: the Brown model's compiled inversion
(:mod:`.inversion`) and the smooth correction field over the image plane (:mod:`.field`).

Kept light: importing :mod:`.field` does not compile or import numba.
"""
