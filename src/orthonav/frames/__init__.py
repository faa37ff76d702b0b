"""Camera frames: recorded (image folder, video file) for replay, live (device, stream, video
played in real time, watched folder) for the companion loop, and an MJPEG server that serves
frames as a camera stream; frames rendered from an orthophoto at a known pose, the north-up
view of a frame that keypoint matching and the global index take, and the views of frame and
map that dense correlation compares."""

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
    MATCHES_PREFIX,
    CheckedCapture,
    FrameSource,
    ImageFrames,
    Unreadable,
    VideoFrames,
    check_frame_size,
    list_images,
    load_frame,
    load_or_unreadable,
    open_frames,
    open_video,
)
from orthonav.frames.render import Photometric, TruePose, render_frame, sees_only_ground
from orthonav.frames.views import NorthUp, ViewGeometry, Views, make_views, north_up

__all__ = [
    "IMAGE_SUFFIXES",
    "MATCHES_PREFIX",
    "CameraStream",
    "CheckedCapture",
    "FolderWatch",
    "Frame",
    "FrameSource",
    "ImageFrames",
    "LiveSource",
    "MjpegServer",
    "NorthUp",
    "Photometric",
    "TruePose",
    "Unreadable",
    "VideoFrames",
    "VideoPlayback",
    "ViewGeometry",
    "Views",
    "capture_time_from_name",
    "check_frame_size",
    "frame_filename",
    "list_images",
    "load_frame",
    "load_or_unreadable",
    "make_views",
    "north_up",
    "open_frames",
    "open_live_source",
    "open_video",
    "render_frame",
    "sees_only_ground",
]
