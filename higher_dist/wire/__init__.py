"""The wire protocol: message schema, codec, episode batches, socket helpers and CURVE security.

Nothing here knows endpoints (launch/ does) or the algorithm (learning/ does); roles combine the three.
"""
from higher_dist.wire.codec import (MAGIC, REASONS, Message, WireError, check_weight_shapes, decode,
                                    decode_weights, encode, encode_weights)
from higher_dist.wire.episodes import pack_episodes, unpack_episodes
from higher_dist.wire.schema import MESSAGE_TYPES, PROTOCOL_VERSION, SPECS
from higher_dist.wire.sockets import (REJECTS, RejectCounter, bind_random, make_socket, recv_message,
                                      recv_routed, recv_weights, send, send_routed)

__all__ = [
    "MAGIC", "MESSAGE_TYPES", "PROTOCOL_VERSION", "REASONS", "REJECTS", "SPECS", "Message", "RejectCounter",
    "WireError", "bind_random", "check_weight_shapes", "decode", "decode_weights", "encode", "encode_weights",
    "make_socket", "pack_episodes", "recv_message", "recv_routed", "recv_weights", "send", "send_routed",
    "unpack_episodes",
]
