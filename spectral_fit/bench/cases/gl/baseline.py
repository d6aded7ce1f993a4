"""The paper's two-pass pipeline in OpenGL 4.5 (moderngl, headless EGL): the comparison baseline.

Mochizuki & Tanaka's method as a GPU rasteriser implements it, on the same inputs as the JAX
renderer's ``mode="paper"`` frame (eq. 5 + eq. 6, quality "fast"):

* **Precomputation** (once, NumPy/JAX, not part of a frame): :func:`baseline_inputs` takes a
  :class:`~spectral_fit.rendering.Prepared` scene (``prepare(scene, mode="paper")``): the
  spectral environment map, its order-2 SH irradiance, the irradiance map over normals, the
  split-sum prefiltered levels in the map's principal spectra, each material's gloss-lobe moment
  table, the meshes, cameras, XYZ weights and display matrix. :class:`BaselineInputs` holds
  them as NumPy arrays (``save`` / ``load``: a frame needs no JAX at all).
* **Per frame** (:meth:`GLBaseline.render`), all in OpenGL:

  1. pass 1, for every ordered pair (receiver i, sender j): j rendered from i's centre looking
     at j's centre (90° vertical FOV, ``texture_size``², back faces culled) into 8 RGBA32F
     targets (31 bands + a pad): T_d = α_j S_j E_sh(N)/π and T_s = β_j I_gloss + χ_j F L(R),
     shaded with the view towards i's centre, stored as α_i/π · T_d + γ_i · T_s (eq. 6's two
     textures, already weighted by the receiver's α_paper and γ: the lookup is linear, so one
     texture set per pair carries both);
  2. pass 2: the background (the spectral map through each pixel centre), then the objects from
     the camera: α S I_d(N)/π (irradiance map, bilinear) + β I_gloss (split sum: lobe albedo
     times 4 lookups of the prefiltered map along the lobe) + χ F L(R), plus, where the fragment
     projects into a sender's pass-1 view (in front, inside, facing the sender), the bilinear
     lookup of that pair's texture set (clamp to edge, 0 outside the sender);
  3. spectra → absolute XYZ → display RGB (exposure, 3 × 3, clip, sRGB curve) in the shader;
     the image read back as 8-bit RGB.

Without interreflection (``interreflection=False``) pass 1 is skipped.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ...._runtime.errors import InputError, SpectralFitError
from . import shaders

if TYPE_CHECKING:  # for annotations (the renderer is imported where it is used)
    from ....rendering import Prepared

__all__ = ["GLUnavailable", "BaselineInputs", "baseline_inputs", "create_context", "GLBaseline",
           "MAX_SENDERS"]

#: most senders per receiver (8 texture units each; llvmpipe has 32 per shader stage)
MAX_SENDERS = 3

# texture units
_ENV_UNIT, _LUT_UNIT, _GLOSS_UNIT, _IR_UNIT0 = 0, 1, 2, 3


class GLUnavailable(SpectralFitError):
    """moderngl is not installed, or no headless OpenGL 4.5 context can be made through EGL."""


def create_context() -> Any:
    """A standalone moderngl context through EGL (Mesa's llvmpipe on a machine without a GPU).

    Raises:
        GLUnavailable: moderngl missing, EGL/Mesa missing, or OpenGL older than 4.5 (one-line
            message saying what to install).
    """
    try:
        import moderngl
    except ImportError:
        raise GLUnavailable("the OpenGL baseline needs moderngl: pip install "
                            "'spectral_fit[gl]' (or: pip install moderngl)") from None
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl")
    except Exception as exc:  # noqa: BLE001 - EGL reports many kinds of failure
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise GLUnavailable(
            f"no headless OpenGL context through EGL ({first}); install Mesa's EGL and DRI "
            "drivers (Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri)") from None
    if ctx.version_code < 450:
        version = ctx.info.get("GL_VERSION", "?")
        ctx.release()
        raise GLUnavailable(f"the OpenGL baseline needs OpenGL 4.5, the EGL context has "
                            f"{version}")
    return ctx


@dataclasses.dataclass(frozen=True)
class BaselineInputs:
    """Everything a frame of the baseline uploads (NumPy; float arrays float32 unless noted).

    Attributes:
        shape: (H, W) frame size in pixels.
        wavelengths: (C,) band centres (nm).
        env: (Hm, Wm, C) spectral radiance of the environment map (W·sr⁻¹·m⁻²·nm⁻¹).
        env_poles: (2, C) means of its first and last rows (the lookup's pole values).
        to_map: (3, 3) map-frame from world rotation (d_map = to_map @ d_world).
        sh: (9, C) order-2 SH coefficients of the map's radiance (R&H order, map frame).
        lut: (Hl, Wl, C) irradiance E(N) at the texel centres of a grid of normals (map frame).
        lut_poles: (2, C) irradiance at the two poles.
        levels: prefiltered levels of the split-sum gloss, each (H_k, W_k, r) in the map's r
            principal spectra; level_poles: each (2, r).
        level_sigma: (M,) prefilter std of each level (rad), level 0 = 0.
        per_octave: levels per octave of std.
        basis: (r, C) the principal spectra.
        along: (k, 2) offsets (std units) and weights of the lookups along the lobe.
        min_ratio, horizon_ratio: split-sum settings (see ``environment.SplitSum``).
        materials: (O, 6) α, β, χ, γ, n, μ per object; reflectance: (O, C).
        moments: (O, T, 4) each material's gloss-lobe moment table (A, δ, var_t, var_b) at
            cosθr = 1 − x², x = j/(T − 1).
        vertices, normals: per object (V_o, 3) object-frame positions (m) and unit normals;
        triangles: per object (T_o, 3) int32, counter-clockwise seen from outside.
        model: (O, 4, 4) world from object; view (4, 4) world → eye; projection (4, 4).
        pair_vp: (P, 4, 4) pass-1 clip-from-world of each ordered pair (i, j), i ≠ j, in the
            order i·(O − 1) + k (j = k for k < i, else k + 1).
        texture_size: side of the pass-1 targets (texels).
        to_xyz: (C, 3) radiance → absolute XYZ (cd/m²).
        display: (3, 3) XYZ → display linear RGB (exposure folded in) and display_offset (3,).
        tone: "srgb" | "gamma" | "linear"; tone_gamma: the exponent of "gamma".
        exposure: luminance (cd/m²) shown as display white; white_xyz: (3,) XYZ of that white
            (the display white at the exposure, float64).
        cull: "back" or "none" (camera and pass-1 face culling).
    """

    shape: tuple[int, int]
    wavelengths: np.ndarray
    env: np.ndarray
    env_poles: np.ndarray
    to_map: np.ndarray
    sh: np.ndarray
    lut: np.ndarray
    lut_poles: np.ndarray
    levels: tuple[np.ndarray, ...]
    level_poles: tuple[np.ndarray, ...]
    level_sigma: np.ndarray
    per_octave: int
    basis: np.ndarray
    along: np.ndarray
    min_ratio: float
    horizon_ratio: float
    materials: np.ndarray
    reflectance: np.ndarray
    moments: np.ndarray
    vertices: tuple[np.ndarray, ...]
    normals: tuple[np.ndarray, ...]
    triangles: tuple[np.ndarray, ...]
    model: np.ndarray
    view: np.ndarray
    projection: np.ndarray
    pair_vp: np.ndarray
    texture_size: int
    to_xyz: np.ndarray
    display: np.ndarray
    display_offset: np.ndarray
    tone: str
    tone_gamma: float
    exposure: float
    white_xyz: np.ndarray
    cull: str

    @property
    def num_objects(self) -> int:
        return int(self.model.shape[0])

    @property
    def channels(self) -> int:
        return int(self.env.shape[-1])

    def save(self, path: str | Path) -> None:
        """Write the inputs to an ``.npz`` file (:meth:`load` reads it back)."""
        arrays: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, tuple) and v and isinstance(v[0], np.ndarray):
                arrays[f"{f.name}__n"] = np.asarray(len(v))
                for k, a in enumerate(v):
                    arrays[f"{f.name}__{k}"] = a
            else:
                arrays[f.name] = np.asarray(v)
        np.savez(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> BaselineInputs:
        """Read inputs written by :meth:`save`."""
        with np.load(path, allow_pickle=False) as z:
            kw: dict[str, Any] = {}
            for f in dataclasses.fields(cls):
                if f"{f.name}__n" in z:
                    kw[f.name] = tuple(z[f"{f.name}__{k}"] for k in range(int(z[f"{f.name}__n"])))
                else:
                    v = z[f.name]
                    kw[f.name] = v.item() if v.ndim == 0 else v
        kw["shape"] = tuple(int(s) for s in kw["shape"])
        kw["texture_size"] = int(kw["texture_size"])
        kw["per_octave"] = int(kw["per_octave"])
        return cls(**kw)


def _binomial_rule(k: int) -> np.ndarray:
    """(k, 2): k binomial nodes at (j − (k−1)/2)·2/√(k−1) std with weights C(k−1, j)/2^(k−1)
    (a discrete Gaussian of unit variance)."""
    j = np.arange(k)
    w = np.array([math.comb(k - 1, int(i)) for i in j], np.float64) / 2.0 ** (k - 1)
    x = (j - 0.5 * (k - 1)) * (2.0 / math.sqrt(k - 1) if k > 1 else 0.0)
    return np.stack([x, w], axis=-1)


def _pairs(n: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(n) for j in range(n) if j != i]


def baseline_inputs(prep: Prepared, *, pass1_fov_deg: float = 90.0) -> BaselineInputs:
    """The baseline's inputs from a prepared scene (:func:`~spectral_fit.rendering.prepare`,
    spectral bands, quality "fast", irradiance map): the same precomputed environment,
    materials, meshes, cameras and display as the JAX frame of that ``prep``.
    ``pass1_fov_deg``: the pass-1 cameras' vertical field of view (the JAX renderer's 90°;
    a narrower view spreads the sender over more of the ``texture_size``² texels).

    Raises:
        InputError: a scene the baseline does not render (basis mode, more than 32 bands, an
            environment with explicit source texels, more than ``MAX_SENDERS`` + 1 objects,
            a lens, another quality).
    """
    import jax
    import jax.numpy as jnp

    from ....color import display_linear
    from ....geometry import interreflection_camera
    from ....lighting import lobe_moment_table

    lit, col, cam, mesh = prep.lighting, prep.colour, prep.camera, prep.mesh
    if col.spectral_mode != "bands":
        raise InputError("the OpenGL baseline renders spectral bands only", field="spectral_mode")
    if lit.quality != "fast" or lit.split_map is None:
        raise InputError("the OpenGL baseline renders quality 'fast' only", field="quality")
    if lit.irradiance_lut is None:
        raise InputError("the OpenGL baseline needs the irradiance map (diffuse='map')",
                         field="diffuse")
    if cam.lens is not None:
        raise InputError("the OpenGL baseline renders a pinhole camera only",
                         field="camera.distortion")
    env = lit.env
    c = int(env.channels)
    if c > 32:
        raise InputError(f"at most 32 bands (8 RGBA targets), got {c}", field="spectral")
    if int(env.source_flux.shape[0]):
        raise InputError("the environment has bright source texels (summed exactly by the JAX "
                         "renderer); the OpenGL baseline does not render them",
                         field="environment")
    n_obj = prep.num_objects
    if n_obj - 1 > MAX_SENDERS:
        raise InputError(f"at most {MAX_SENDERS + 1} objects, got {n_obj}", field="objects")

    texels = np.asarray(env.texels, np.float32)
    hl_wl = int(lit.irradiance_lut.shape[0]) - 2
    hl = int(round(math.sqrt(hl_wl / 2)))
    lut_flat = np.asarray(lit.irradiance_lut, np.float32)
    sm = lit.split_map
    atlas = np.asarray(sm.atlas, np.float32)
    table = np.asarray(sm.level_table)
    levels, level_poles = [], []
    for off, h, w in table:
        off, h, w = int(off), int(h), int(w)
        levels.append(atlas[off:off + h * w].reshape(h, w, -1))
        level_poles.append(atlas[off + h * w:off + h * w + 2])
    settings = lit.split_settings
    mats = prep.materials
    params = np.stack([np.asarray(getattr(mats, f), np.float64)
                       for f in ("alpha", "beta", "chi", "gamma", "n", "mu")], axis=-1)
    # one compiled table for all materials, as the frame computes them
    table_fn = jax.jit(jax.vmap(functools.partial(
        lobe_moment_table, distribution=mats.distribution, geometry=mats.geometry,
        settings=settings)))
    moments = np.asarray(table_fn(jnp.asarray(mats.mu, jnp.float32),
                                  jnp.asarray(mats.n, jnp.float32)))
    verts, nrms, tris = [], [], []
    for (a, b), (ta, tb) in zip(mesh.object_slices, mesh.triangle_slices, strict=True):
        verts.append(np.asarray(mesh.vertices[a:b], np.float32))
        nrms.append(np.asarray(mesh.normals[a:b], np.float32))
        tris.append(np.asarray(mesh.triangles[ta:tb], np.int32) - a)
    model = np.asarray(prep.model, np.float64)
    centres = model[:, :3, 3]
    pair_vp = np.zeros((0, 4, 4))
    if n_obj > 1:
        pair_vp = np.stack([np.asarray(interreflection_camera(
            centres[i].astype(np.float32), centres[j].astype(np.float32), aspect=1.0,
            fov_y_deg=pass1_fov_deg).view_projection, np.float64) for i, j in _pairs(n_obj)])
    display = col.display
    kw = dict(exposure_luminance=float(col.exposure), display=display,
              scene_white_xy=col.scene_white_xy)
    offset = -np.asarray(display_linear(np.zeros(3), **kw), np.float64)
    disp = np.stack([np.asarray(display_linear(e, **kw), np.float64) + offset
                     for e in np.eye(3)], axis=-1)  # columns: the images of X, Y, Z
    import colour

    white = np.asarray(colour.xy_to_XYZ(display.white_xy), np.float64) * float(col.exposure)
    return BaselineInputs(
        shape=tuple(int(s) for s in cam.shape),
        wavelengths=np.asarray(col.wavelengths, np.float64),
        env=texels, env_poles=np.asarray(env.poles, np.float32),
        to_map=np.asarray(env.rotation, np.float64).T,
        sh=np.asarray(env.sh, np.float32),
        lut=lut_flat[:-2].reshape(hl, hl_wl // hl, c), lut_poles=lut_flat[-2:],
        levels=tuple(levels), level_poles=tuple(level_poles),
        level_sigma=np.asarray(sm.level_sigma, np.float64), per_octave=int(sm.per_octave),
        basis=np.asarray(env.spectral_basis, np.float32),
        along=_binomial_rule(int(settings.along)),
        min_ratio=float(settings.min_ratio), horizon_ratio=float(settings.horizon_ratio),
        materials=params, reflectance=np.asarray(mats.reflectance, np.float32),
        moments=moments.astype(np.float32),
        vertices=tuple(verts), normals=tuple(nrms), triangles=tuple(tris),
        model=model, view=np.asarray(cam.view, np.float64),
        projection=np.asarray(cam.projection, np.float64), pair_vp=pair_vp,
        texture_size=int(prep.interreflection.texture_size),
        to_xyz=np.asarray(col.to_xyz, np.float64),
        display=disp, display_offset=offset, tone=display.tone,
        tone_gamma=float(display.gamma), exposure=float(col.exposure), white_xyz=white,
        cull=cam.cull,
    )


# --------------------------------------------------------------------------------------------
# OpenGL


def _layers(a: np.ndarray, layers: int) -> np.ndarray:
    """(..., C) → (layers, ..., 4) float32: channels 4i … 4i + 3 in layer i, zero padded."""
    c = a.shape[-1]
    out = np.zeros((*a.shape[:-1], 4 * layers), np.float32)
    out[..., :c] = a
    out = out.reshape(*a.shape[:-1], layers, 4)
    return np.ascontiguousarray(np.moveaxis(out, -2, 0))


def _padded(grid: np.ndarray, poles: np.ndarray) -> np.ndarray:
    """(H, W, C) map + (2, C) pole values → (H + 2, W + 2, C): the north pole's row above, the
    south pole's below, the last column copied before the first and the first after the last
    (the grid whose GPU bilinear filter, with ``grid_coord``'s remap, is the map lookup)."""
    h, w, c = grid.shape
    rows = np.concatenate([np.broadcast_to(poles[0], (1, w, c)), grid,
                           np.broadcast_to(poles[1], (1, w, c))])
    return np.ascontiguousarray(np.concatenate([rows[:, -1:], rows, rows[:, :1]], axis=1))


def _vec4s(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, np.float32).tobytes()


def _mat_bytes(m: np.ndarray) -> bytes:
    """A matrix as GLSL reads it (column-major)."""
    return np.ascontiguousarray(np.asarray(m).T, np.float32).tobytes()


class GLBaseline:
    """The two-pass OpenGL renderer of one scene (see the module docstring).

    ``GLBaseline(inputs)`` uploads the textures and buffers and compiles the programs
    (``setup_s``); :meth:`render` draws one frame. Use it as a context manager, or call
    :meth:`release`.

    Options that add work without changing the image (for timing against other
    implementations of the pipeline that do it): ``cull="none"`` draws back faces too (the
    depth test keeps the nearest); ``pass1_mipmaps`` builds the mip chain of every pass-1
    target each frame (for blurred lookups; the frame reads level 0);
    ``interreflection_everywhere`` runs the pass-2 texture lookups on every object fragment,
    weighting those outside a sender's view by zero.
    """

    def __init__(self, inputs: BaselineInputs, ctx: Any = None, *, cull: str | None = None,
                 pass1_mipmaps: bool = False, interreflection_everywhere: bool = False
                 ) -> None:
        import moderngl

        t0 = time.perf_counter()
        self.inputs = inp = inputs
        self.cull = inputs.cull if cull is None else cull
        self.pass1_mipmaps = bool(pass1_mipmaps)
        self.interreflection_everywhere = bool(interreflection_everywhere)
        if self.cull not in ("back", "none"):
            raise InputError(f"must be 'back' or 'none', got {cull!r}", field="cull")
        self.ctx = ctx if ctx is not None else create_context()
        self._own_ctx = ctx is None
        self.nb = (inp.channels + 3) // 4
        self.nr = (int(inp.basis.shape[0]) + 3) // 4
        self.n_obj = inp.num_objects
        self.ns = max(self.n_obj - 1, 1)
        self._sizes = dict(nb=self.nb, nr=self.nr, nlev=len(inp.levels),
                           nalong=int(inp.along.shape[0]), ntab=int(inp.moments.shape[1]),
                           ns=self.ns)
        ctx = self.ctx
        # ---- textures: environment, irradiance map, gloss levels (padded grids)
        self.env_tex = self._grid_texture(_padded(inp.env, inp.env_poles), self.nb)
        self.lut_tex = self._grid_texture(_padded(inp.lut, inp.lut_poles), self.nb)
        rects, padded = [], []
        y = 0
        for lev, poles in zip(inp.levels, inp.level_poles, strict=True):
            p = _padded(lev, poles)
            rects.append((0.0, float(y), float(lev.shape[1]), float(lev.shape[0])))
            padded.append(p)
            y += p.shape[0]
        aw = max(p.shape[1] for p in padded)
        atlas = np.zeros((y, aw, padded[0].shape[-1]), np.float32)
        for (_, y0, _, _), p in zip(rects, padded, strict=True):
            atlas[int(y0):int(y0) + p.shape[0], :p.shape[1]] = p
        self.gloss_tex = self._grid_texture(atlas, self.nr, repeat=False)
        self._gloss_rects = np.asarray(rects, np.float32)
        self._gloss_atlas = (float(aw), float(y))
        # ---- meshes
        self._vbo, self._ibo = [], []
        for v, n, t in zip(inp.vertices, inp.normals, inp.triangles, strict=True):
            self._vbo.append(ctx.buffer(np.concatenate([v, n], axis=1).astype("f4").tobytes()))
            self._ibo.append(ctx.buffer(np.asarray(t, "u4").tobytes()))
        # ---- programs
        self.p1 = self._program(shaders.FS_PASS1)
        self.p2 = self._program(shaders.FS_PASS2)
        self.pbg = self._program(shaders.FS_BACKGROUND, vertex=shaders.VS_BACKGROUND)
        self._vao1 = [self._mesh_vao(self.p1, o) for o in range(self.n_obj)]
        self._vao2 = [self._mesh_vao(self.p2, o) for o in range(self.n_obj)]
        self._vao_bg = ctx.vertex_array(self.pbg, [])
        self._xyz_programs: tuple[Any, ...] | None = None
        # ---- pass-1 targets: per pair, NB RGBA32F colour targets and a depth buffer
        t = inp.texture_size
        self.pairs = _pairs(self.n_obj)
        self._ir: list[dict[str, Any]] = []
        for p, (i, j) in enumerate(self.pairs):
            texs = []
            for _ in range(self.nb):
                tex = ctx.texture((t, t), 4, dtype="f4")
                tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
                tex.repeat_x = tex.repeat_y = False
                texs.append(tex)
            fbo = ctx.framebuffer(color_attachments=texs,
                                  depth_attachment=ctx.depth_renderbuffer((t, t)))
            self._ir.append(dict(receiver=i, sender=j, texs=texs, fbo=fbo, vp=inp.pair_vp[p]))
        # ---- camera target
        h, w = inp.shape
        self.fbo = ctx.framebuffer(color_attachments=[ctx.texture((w, h), 4)],
                                   depth_attachment=ctx.depth_renderbuffer((w, h)))
        self._fbo_xyz: Any = None
        self._cam_vp = inp.projection @ inp.view
        self._eye = -np.linalg.solve(inp.view[:3, :3], inp.view[:3, 3])
        for prog in (self.p1, self.p2, self.pbg):
            self._set_common(prog)
        ctx.finish()
        self.setup_s = time.perf_counter() - t0

    # -- construction helpers

    def _grid_texture(self, grid: np.ndarray, layers: int, repeat: bool = True) -> Any:
        import moderngl

        h, w = grid.shape[:2]
        tex = self.ctx.texture_array((w, h, layers), 4, _layers(grid, layers).tobytes(),
                                     dtype="f4")
        tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        tex.repeat_x = tex.repeat_y = False  # the padding does the wrap and the poles
        return tex

    def _program(self, body: str, *, vertex: str = shaders.VS_MESH, xyz: bool = False) -> Any:
        return self.ctx.program(vertex_shader=vertex,
                                fragment_shader=shaders.source(body, xyz=xyz, **self._sizes))

    def _mesh_vao(self, prog: Any, o: int) -> Any:
        return self.ctx.vertex_array(prog, [(self._vbo[o], "3f 3f", "in_pos", "in_nrm")],
                                     self._ibo[o])

    @staticmethod
    def _set(prog: Any, name: str, value: Any) -> None:
        if name not in prog:
            return
        if isinstance(value, bytes):
            prog[name].write(value)
        else:
            prog[name].value = value

    def _set_common(self, prog: Any) -> None:
        inp = self.inputs
        s = self._set
        s(prog, "env_tex", _ENV_UNIT)
        s(prog, "lut_tex", _LUT_UNIT)
        s(prog, "gloss_tex", _GLOSS_UNIT)
        s(prog, "to_map", _mat_bytes(inp.to_map))
        s(prog, "env_size", (float(inp.env.shape[1]), float(inp.env.shape[0])))
        s(prog, "lut_size", (float(inp.lut.shape[1]), float(inp.lut.shape[0])))
        s(prog, "gloss_atlas", self._gloss_atlas)
        s(prog, "lev_rect", _vec4s(self._gloss_rects))
        s(prog, "lev_sigma", _vec4s(inp.level_sigma))
        s(prog, "per_octave", float(inp.per_octave))
        basis = np.zeros((4 * self.nr, inp.channels), np.float32)
        basis[:inp.basis.shape[0]] = inp.basis
        s(prog, "gbasis", _vec4s(np.moveaxis(_layers(basis, self.nb), 0, 1)))
        s(prog, "along_off", _vec4s(inp.along[:, 0]))
        s(prog, "along_w", _vec4s(inp.along[:, 1]))
        s(prog, "min_ratio", float(inp.min_ratio))
        s(prog, "horizon_ratio", float(inp.horizon_ratio))
        s(prog, "sh", _vec4s(np.moveaxis(_layers(inp.sh, self.nb), 0, 1)))
        s(prog, "parity", (1.0, -1.0, 1.0, 1.0))
        s(prog, "cmf", _vec4s(np.moveaxis(_layers(inp.to_xyz.T, self.nb), 0, 1)))
        s(prog, "disp_m", _mat_bytes(inp.display))
        s(prog, "disp_off", tuple(float(x) for x in inp.display_offset))
        s(prog, "tone", {"srgb": 0, "gamma": 1, "linear": 2}[str(inp.tone)])
        s(prog, "tone_gamma", float(inp.tone_gamma))
        s(prog, "normal_matrix", _mat_bytes(np.eye(3)))
        if "ir_tex" in prog:
            prog["ir_tex"].value = list(range(_IR_UNIT0, _IR_UNIT0 + self.ns * self.nb))
        h, w = inp.shape
        s(prog, "viewport", (float(w), float(h)))
        a, b, c = self._background_rays()
        s(prog, "ray_a", a)
        s(prog, "ray_b", b)
        s(prog, "ray_c", c)

    def _background_rays(self) -> tuple[tuple[float, ...], ...]:
        """Map-frame ray of the pixel at NDC (x, y) as x·a + y·b + c (not normalised): the
        far-plane point of (x, y) minus the eye, times the (positive) perspective divisor."""
        inp = self.inputs
        inv = np.linalg.inv(inp.projection @ inp.view)
        eye = -np.linalg.solve(inp.view[:3, :3], inp.view[:3, 3])
        wrow = inv[3]
        cols = [inv[:3, 0], inv[:3, 1], inv[:3, 2] + inv[:3, 3]]
        ws = [wrow[0], wrow[1], wrow[2] + wrow[3]]
        rays = [(col - eye * wv) for col, wv in zip(cols, ws, strict=True)]
        scale = np.sign(ws[2]) / np.linalg.norm(rays[2])
        return tuple(tuple(float(x) for x in inp.to_map @ (r * scale)) for r in rays)

    def _set_material(self, prog: Any, o: int) -> None:
        inp = self.inputs
        a, b, chi, _, n, _ = (float(x) for x in inp.materials[o])
        s = self._set
        s(prog, "refl", _vec4s(_layers(inp.reflectance[o], self.nb)))
        s(prog, "m_alpha", a)
        s(prog, "m_beta", b)
        s(prog, "m_chi", chi)
        s(prog, "m_n", n)
        s(prog, "moments", _vec4s(inp.moments[o]))
        model = inp.model[o]
        s(prog, "model", _mat_bytes(model))
        s(prog, "normal_matrix", _mat_bytes(np.linalg.inv(model[:3, :3]).T))

    def _bind_maps(self) -> None:
        self.env_tex.use(_ENV_UNIT)
        self.lut_tex.use(_LUT_UNIT)
        self.gloss_tex.use(_GLOSS_UNIT)

    def _cull(self) -> None:
        import moderngl

        self.ctx.enable(moderngl.DEPTH_TEST)
        if self.cull == "back":
            self.ctx.enable(moderngl.CULL_FACE)
            self.ctx.front_face = "ccw"
            self.ctx.cull_face = "back"
        else:
            self.ctx.disable(moderngl.CULL_FACE)

    # -- frames

    def pass1(self) -> None:
        """Pass 1: every sender seen from every receiver's centre into the pair's targets."""
        import moderngl

        self._bind_maps()
        self._cull()
        inp = self.inputs
        for ir in self._ir:
            i, j = ir["receiver"], ir["sender"]
            ir["fbo"].use()
            ir["fbo"].clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            self._set_material(self.p1, j)
            self.p1["vp"].write(_mat_bytes(ir["vp"]))
            self.p1["eye"].value = tuple(float(x) for x in inp.model[i][:3, 3])
            self._set(self.p1, "recv_alpha", float(inp.materials[i, 0]) / math.pi)
            self._set(self.p1, "recv_gamma", float(inp.materials[i, 3]))
            self._vao1[j].render(moderngl.TRIANGLES)
            if self.pass1_mipmaps:
                for tex in ir["texs"]:
                    tex.build_mipmaps()

    def pass2(self, interreflection: bool = True, *, xyz: bool = False) -> Any:
        """Pass 2 into the camera target (``xyz``: the float XYZ target); returns it."""
        import moderngl

        ctx = self.ctx
        p2, pbg, vao2, vao_bg, fbo = self.p2, self.pbg, self._vao2, self._vao_bg, self.fbo
        if xyz:
            p2, pbg, vao2, vao_bg, fbo = self._xyz()
        inp = self.inputs
        self._bind_maps()
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        vao_bg.render(moderngl.TRIANGLES, vertices=3)
        self._cull()
        p2["vp"].write(_mat_bytes(self._cam_vp))
        p2["eye"].value = tuple(float(x) for x in self._eye)
        self._set(p2, "use_ir", (2 if self.interreflection_everywhere else 1)
                  if interreflection and self.n_obj > 1 else 0)
        for o in range(self.n_obj):
            if interreflection and self.n_obj > 1:
                mine = [ir for ir in self._ir if ir["receiver"] == o]
                for s, ir in enumerate(mine):
                    for k, tex in enumerate(ir["texs"]):
                        tex.use(_IR_UNIT0 + s * self.nb + k)
                self._set(p2, "ir_vp", b"".join(_mat_bytes(ir["vp"]) for ir in mine))
                self._set(p2, "ir_centre", _vec4s(np.stack(
                    [inp.model[ir["sender"]][:3, 3] for ir in mine])))
            self._set_material(p2, o)
            self._set(p2, "object_id", float(o))
            vao2[o].render(moderngl.TRIANGLES)
        return fbo

    def render(self, interreflection: bool = True, readback: bool = True) -> np.ndarray | None:
        """One frame: pass 1 (with ``interreflection``), pass 2, and the display image read
        back as (H, W, 3) uint8 (row 0 at the top); ``readback`` False: wait for the frame
        (``glFinish``) and return None."""
        if interreflection and self.n_obj > 1:
            self.pass1()
        fbo = self.pass2(interreflection)
        if readback:
            h, w = self.inputs.shape
            data = fbo.read(components=3)
            return np.frombuffer(data, np.uint8).reshape(h, w, 3)[::-1]
        self.ctx.finish()
        return None

    def render_xyz(self, interreflection: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """The same frame as absolute XYZ (cd/m², float32 (H, W, 3), row 0 at the top) and the
        object of each pixel ((H, W) int32, −1 = background): for accuracy checks."""
        if interreflection and self.n_obj > 1:
            self.pass1()
        fbo = self.pass2(interreflection, xyz=True)
        h, w = self.inputs.shape
        data = np.frombuffer(fbo.read(components=4, dtype="f4"), np.float32)
        img = data.reshape(h, w, 4)[::-1]
        return np.ascontiguousarray(img[..., :3]), np.rint(img[..., 3]).astype(np.int32) - 1

    def _xyz(self) -> tuple[Any, ...]:
        if self._xyz_programs is None:
            ctx = self.ctx
            p2 = self._program(shaders.FS_PASS2, xyz=True)
            pbg = self._program(shaders.FS_BACKGROUND, vertex=shaders.VS_BACKGROUND, xyz=True)
            for prog in (p2, pbg):
                self._set_common(prog)
            h, w = self.inputs.shape
            fbo = ctx.framebuffer(color_attachments=[ctx.texture((w, h), 4, dtype="f4")],
                                  depth_attachment=ctx.depth_renderbuffer((w, h)))
            self._xyz_programs = (p2, pbg, [self._mesh_vao(p2, o) for o in range(self.n_obj)],
                                  ctx.vertex_array(pbg, []), fbo)
        return self._xyz_programs

    @property
    def info(self) -> dict[str, str]:
        """The OpenGL renderer and version strings."""
        return {"gl_renderer": str(self.ctx.info.get("GL_RENDERER", "?")),
                "gl_version": str(self.ctx.info.get("GL_VERSION", "?"))}

    def release(self) -> None:
        """Free the context (when this object made it)."""
        if self._own_ctx and self.ctx is not None:
            self.ctx.release()
            self.ctx = None

    def __enter__(self) -> GLBaseline:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
