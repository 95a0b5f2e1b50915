"""Board I/O: the wire protocol (:mod:`.wire`), the serial driver (:mod:`.driver`) and a simulated
board (:mod:`.sim`) on a pseudo-terminal or an in-process virtual link (:mod:`.links`, opened as
``virtual://NAME``). Only :mod:`.driver` and its URL handler :mod:`.protocol_virtual` import pyserial."""
from .wire import (
    Ack,
    DataFrame,
    Decoder,
    DecoderStats,
    Error,
    Identify,
    Identity,
    SetCurrent,
    SetPattern,
    Start,
    Stop,
    TextDecoder,
    encode,
    encode_text,
)

__all__ = [
    "Ack", "DataFrame", "Decoder", "DecoderStats", "Error", "Identify", "Identity", "SetCurrent",
    "SetPattern", "Start", "Stop", "TextDecoder", "encode", "encode_text",
]
