"""Who and what a calibration certificate is for: the identity block of its first page.

:class:`CertificateIdentity` is the ``certificate`` section of a data set's
``dataset.yaml`` (a recorded cell) or of a run configuration (a simulated run; a run
configuration's section takes precedence over the data set's). Every field is
optional: the certificate shows what is given and leaves a blank line to fill in for
what is not, so a run without one still has a certificate page, with empty fields.

The certificate's number is not a field: it is derived from the run's digests
(:func:`certificate_number`), so the same inputs, settings and results always carry
the same number and any change to them gives another.
"""

from __future__ import annotations

import datetime
import hashlib
from typing import Optional

from pydantic import Field

from fringecal.config import StrictModel

__all__ = ["CertificateReference", "CertificateIdentity", "certificate_number"]


class CertificateReference(StrictModel):
    """A calibration certificate of a reference object (the artefact's CMM
    certificate, the ball-bar's, the acceptance objects'): its number, date and issuer."""

    number: str
    date: Optional[datetime.date] = None
    issuer: Optional[str] = None


class CertificateIdentity(StrictModel):
    """The identity block of the certificate (``certificate`` in ``dataset.yaml`` or the
    run configuration).

    ``scanners`` maps each scanner's name (as in the rig) to its serial number;
    ``temperatures_c`` names each temperature recorded during the measurements (e.g.
    ``air``, ``artefact``) in degrees Celsius; ``approved_by`` prints the approver's
    name under the signature line.
    """

    customer: Optional[str] = None
    cell: Optional[str] = None
    place: Optional[str] = None
    date: Optional[datetime.date] = None
    operator: Optional[str] = None
    scanners: dict[str, str] = Field(default_factory=dict)
    artefact_certificate: Optional[CertificateReference] = None
    ballbar_certificate: Optional[CertificateReference] = None
    standards_certificate: Optional[CertificateReference] = None
    temperatures_c: dict[str, float] = Field(default_factory=dict)
    approved_by: Optional[str] = None
    remarks: Optional[str] = None


def certificate_number(parts: dict[str, str]) -> str:
    """The certificate's number from the run's digests: ``FC-`` and twelve hexadecimal
    digits of the SHA-256 of the named ``parts`` (digests of the configuration, the
    inputs and the result documents), in groups of four.

    >>> certificate_number({"config": "ab" * 32, "calibration.json": "cd" * 32})
    'FC-EBE5-CF1B-F30C'
    >>> certificate_number({"calibration.json": "cd" * 32, "config": "ab" * 32})  # order does not matter
    'FC-EBE5-CF1B-F30C'
    """
    text = "\n".join(f"{k}={parts[k]}" for k in sorted(parts))
    h = hashlib.sha256(text.encode("utf-8")).hexdigest()[:12].upper()
    return f"FC-{h[:4]}-{h[4:8]}-{h[8:]}"
