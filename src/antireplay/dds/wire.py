"""The one DDS type of every sealed topic.

No ``from __future__ import annotations`` here: Cyclone's IDL layer resolves
the field annotations at run time and needs them as objects, not strings.
"""

from dataclasses import dataclass
from typing import TYPE_CHECKING

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.annotations import key
from cyclonedds.idl.types import sequence, uint8


@dataclass
class SealedSample(IdlStruct, typename="antireplay.SealedSample"):
    """An instance key (the DDS key field) and a sealed epoch announcement."""

    instance: str
    key("instance")
    if TYPE_CHECKING:  # what the application sees: bytes written, a list of ints read
        sealed: bytes | list[int]
    else:
        sealed: sequence[uint8]
