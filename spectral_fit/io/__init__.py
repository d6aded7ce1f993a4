"""Files a user brings: spectral OpenEXR, meshes (OBJ, PLY, spheres), scene configs (TOML) and
measurement sessions.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from .._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "CameraColourSpec": "_scene",
    "CameraSpec": "_scene",
    "ColourChartSpec": "_scene",
    "DATA_KINDS": "_session",
    "DEFAULT_FREE": "_session",
    "DisplaySpec": "_scene",
    "EMISSIVE_UNITS": "_exr",
    "EnvironmentSpec": "_scene",
    "InterreflectionSpec": "_scene",
    "ImageReading": "_image_reading",
    "KINDS": "_session",
    "MARKER_DICTIONARIES": "_scene",
    "MAX_BLUR_PX": "_scene",
    "MAX_NOISE": "_scene",
    "MarkerSpec": "_scene",
    "SurfaceSpec": "_scene",
    "MaterialSpec": "_scene",
    "Mesh": "_mesh",
    "NoiseModel": "_noise",
    "ObjectMeasurement": "_session",
    "ObjectSpec": "_scene",
    "PARAMETERS": "_session",
    "PLY_PART_PROPERTIES": "_mesh",
    "PHYSICAL_LOWER": "_session",
    "RADIANCE_UNITS": "_spectrum_files",
    "Reading": "_session",
    "Scene": "_scene",
    "Session": "_session",
    "SpectralImage": "_exr",
    "SpectralSpec": "_scene",
    "WhiteStandard": "_session",
    "channel_name": "_exr",
    "concat_meshes": "_mesh",
    "estimate_noise": "_noise",
    "face_labels": "_mesh",
    "icosphere": "_mesh",
    "is_closed_outward": "_mesh",
    "load_labelled_mesh": "_mesh",
    "load_mesh": "_mesh",
    "load_obj": "_mesh",
    "load_ply": "_mesh",
    "load_image_pixels": "_image_reading",
    "load_scene": "_scene",
    "load_sensitivities": "_image_reading",
    "load_session": "_session_load",
    "parse_channel_name": "_exr",
    "parse_scene": "_scene",
    "parse_session": "_session_load",
    "read_channels_exr": "_exr",
    "read_rgb_exr": "_exr",
    "read_spectral_exr": "_exr",
    "read_spectral_exr_ex": "_exr",
    "rotate": "_mesh",
    "rotate_x": "_mesh",
    "rotate_y": "_mesh",
    "rotate_z": "_mesh",
    "scale": "_mesh",
    "select_faces": "_mesh",
    "sphere": "_mesh",
    "sphere_resolution": "_mesh",
    "transform_normals": "_mesh",
    "transform_points": "_mesh",
    "translate": "_mesh",
    "uv_sphere": "_mesh",
    "vertex_normals": "_mesh",
    "toml_value": "_session_write",
    "write_session": "_session_write",
    "write_spectral_exr": "_exr",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
