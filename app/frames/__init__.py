"""Full-frame images: star-camera frames -> the same Sequence as spot-list telemetry.

* :mod:`app.frames.images` reads FITS (astropy; a multi-extension FITS is a pass) and PNG, JPEG,
  TIFF 8/16 bit (Pillow), bounded by :class:`FrameLimits`;
* :mod:`app.frames.detect` finds and centroids stars with ``sep``, flags hot pixels, trails,
  extended and saturated blobs;
* :mod:`app.frames.hotpixels` keeps a camera's hot-pixel map and filters spot lists with it;
* :mod:`app.frames.assemble` turns the frames of one pass (with an optional ``tubsat-frames/1``
  sidecar) into a validated `tubsat-snapshots/1` Sequence.
"""

from app.frames.assemble import (FramePass, FramesTimeout, Sidecar, camera_for_fov, frames_content_sha256,
                                 frames_to_sequence, parse_sidecar)
from app.frames.detect import DetectionError, DetectionOptions, Detections, detect
from app.frames.hotpixels import HotPixelMap, drop_hot_pixel_sources, near_hot_pixel
from app.frames.images import Frame, FrameLimits, looks_like_image, peek_frame, read_frames

__all__ = ["DetectionError", "DetectionOptions", "Detections", "Frame", "FrameLimits", "FramePass",
           "FramesTimeout", "HotPixelMap", "Sidecar", "camera_for_fov", "detect", "drop_hot_pixel_sources",
           "frames_content_sha256", "frames_to_sequence", "looks_like_image", "near_hot_pixel", "parse_sidecar", "peek_frame",
           "read_frames"]
