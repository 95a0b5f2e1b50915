"""Board I/O: the wire protocol (:mod:`.wire`), the serial driver (:mod:`.driver`) and a simulated
board on a pseudo-terminal (:mod:`.sim`). Only :mod:`.driver` imports pyserial."""
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
