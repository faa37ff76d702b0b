"""Camera frames: recorded (image folder, video file) for replay, live (device, stream, video
played in real time, watched folder) for the companion loop, and an MJPEG server that serves
frames as a camera stream."""

from orthonav.frames.live import (
    CameraStream,
    FolderWatch,
    Frame,
    LiveSource,
    VideoPlayback,
    capture_time_from_name,
    frame_filename,
    open_live_source,
)
from orthonav.frames.mjpeg import MjpegServer
from orthonav.frames.offline import (
    IMAGE_SUFFIXES,
    FrameSource,
    ImageFrames,
    VideoFrames,
    check_frame_size,
    list_images,
    open_frames,
    open_video,
)

__all__ = [
    "IMAGE_SUFFIXES",
    "CameraStream",
    "FolderWatch",
    "Frame",
    "FrameSource",
    "ImageFrames",
    "LiveSource",
    "MjpegServer",
    "VideoFrames",
    "VideoPlayback",
    "capture_time_from_name",
    "check_frame_size",
    "frame_filename",
    "list_images",
    "open_frames",
    "open_live_source",
    "open_video",
]
