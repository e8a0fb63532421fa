"""Recording framegate buffers to MCAP and reading them back (``record`` / ``play``).

The file layout is described in ``services.tools.bag._format``: one lossless ``framegate.Element``
channel per buffer (msgpack of timestamp, payload and metadata XML, with the buffer's kind
and retention in the channel metadata) and, for raw camera frames, a ``foxglove.RawImage``
channel that Foxglove shows as images. ``_derived`` adds the Foxglove channels a viewer draws
and plots (verdict and detection annotations, verdict and gyro-rate plots), which ``record``
writes and ``view`` streams live under the same topics.
"""

from services.lib.frame_layout import FrameLayout, frame_layout, metadata_kind

from ._derived import (
    DerivedMessage,
    DerivedTopic,
    Deriver,
    Marker,
    annotations_topic,
    derived_topics,
    detection_annotations,
    metadata_json,
    metadata_topic,
    rates_topic,
    read_markers,
    verdict_annotations,
    verdict_json,
    verdict_topic,
)
from ._format import (
    ELEMENT_MESSAGE_ENCODING,
    ELEMENT_SCHEMA_ENCODING,
    ELEMENT_SCHEMA_NAME,
    IMAGE_MESSAGE_ENCODING,
    IMAGE_SCHEMA_NAME,
    BagError,
    decode_element,
    element_topic,
    encode_element,
    image_topic,
)
from ._info import BufferRecord, ChannelInfo, RecordingInfo, recording_info, recording_started_ns
from ._reader import Bag, RecordedBuffer, open_bag
from ._recorder import STOP_SLACK_S, TAIL_FLOOR_S, Progress, Recorder, WriteQueue, at_start
from ._retime import shift_element, timestamp_fields
from ._scan import Integrity
from ._writer import COMPRESSIONS, BagWriter

__all__ = [
    "COMPRESSIONS",
    "ELEMENT_MESSAGE_ENCODING",
    "ELEMENT_SCHEMA_ENCODING",
    "ELEMENT_SCHEMA_NAME",
    "IMAGE_MESSAGE_ENCODING",
    "IMAGE_SCHEMA_NAME",
    "STOP_SLACK_S",
    "TAIL_FLOOR_S",
    "Bag",
    "BagError",
    "BagWriter",
    "BufferRecord",
    "ChannelInfo",
    "DerivedMessage",
    "DerivedTopic",
    "Deriver",
    "FrameLayout",
    "Integrity",
    "Marker",
    "Progress",
    "RecordedBuffer",
    "Recorder",
    "RecordingInfo",
    "WriteQueue",
    "annotations_topic",
    "at_start",
    "decode_element",
    "derived_topics",
    "detection_annotations",
    "element_topic",
    "encode_element",
    "frame_layout",
    "image_topic",
    "metadata_json",
    "metadata_kind",
    "metadata_topic",
    "open_bag",
    "rates_topic",
    "read_markers",
    "recording_info",
    "recording_started_ns",
    "shift_element",
    "timestamp_fields",
    "verdict_annotations",
    "verdict_json",
    "verdict_topic",
]
