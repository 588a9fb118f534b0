"""Validation and broadcasting of the components given to ``from_components``."""
from __future__ import annotations

from ..functional import checks


def prepare(**parts):
    """parts: name -> (tensor, trailing shape).  Returns the tensors broadcast to one batch."""
    return checks.components(**parts)
