"""Mixed reality on video: markers, camera calibration, colour-matched compositing, video input and
output, the live loop.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from .._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "Calibration": "_calibration",
    "CalibrationTarget": "_calibration",
    "CameraModel": "_compositing",
    "ChartCalibration": "_compositing",
    "FrameTimings": "_frames",
    "LiveSession": "_session",
    "MARKER_AXES": "_synthetic_video",
    "MarkerDetection": "_markers",
    "MarkerDetector": "_markers",
    "MarkerPlacement": "_synthetic_video",
    "MarkerTracker": "_markers",
    "MR_TARGETS": "_mr_score",
    "Poses": "_markers",
    "RunStats": "_frames",
    "STEP_TRACES": "_step",
    "Table": "_synthetic_video",
    "VideoSink": "_video",
    "VideoSource": "_video",
    "aruco_dictionary": "_markers",
    "calibrate_camera": "_calibration",
    "calibrate_colour": "_compositing",
    "calibrate_images": "_calibration",
    "camera_model_from_colorchecker": "_compositing",
    "calibrate_colour_samples": "_compositing",
    "chart_camera_model": "_chart_video",
    "chart_corners_in_frame": "_chart_video",
    "chart_corners_world": "_chart_video",
    "VideoChart": "_chart_video",
    "camera_model_from_sensitivities": "_compositing",
    "camera_model_from_spec": "_compositing",
    "camera_output_matrix": "_step",
    "camera_spectral_matrix": "_step",
    "camera_pose_looking_at": "_synthetic_video",
    "camera_sensitivities": "_compositing",
    "chart_xyz": "_compositing",
    "colorchecker_reflectances": "_compositing",
    "colour_config_text": "_compositing",
    "composite": "_compositing",
    "composite_pixels": "_compositing",
    "relight": "_compositing",
    "count_frames": "_video",
    "decode_frame": "_compositing",
    "detect_target": "_calibration",
    "encode_frame": "_compositing",
    "estimate_marker_pose": "_markers",
    "fit_colour_matrix": "_compositing",
    "frame_delta_e00": "_compositing",
    "ground_frame": "_markers",
    "live_step": "_step",
    "make_table": "_synthetic_video",
    "marker_object_points": "_markers",
    "marker_pose_in_camera": "_synthetic_video",
    "mr_figure": "_mr_score",
    "pose_errors": "_mr_score",
    "score_mr": "_mr_score",
    "pipeline_pays": "_frames",
    "put_on_device": "_devices",
    "read_frames": "_video",
    "refine_corners_by_edges": "_markers",
    "render_table": "_synthetic_video",
    "sample_chart": "_compositing",
    "scene_camera_model": "_scene_camera",
    "scene_intrinsics": "_scene_camera",
    "target_image": "_calibration",
    "undistort_maps": "_calibration",
    "write_calibrated_config": "_calibration",
    "write_colour_config": "_compositing",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
