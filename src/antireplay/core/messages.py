"""The RCAN message vocabulary: message type numbers and safety events.

``MessageType`` follows the current canonical RCAN table (the one the RCAN SDK
calls its single source of truth): COMMAND=1, SAFETY=6, COMMAND_NACK=18.  The
§8.3 text's "COMMAND_NACK (type 31)" is the v1.5/v1.6 numbering; see
``SecurityConfig.nack_type``.
"""

from __future__ import annotations

from enum import Enum, IntEnum


class StrEnum(str, Enum):
    """``enum.StrEnum`` (Python 3.11) for 3.10 too: members are str, and ``str()`` and
    ``format()`` give the value (what goes on the wire, in f-strings and in JSON)."""

    def __str__(self) -> str:
        return str.__str__(self)

    def __format__(self, spec: str) -> str:
        return str.__format__(str.__str__(self), spec)


class MessageType(IntEnum):
    """Canonical RCAN message type numbers."""

    COMMAND = 1
    RESPONSE = 2
    STATUS = 3
    HEARTBEAT = 4
    CONFIG = 5
    SAFETY = 6
    AUTH = 7
    ERROR = 8
    DISCOVER = 9
    PENDING_AUTH = 10
    INVOKE = 11
    INVOKE_RESULT = 12
    INVOKE_CANCEL = 13
    REGISTRY_REGISTER = 14
    REGISTRY_RESOLVE = 15
    TRANSPARENCY = 16
    COMMAND_ACK = 17
    COMMAND_NACK = 18
    ROBOT_REVOCATION = 19
    CONSENT_REQUEST = 20
    CONSENT_GRANT = 21
    CONSENT_DENY = 22
    FLEET_COMMAND = 23
    SUBSCRIBE = 24
    UNSUBSCRIBE = 25
    FAULT_REPORT = 26
    KEY_ROTATION = 27
    COMMAND_COMMIT = 28
    SENSOR_DATA = 29
    TRAINING_CONSENT_REQUEST = 30
    TRAINING_CONSENT_GRANT = 31
    TRAINING_CONSENT_DENY = 32


class SafetyEvent(StrEnum):
    """The events a SAFETY (type 6) message carries."""

    ESTOP = "ESTOP"
    STOP = "STOP"
    RESUME = "RESUME"
