"""A Foxglove WebSocket protocol client for tests and benches (the ``websockets``
package, synchronous): what the Foxglove app does on connecting, in a few calls; and a
protobuf wire-format reader for the FrameTransforms live_view sends on /tf (no protobuf
runtime is installed).

Protocol (ws-protocol spec, the same wire format under ``foxglove.websocket.v1`` and
``foxglove.sdk.v1``): JSON text frames ``{"op": ...}`` (serverInfo, advertise,
subscribe...); binary frames with a one-byte opcode, message data being
``0x01 | uint32 subscription id | uint64 log time [ns] | payload`` (little endian).
"""

import json
import re
import struct
import time

from websockets.sync.client import connect

SDK_SUBPROTOCOL = 'foxglove.sdk.v1'
MESSAGE_DATA = 0x01
_HEADER = struct.Struct('<BIQ')


def live_view_url(log_text):
    """The ws:// URL live_view logged on start-up, or None yet."""
    match = re.search(r'serving the graph to Foxglove at (ws://\S+)', log_text)
    return match.group(1) if match else None


class FoxgloveClient:
    """One connection: ``channels`` {topic: advertised channel dict}; ``subscribe``
    topics, then ``receive`` message data as (topic, log_time_ns, payload)."""

    def __init__(self, url, subprotocol=SDK_SUBPROTOCOL, open_timeout=10.0):
        # Entered by hand: the connection outlives this constructor (closed by close()).
        self.ws = connect(
            url, subprotocols=[subprotocol], max_size=None, open_timeout=open_timeout
        ).__enter__()
        self.server_info = None
        self.channels = {}  # topic -> channel (the advertise entry)
        self._by_id = {}  # channel id -> channel
        self._subscriptions = {}  # subscription id -> topic
        self.received_bytes = 0

    @property
    def subprotocol(self):
        return self.ws.subprotocol

    def close(self):
        self.ws.close()

    def _handle_text(self, text):
        message = json.loads(text)
        if message['op'] == 'serverInfo':
            self.server_info = message
        elif message['op'] == 'advertise':
            for channel in message['channels']:
                self.channels[channel['topic']] = channel
                self._by_id[channel['id']] = channel
        elif message['op'] == 'unadvertise':
            for channel_id in message['channelIds']:
                channel = self._by_id.pop(channel_id, None)
                if channel is not None:
                    self.channels.pop(channel['topic'], None)

    def _next(self, timeout):
        """One frame handled; returns (topic, log_time_ns, payload) for message data,
        else None. Raises TimeoutError when nothing came within ``timeout`` [s]."""
        frame = self.ws.recv(timeout=timeout)
        if isinstance(frame, str):
            self._handle_text(frame)
            return None
        self.received_bytes += len(frame)
        if frame[0] != MESSAGE_DATA:
            return None
        _, subscription_id, log_time_ns = _HEADER.unpack_from(frame)
        topic = self._subscriptions.get(subscription_id)
        return None if topic is None else (topic, log_time_ns, frame[_HEADER.size :])

    def wait_for_channels(self, topics, timeout):
        """Handle frames until every topic in ``topics`` is advertised."""
        deadline = time.monotonic() + timeout
        while not set(topics) <= set(self.channels):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                missing = sorted(set(topics) - set(self.channels))
                raise TimeoutError(f'not advertised within {timeout:.0f} s: {missing}')
            try:
                self._next(remaining)
            except TimeoutError:
                pass
        return self.channels

    def subscribe(self, topics):
        subscriptions = []
        for topic in topics:
            channel = self.channels[topic]
            subscription_id = channel['id']  # one subscription per channel
            self._subscriptions[subscription_id] = topic
            subscriptions.append({'id': subscription_id, 'channelId': channel['id']})
        self.ws.send(json.dumps({'op': 'subscribe', 'subscriptions': subscriptions}))

    def receive(self, timeout):
        """The next message data (topic, log_time_ns, payload); TimeoutError if none
        within ``timeout`` [s]."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f'no message data within {timeout:.0f} s')
            message = self._next(remaining)
            if message is not None:
                return message

    def receive_until(self, done, timeout, what):
        """Receive until ``done(topic, log_time_ns, payload)`` is true; returns that message."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f'timed out after {timeout:.0f} s waiting for {what}')
            try:
                message = self.receive(remaining)
            except TimeoutError:
                continue
            if done(*message):
                return message


# -- protobuf wire format (enough for foxglove.FrameTransforms) ---------------------------


def _varint(data, offset):
    value = shift = 0
    while True:
        byte = data[offset]
        offset += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, offset


def protobuf_fields(data):
    """{field number: [values]} of one protobuf message: ints for varints, bytes for
    length-delimited fields, floats for 64-bit ones (doubles; fixed64 is unused here)."""
    fields = {}
    offset = 0
    while offset < len(data):
        key, offset = _varint(data, offset)
        number, wire_type = key >> 3, key & 7
        if wire_type == 0:
            value, offset = _varint(data, offset)
        elif wire_type == 1:
            value = struct.unpack_from('<d', data, offset)[0]
            offset += 8
        elif wire_type == 2:
            length, offset = _varint(data, offset)
            value = bytes(data[offset : offset + length])
            offset += length
        elif wire_type == 5:
            value = struct.unpack_from('<f', data, offset)[0]
            offset += 4
        else:
            raise ValueError(f'unsupported protobuf wire type {wire_type}')
        fields.setdefault(number, []).append(value)
    return fields


def decode_frame_transforms(payload):
    """foxglove.FrameTransforms -> [{parent, child, translation (x, y, z), rotation
    (x, y, z, w)}] (proto3 leaves zero values out: they read as 0, w as well)."""
    transforms = []
    for item in protobuf_fields(payload).get(1, []):
        fields = protobuf_fields(item)
        translation = protobuf_fields(fields.get(4, [b''])[0])
        rotation = protobuf_fields(fields.get(5, [b''])[0])
        transforms.append(
            {
                'parent': fields.get(2, [b''])[0].decode(),
                'child': fields.get(3, [b''])[0].decode(),
                'translation': tuple(translation.get(i, [0.0])[0] for i in (1, 2, 3)),
                'rotation': tuple(rotation.get(i, [0.0])[0] for i in (1, 2, 3, 4)),
            }
        )
    return transforms
