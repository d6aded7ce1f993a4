"""Offline ground truth: our exact reflection model in Mitsuba 3 (optional extra ``validate``).

- :mod:`.bsdf`: ONE Mitsuba BSDF equal to the whole model α S/π + β F D G/(4 cosθi cosθr) + χ F δ
  (docs/conventions.md, 'External reference renderer'): summing per-term renders would drop the
  cross terms that are the interreflection.
- :mod:`.export`: a :class:`~spectral_fit.io.Scene` as a Mitsuba scene (meshes, camera,
  environment with our mapping and rotation).
- :mod:`.render`: spectral renders by the band trick (⌈L/3⌉ rgb renders), patches on spheres.
- :mod:`.patches`: the frame's 5×5 patch grid labelled by object / table (scenes of any shape).
- :mod:`.generate`: references from renders (sphere patches; any shape: the patch grid).
- :mod:`.data`: the committed references (``measurements/reference/*.npz``) and their loader.
- :mod:`.instrument`: a simulated spectroradiometer (SR-3A-like readings).

Loader API (needs no Mitsuba)::

    from spectral_fit.validation.reference import load_reference
    ref = load_reference("benchmark")        # or "two_spheres", or a path to an .npz
    ref.wavelengths (L,), ref.boxes (P, 4) x0, y0, x1, y1, ref.spectra (P, L) with
    interreflection, ref.direct (P, L) without, ref.noise / ref.noise_direct (P, L) standard
    errors, ref.labels (P,) "direct" | "interreflection", ref.ir_fraction (P,),
    ref.patch_means(image (H, W, L)) -> (P, L), ref.xyz() -> (P, 3)

Everything that needs Mitsuba imports it lazily (:func:`.backend.init_mitsuba`).
"""

from __future__ import annotations

from ..._runtime.lazy import lazy_exports

_EXPORTS = {
    "Reference": "data",
    "load_reference": "data",
    "save_reference": "data",
    "REFERENCE_DIR": "data",
    "init_mitsuba": "backend",
    "mitsuba_available": "backend",
    "render_spectral": "render",
    "SpectralRender": "render",
    "sphere_patches": "render",
    "make_reference": "generate",
    "make_mesh_reference": "generate",
    "raster_patches": "generate",
    "render_grid": "generate",
    "Spectroradiometer": "instrument",
    "simulate_readings": "instrument",
}

__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
