"""Our whole reflection model as ONE Mitsuba 3 BSDF.

Plugin name ``spectral_fit_model``; per unit projected solid angle (Mitsuba's ``eval`` includes
the cosine of the light direction, cosθi = wo.z in the local shading frame):

    f(V, L) cosθi = α S/π · cosθi  +  β F(n, θd) D(μ, θh) G / (4 cosθr)         (eq. 4)

plus the delta lobe χ F(n, θr) δ(L − reflect(V)) (sampled only, flagged ``DeltaReflection``;
``eval``/``pdf`` exclude it, as Mitsuba expects). S is three numbers: in the band trick each
render carries three spectral bands in the rgb channels (F, D, G do not depend on λ).

Properties: ``alpha``, ``beta``, ``chi``, ``mu``, ``n`` (floats), ``s0``, ``s1``, ``s2`` (S in
the three channels), ``distribution`` ("gaussian" | "beckmann"), ``geometry`` ("vcavity" |
"smith"), ``gaussian_k`` (K(μ) of the normalised Gaussian; default: computed by
:func:`spectral_fit.lighting.gaussian_normalisation`), ``unit_fg`` (test switch: F = G = 1 in
the gloss lobe, for the gloss furnace value).

- D: Gaussian K(μ) exp(−(θh/μ)²) with ∫ D cosθh dω = 1, or Beckmann exp(−tan²θh/m²)/(π m² cos⁴θh).
- G: V-cavity min(1, 2 NH NV/VH, 2 NH NL/VH), or separable Smith with Beckmann's G1 (m = μ).
- F: exact unpolarised dielectric Fresnel.

Sampling is a mixture chosen per V: the mirror with weight χ F(θr), the diffuse lobe (cosine
hemisphere) with α·mean(S), the gloss lobe with β (F(θr) + 0.05). Gloss half vectors: Beckmann's
exact sampling of D cosθh; for the Gaussian, θh from the truncated density ∝ θ exp(−θ²/μ²) on
[0, π/2] (exact pdf θ e^{−θ²/μ²} / (π μ² Z sinθ), Z = 1 − e^{−(π/2μ)²}), then L = reflect(V, H)
with the Jacobian 1/(4 V·H). ``pdf`` returns the mixture's density of the non-delta lobes.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["PLUGIN", "register_bsdf", "gaussian_k"]

PLUGIN = "spectral_fit_model"


def gaussian_k(mu: float) -> float:
    """K(μ) of the normalised Gaussian distribution (float), from the reflectance module."""
    import numpy as np

    from ...lighting import gaussian_normalisation

    return float(np.asarray(gaussian_normalisation(np.float32(mu))))


def register_bsdf(mi: Any, dr: Any) -> None:
    """Define the BSDF class for the active variant and register it as ``spectral_fit_model``."""

    def fresnel(c: Any, n: float) -> Any:
        c = dr.clip(dr.abs(c), 0.0, 1.0)
        g = dr.sqrt(n * n + c * c - 1.0)
        a = (g - c) / (g + c)
        b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
        return 0.5 * a * a * (1.0 + b * b)

    class ModelBSDF(mi.BSDF):
        def __init__(self, props: Any) -> None:
            mi.BSDF.__init__(self, props)
            self.alpha = float(props.get("alpha", 1.0))
            self.beta = float(props.get("beta", 1.0))
            self.chi = float(props.get("chi", 0.0))
            self.mu = float(props.get("mu", 0.1))
            self.eta = float(props.get("n", 1.5))
            self.distribution = str(props.get("distribution", "gaussian"))
            self.geometry = str(props.get("geometry", "vcavity"))
            self.unit_fg = bool(props.get("unit_fg", False))
            if self.distribution not in ("gaussian", "beckmann"):
                raise ValueError(f"distribution: unknown {self.distribution!r}")
            if self.geometry not in ("vcavity", "smith"):
                raise ValueError(f"geometry: unknown {self.geometry!r}")
            s = [float(props.get(f"s{i}", 0.5)) for i in range(3)]
            self.s_mean = sum(s) / 3.0
            self.s = mi.Color3f(*s)
            if dr.is_jit_v(self.s):
                dr.make_opaque(self.s)  # a new S does not recompile the kernels
            self.k = float(props.get("gaussian_k", 0.0)) or (
                gaussian_k(self.mu) if self.distribution == "gaussian" else 0.0)
            self.z = 1.0 - math.exp(-((0.5 * math.pi / self.mu) ** 2))
            flags = []
            if self.alpha > 0:
                flags.append(mi.BSDFFlags.DiffuseReflection)
            if self.beta > 0:
                flags.append(mi.BSDFFlags.GlossyReflection)
            if self.chi > 0:
                flags.append(mi.BSDFFlags.DeltaReflection)
            if not flags:
                flags.append(mi.BSDFFlags.DiffuseReflection)
            comps = [f | mi.BSDFFlags.FrontSide for f in flags]
            self.m_components = comps
            all_flags = comps[0]
            for f in comps[1:]:
                all_flags = all_flags | f
            self.m_flags = all_flags
            self._index = {f: i for i, f in enumerate(flags)}

        # ------------------------------------------------------------------ pieces
        def _enabled(self, ctx: Any, flag: Any) -> bool:
            i = self._index.get(flag)
            return i is not None and bool(ctx.is_enabled(flag, i))

        def _weights(self, ctx: Any, cos_o: Any) -> tuple[Any, Any, Any]:
            f = fresnel(cos_o, self.eta)
            wd = self.alpha * self.s_mean if self._enabled(
                ctx, mi.BSDFFlags.DiffuseReflection) else 0.0
            wg = self.beta * (f + 0.05) if self._enabled(
                ctx, mi.BSDFFlags.GlossyReflection) else 0.0 * f
            wm = self.chi * f if self._enabled(ctx, mi.BSDFFlags.DeltaReflection) else 0.0 * f
            total = wd + wg + wm
            ok = total > 0
            inv = dr.select(ok, 1.0 / dr.select(ok, total, 1.0), 0.0)
            pd = dr.select(ok, wd * inv, 1.0)
            return pd, wg * inv, wm * inv

        def _theta_h(self, h: Any) -> Any:
            return dr.atan2(dr.sqrt(dr.square(h.x) + dr.square(h.y)), h.z)

        def _d(self, h: Any) -> Any:
            if self.distribution == "gaussian":
                t = self._theta_h(h)
                return dr.select(h.z > 0, self.k * dr.exp(-dr.square(t / self.mu)), 0.0)
            c2 = dr.square(dr.maximum(h.z, 1e-12))
            tan2 = dr.maximum(1.0 - c2, 0.0) / c2
            m2 = self.mu * self.mu
            return dr.select(h.z > 0, dr.exp(-tan2 / m2) / (math.pi * m2 * c2 * c2), 0.0)

        def _pdf_h(self, h: Any) -> Any:
            """Density (per solid angle) with which a half vector h is sampled."""
            if self.distribution == "gaussian":
                t = self._theta_h(h)
                st = dr.sin(t)
                ratio = dr.select(t > 1e-4, t / dr.select(t > 1e-4, st, 1.0), 1.0)
                p = ratio * dr.exp(-dr.square(t / self.mu)) / (
                    math.pi * self.mu * self.mu * self.z)
                return dr.select(h.z > 0, p, 0.0)
            return self._d(h) * dr.maximum(h.z, 0.0)

        def _g1_smith(self, c: Any) -> Any:
            c = dr.clip(c, 0.0, 1.0)
            s = dr.sqrt(dr.maximum(1.0 - c * c, 1e-12))
            a = dr.maximum(c / (self.mu * s), 1e-6)
            lam = 0.5 * (dr.erf(a) - 1.0) + dr.exp(-a * a) / (2.0 * a * math.sqrt(math.pi))
            return dr.select(c > 0, 1.0 / (1.0 + lam), 0.0)

        def _g(self, nh: Any, nv: Any, nl: Any, vh: Any) -> Any:
            if self.geometry == "vcavity":
                vs = dr.select(vh > 0, vh, 1.0)
                g = dr.minimum(1.0, dr.minimum(2.0 * nh * nv / vs, 2.0 * nh * nl / vs))
                return dr.select(vh > 0, dr.clip(g, 0.0, 1.0), 0.0)
            return dr.select(vh > 0, self._g1_smith(nv) * self._g1_smith(nl), 0.0)

        def _gloss(self, wi: Any, wo: Any) -> tuple[Any, Any, Any]:
            """(F D G / (4 cosθr), h, V·H) for wi, wo in the upper hemisphere."""
            h = dr.normalize(wi + wo)
            vh = dr.dot(wi, h)
            f = fresnel(vh, self.eta)
            g = self._g(h.z, wi.z, wo.z, vh)
            if self.unit_fg:
                f, g = dr.select(vh > 0, 1.0, 0.0), 1.0
            val = f * self._d(h) * g / (4.0 * dr.maximum(wi.z, 1e-12))
            return val, h, vh

        # ------------------------------------------------------------------ BSDF interface
        def eval(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            wi = si.wi
            ok = active & (wi.z > 0) & (wo.z > 0)
            val = mi.Color3f(0.0)
            if self._enabled(ctx, mi.BSDFFlags.DiffuseReflection) and self.alpha > 0:
                val += self.s * (self.alpha / math.pi * wo.z)
            if self._enabled(ctx, mi.BSDFFlags.GlossyReflection) and self.beta > 0:
                gl, _, _ = self._gloss(wi, wo)
                val += mi.Color3f(self.beta * gl)
            return dr.select(ok, val, mi.Color3f(0.0))

        def pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            wi = si.wi
            ok = active & (wi.z > 0) & (wo.z > 0)
            pd, pg, _ = self._weights(ctx, wi.z)
            h = dr.normalize(wi + wo)
            vh = dr.dot(wi, h)
            pgl = dr.select(vh > 0, self._pdf_h(h) / (4.0 * dr.select(vh > 0, vh, 1.0)), 0.0)
            p = pd * dr.maximum(wo.z, 0.0) / math.pi + pg * pgl
            return dr.select(ok, p, 0.0)

        def eval_pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx: Any, si: Any, sample1: Any, sample2: Any, active: Any = True
                   ) -> Any:
            wi = si.wi
            ok = active & (wi.z > 0)
            pd, pg, pm = self._weights(ctx, wi.z)
            pick_m = sample1 < pm
            not_m = (not pick_m) if isinstance(pick_m, bool) else ~pick_m  # scalar variants
            pick_d = not_m & (sample1 < pm + pd)
            # diffuse direction
            wo_d = mi.warp.square_to_cosine_hemisphere(sample2)
            # gloss direction: sample a half vector, reflect
            phi = 2.0 * math.pi * sample2.y
            if self.distribution == "gaussian":
                t = self.mu * dr.sqrt(-dr.log(dr.maximum(1.0 - sample2.x * self.z, 1e-30)))
                st, ct = dr.sin(t), dr.cos(t)
            else:
                tan2 = -self.mu * self.mu * dr.log(dr.maximum(1.0 - sample2.x, 1e-30))
                ct = 1.0 / dr.sqrt(1.0 + tan2)
                st = dr.sqrt(dr.maximum(1.0 - ct * ct, 0.0))
            h = mi.Vector3f(st * dr.cos(phi), st * dr.sin(phi), ct)
            wo_g = 2.0 * dr.dot(wi, h) * h - wi
            wo_m = mi.Vector3f(-wi.x, -wi.y, wi.z)
            wo = dr.select(pick_m, wo_m, dr.select(pick_d, wo_d, wo_g))
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = wo
            bs.eta = 1.0
            delta_t = mi.UInt32(+mi.BSDFFlags.DeltaReflection)
            diff_t = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            gloss_t = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_type = dr.select(pick_m, delta_t, dr.select(pick_d, diff_t, gloss_t))
            idx = self._index
            bs.sampled_component = dr.select(
                pick_m, mi.UInt32(idx.get(mi.BSDFFlags.DeltaReflection, 0)),
                dr.select(pick_d, mi.UInt32(idx.get(mi.BSDFFlags.DiffuseReflection, 0)),
                          mi.UInt32(idx.get(mi.BSDFFlags.GlossyReflection, 0))))
            p_smooth = self.pdf(ctx, si, wo, ok)
            bs.pdf = dr.select(pick_m, pm, p_smooth)
            val = self.eval(ctx, si, wo, ok)
            w_smooth = dr.select(p_smooth > 0, val / dr.select(p_smooth > 0, p_smooth, 1.0),
                                 mi.Color3f(0.0))
            w_mirror = mi.Color3f(self.chi * fresnel(wi.z, self.eta)
                                  / dr.select(pm > 0, pm, 1.0))
            weight = dr.select(pick_m, w_mirror, w_smooth)
            valid = ok & (wo.z > 0) & (bs.pdf > 0)
            bs.pdf = dr.select(valid, bs.pdf, 0.0)
            return bs, dr.select(valid, weight, mi.Color3f(0.0))

        def eval_diffuse_reflectance(self, si: Any, active: Any = True) -> Any:
            return self.s * self.alpha

        def traverse(self, callback: Any) -> None:
            pass

        def parameters_changed(self, keys: Any) -> None:
            pass

        def to_string(self) -> str:
            return (f"SpectralFitModel[alpha={self.alpha}, beta={self.beta}, chi={self.chi}, "
                    f"mu={self.mu}, n={self.eta}, {self.distribution}, {self.geometry}]")

    mi.register_bsdf(PLUGIN, lambda props: ModelBSDF(props))
