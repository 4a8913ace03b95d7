"""Errors of the engineering tools: bad input the user can fix."""

from __future__ import annotations

__all__ = ["EngineeringInputError", "SupportError", "TrussError", "MechanismError"]


class EngineeringInputError(ValueError):
    """Bad input to an engineering computation; the message says what and where."""


class SupportError(EngineeringInputError):
    """A support specification is malformed, names unknown nodes or is too weak."""


class TrussError(EngineeringInputError):
    """A truss cannot be built (unknown spheres, zero-length or repeated members)."""


class MechanismError(EngineeringInputError):
    """The supported structure can move without deforming: its stiffness is singular.

    Attributes
    ----------
    modes : ndarray, shape (k, n, 3)
        Orthonormal basis of the free motions (displacement per node, unitless).
    node_ids : tuple of str, length n
    """

    def __init__(self, message: str, modes, node_ids):
        super().__init__(message)
        self.modes = modes
        self.node_ids = tuple(node_ids)
