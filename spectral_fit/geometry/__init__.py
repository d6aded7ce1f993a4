"""Cameras and lenses, the watertight rasteriser, cluster culling, ray casting against meshes
(a bounding volume hierarchy), and the pytrees passed between rasterising and shading.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from .._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "BVH": "_bvh",
    "CLUSTER_SIZE": "_culling",
    "Camera": "_camera",
    "GBuffer": "_gbuffer",
    "MARGIN": "_culling",
    "ObjectGeometry": "_gbuffer",
    "PixelList": "_pixels",
    "PlanCounts": "_raster_plan",
    "Raster": "_raster",
    "RayHit": "_bvh",
    "SelfVisibility": "_visibility",
    "RasterConfig": "_raster_plan",
    "TILE_SIZES": "_raster_plan",
    "TriangleClusters": "_culling",
    "build_bvh": "_bvh",
    "is_convex": "_visibility",
    "fibonacci_directions": "_visibility",
    "octahedral_directions": "_visibility",
    "octahedral_taps": "_visibility",
    "octahedral_uv": "_visibility",
    "self_visibility": "_visibility",
    "build_clusters": "_culling",
    "capacity_ladder": "_raster_plan",
    "clear_plans": "_raster",
    "clip_to_pixel": "_raster_setup",
    "closest_hit": "_bvh",
    "cluster_rows": "_culling",
    "compact_flags": "_pixels",
    "count_clusters": "_culling",
    "covered_pixels": "_pixels",
    "default_config": "_raster_plan",
    "distort_eye": "_lens",
    "distort_normalized": "_lens",
    "edge_error_px": "_lens",
    "eye_position": "_camera",
    "grown_clusters": "_culling",
    "interpolate": "_interpolate",
    "interpolate_pixels": "_pixels",
    "interreflection_camera": "_camera",
    "intrinsics_matrix": "_camera",
    "intrinsics_to_projection": "_camera",
    "inverse_3x3": "_camera",
    "inverse_4x4": "_camera",
    "is_identity": "_lens",
    "lens_parameters": "_lens",
    "look_at": "_camera",
    "occluded": "_bvh",
    "opencv_pose_to_view": "_camera",
    "opencv_to_opengl_axes": "_camera",
    "perspective": "_camera",
    "perspective_camera": "_camera",
    "pixel_barycentrics": "_pixels",
    "pixel_rays": "_lens",
    "plan_config": "_raster_plan",
    "plan_counts": "_raster_plan",
    "project": "_camera",
    "projection_to_intrinsics": "_camera",
    "raster_jit": "_raster",
    "rasterize": "_raster",
    "rasterize_batch": "_raster",
    "relative_transform": "_camera",
    "scatter_pixels": "_pixels",
    "sized": "_culling",
    "spatial_order": "_culling",
    "undistort_normalized": "_lens",
    "view_to_opencv_pose": "_camera",
    "visible_clusters": "_culling",
    "worst_direction_count": "_culling",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
