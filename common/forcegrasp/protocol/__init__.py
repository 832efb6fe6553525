"""ForceGrasp wire protocol: Zenoh key expressions and msgpack messages.

Every service (and any third-party client, see ``docs/protocol.md``) talks through the keys of
:class:`Keys` (``keys.py``) and six message types: ``transitions``, ``weights``, ``stats``,
``checkpoint`` and ``progress`` (``messages.py``), ``best`` (``best.py``). Messages are msgpack
maps carrying a protocol version ``v`` and a type tag ``t``; numeric arrays travel as raw
little-endian bytes with their dtype and shape, so a batch of transitions costs one memory copy to
encode and none to decode (``wire.py``).

Receivers are never trusted: every ``decode_*`` function checks the size, msgpack limits, version,
type, field types, array dtypes (whitelist), shapes and finiteness, and raises exactly one
exception type, :class:`ProtocolError`, whose ``reason`` is a short category that services count
with :class:`RejectCounter` before dropping the message. Nothing here ever unpickles. What a
sender keeps until it is acknowledged, and how a receiver tells resends and restarts apart, is
``forcegrasp.delivery``.
"""

from forcegrasp.protocol.keys import Keys
from forcegrasp.protocol.messages import (
    Checkpoint,
    Progress,
    Stats,
    TransitionBatch,
    Weights,
    decode_checkpoint,
    decode_progress,
    decode_stats,
    decode_transitions,
    decode_weights,
    encode_checkpoint,
    encode_progress,
    encode_stats,
    encode_transitions,
    encode_weights,
)
from forcegrasp.protocol.wire import (
    ALLOWED_DTYPES,
    DEFAULT_LIMITS,
    PROTOCOL_VERSION,
    REASONS,
    ROOT,
    Limits,
    ProtocolError,
    RejectCounter,
    decode_array,
    encode_array,
    message_type,
    validate_name,
)

__all__ = [
    "ALLOWED_DTYPES", "DEFAULT_LIMITS", "PROTOCOL_VERSION", "REASONS", "ROOT", "Checkpoint", "Keys", "Limits",
    "Progress", "ProtocolError", "RejectCounter", "Stats", "TransitionBatch", "Weights", "decode_array",
    "decode_checkpoint", "decode_progress", "decode_stats", "decode_transitions", "decode_weights", "encode_array",
    "encode_checkpoint", "encode_progress", "encode_stats", "encode_transitions", "encode_weights", "message_type",
    "validate_name",
]
