"""The metadata of the services' buffers: build it, read it back (schemas/*.xsd).

camera/images and mediator/images hold ``frame`` elements (key = exposure start), gyro/rates
``gyro`` batches (key = last sample), mediator/decisions ``decision`` records (key = decision
time), detector/detections ``detections`` (key = the frame's timestamp).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from middleware import field_text, make_metadata, validate_metadata
from services.lib.camera_model import CameraModel
from services.lib.frame_layout import FrameError, FrameLayout
from services.lib.frame_pixels import frame_array
from services.lib.quality import Exposure, GyroSamples


@dataclass(frozen=True, slots=True)
class FrameMeta:
    """What a frame's metadata says."""

    timestamp_ns: int
    frame_id: int
    exposure: Exposure
    encoding: str
    width_px: int
    height_px: int
    camera: CameraModel | None


def frame_metadata(
    frame_id: int,
    exposure: Exposure,
    image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
    camera: CameraModel | None,
) -> bytes:
    """``frame`` metadata for an image exposed over ``exposure`` (key = exposure start); an
    OpenCV image, so its channels are gray (8 or 16 bits), BGR or BGRA."""
    if image.ndim == 2:
        encoding = "mono16" if image.dtype == np.uint16 else "mono8"
    else:
        encoding = "bgra8" if image.shape[2] == 4 else "bgr8"
    height, width = int(image.shape[0]), int(image.shape[1])
    return frame_metadata_of(frame_id, exposure, encoding, width, height, camera)


def frame_metadata_of(
    frame_id: int,
    exposure: Exposure,
    encoding: str,
    width_px: int,
    height_px: int,
    camera: CameraModel | None,
) -> bytes:
    """``frame`` metadata from its fields (a source with no image array, e.g. a bridge)."""
    fields: dict[str, Any] = {
        "frame_id": frame_id,
        "exposure_start_ns": exposure.start_ns,
        "exposure_ns": exposure.duration_ns,
        "encoding": encoding,
        "width_px": width_px,
        "height_px": height_px,
    }
    if camera is not None:
        fields["camera"] = camera.camera_fields()
    return make_metadata("frame", exposure.start_ns, fields)


def read_frame_metadata(metadata: bytes) -> FrameMeta:
    """Validate and read ``frame`` metadata."""
    root = validate_metadata(metadata, "frame")
    camera = (
        CameraModel.from_element(root) if root.find("{urn:framegate:1}camera") is not None else None
    )
    return FrameMeta(
        timestamp_ns=int(root.get("timestamp_ns")),
        frame_id=int(field_text(root, "frame_id") or 0),
        exposure=Exposure(
            int(field_text(root, "exposure_start_ns") or 0),
            int(field_text(root, "exposure_ns") or 0),
        ),
        encoding=str(field_text(root, "encoding")),
        width_px=int(field_text(root, "width_px") or 0),
        height_px=int(field_text(root, "height_px") or 0),
        camera=camera,
    )


# Longer than any exposure a vision camera takes, and farther than any exposure starts
# from its frame's stamp: schema-valid, but no frame.
MAX_EXPOSURE_NS = 10_000_000_000


def check_frame(meta: FrameMeta, payload_bytes: int) -> None:
    """The one check of a frame's size, exposure and encoding against its payload:
    FrameError for a frame no consumer could use, whatever its XSD allowed."""
    layout = FrameLayout.checked(meta.encoding, meta.width_px, meta.height_px)
    duration_ns = meta.exposure.duration_ns
    if not 0 < duration_ns <= MAX_EXPOSURE_NS:
        raise FrameError("bad-exposure", f"exposure of {duration_ns} ns")
    # The key is the exposure's start as the camera stamped it (a bridge's header stamp is
    # within a frame of it): a start far from the key pairs the frame with gyro data from
    # another moment, and the frame stays "without gyro coverage" forever.
    apart_ns = abs(meta.exposure.start_ns - meta.timestamp_ns)
    if apart_ns > MAX_EXPOSURE_NS:
        raise FrameError(
            "bad-exposure",
            f"exposure starts {apart_ns / 1e9:.3g} s from the frame's stamp",
        )
    layout.check_payload(payload_bytes, f"frame {meta.frame_id}")


def decode_image(payload: bytes, meta: FrameMeta) -> npt.NDArray[np.uint8] | npt.NDArray[np.uint16]:
    """The image as a read-only array view of the payload (no copy); FrameError if the
    payload does not hold the frame its metadata describes."""
    check_frame(meta, len(payload))
    layout = FrameLayout(meta.encoding, meta.width_px, meta.height_px)
    return frame_array(payload, layout)  # (h, w) for one channel, else (h, w, channels)


def gyro_metadata(samples: GyroSamples) -> bytes:
    """``gyro`` metadata for a batch (key = last sample time)."""
    first, last = int(samples.t_ns[0]), int(samples.t_ns[-1])
    rate = 1e9 / samples.period_ns if samples.period_ns else 1.0
    return make_metadata(
        "gyro",
        last,
        {
            "count": len(samples),
            "first_ns": first,
            "last_ns": last,
            "rate_hz": float(rate),
            "layout": "i8,f8,f8,f8",
        },
    )


def detections_metadata(
    timestamp_ns: int,
    frame_id: int,
    source: str,
    processing_ns: int,
    markers: list[tuple[int, list[float]]],
    *,
    scores: list[float | None] | None = None,
    taken_ns: int | None = None,
) -> bytes:
    """``detections`` metadata: the marker ids and corners (8 numbers) found in one frame,
    each one's score if any (``scores``, in the same order), and when the runner took the
    frame up (``taken_ns``)."""
    found: list[dict[str, Any]] = []
    for n, (label, corners) in enumerate(markers):
        marker: dict[str, Any] = {"id": label, "corners_px": corners}
        score = scores[n] if scores is not None else None
        if score is not None:
            marker["score"] = score
        found.append(marker)
    head: dict[str, Any] = {"frame_id": frame_id, "source": source}
    head["processing_ns"] = processing_ns
    if taken_ns is not None:
        head["taken_ns"] = taken_ns
    return make_metadata("detections", timestamp_ns, {**head, "marker": found})


def read_detections(metadata: bytes) -> tuple[int, list[int]]:
    """(frame_id, marker ids) of ``detections`` metadata."""
    root = validate_metadata(metadata, "detections")
    ids = [int(m.findtext("{urn:framegate:1}id")) for m in root.iter("{urn:framegate:1}marker")]
    return int(field_text(root, "frame_id") or 0), ids


@dataclass(frozen=True, slots=True)
class DecisionRecord:
    """One mediator decision as stored in mediator/decisions."""

    frame_timestamp_ns: int
    frame_id: int
    blur_px: float | None
    quality: float | None
    load: float
    accepted: bool
    reason: str
    policy: str
    b0_px: float
    latency_ns: int
    # When the mediator last saw the detector take a frame (wall clock), if it had.
    take_seen_ns: int | None = None

    def metadata(self, key_ns: int) -> bytes:
        fields: dict[str, Any] = {
            "frame_timestamp_ns": self.frame_timestamp_ns,
            "frame_id": self.frame_id,
        }
        if self.blur_px is not None and np.isfinite(self.blur_px):
            fields["blur_px"] = float(self.blur_px)
        if self.quality is not None:
            fields["quality"] = float(self.quality)
        fields |= {
            "load": float(min(1.0, max(0.0, self.load))),
            "accepted": bool(self.accepted),
            "reason": self.reason,
            "policy": self.policy,
            "b0_px": float(self.b0_px),
            "latency_ns": max(0, int(self.latency_ns)),
        }
        if self.take_seen_ns is not None and self.take_seen_ns >= 0:
            fields["take_seen_ns"] = int(self.take_seen_ns)
        return make_metadata("decision", key_ns, fields)

    @classmethod
    def from_metadata(cls, metadata: bytes) -> DecisionRecord:
        root = validate_metadata(metadata, "decision")

        def opt(name: str) -> float | None:
            text = field_text(root, name)
            return float(text) if text else None

        return cls(
            frame_timestamp_ns=int(field_text(root, "frame_timestamp_ns") or 0),
            frame_id=int(field_text(root, "frame_id") or 0),
            blur_px=opt("blur_px"),
            quality=opt("quality"),
            load=float(field_text(root, "load") or 0),
            accepted=field_text(root, "accepted") in ("true", "1"),
            reason=str(field_text(root, "reason")),
            policy=str(field_text(root, "policy")),
            b0_px=float(field_text(root, "b0_px") or 0),
            latency_ns=int(field_text(root, "latency_ns") or 0),
            take_seen_ns=int(seen) if (seen := field_text(root, "take_seen_ns")) else None,
        )
