"""GLSL 4.50 sources of the OpenGL baseline (:mod:`spectral_fit.bench.cases.gl.baseline`).

Spectral quantities are ``NB`` vec4 layers (bands 4i … 4i + 3 in layer i; the 31 bands of
400–700 nm fill 8 layers, the last slot a zero pad). Every map lookup follows the project's
equirectangular convention (docs/lighting.md): u = φ/2π, v = θ/π from +Y, bilinear, wrapped in u,
blended towards the pole mean past the first and last row centres. The GPU's bilinear filter does
that exactly on a *padded grid* (a pole row above and below, the last column copied before the
first and the first after the last) when v is remapped by :func:`grid_coord` (the pole rows are
placed half a texel beyond the first and last row centres, i.e. at the poles themselves).

Sources are templates: ``{nb}`` (spectral layers), ``{nr}`` (layers of the gloss atlas's principal
spectra), ``{nlev}`` (prefiltered levels), ``{nalong}`` (split-sum lookups along the lobe),
``{ntab}`` (lobe moment table entries), ``{ns}`` (senders per receiver) and ``{defines}``.
"""

from __future__ import annotations

__all__ = ["COMMON", "VS_MESH", "FS_PASS1", "FS_PASS2", "VS_BACKGROUND", "FS_BACKGROUND",
           "source"]

COMMON = """
#version 450
#define NB {nb}
#define NR {nr}
#define NLEV {nlev}
#define NALONG {nalong}
#define NTAB {ntab}
#define NS {ns}
{defines}
const float PI = 3.14159265358979;

// ---- environment (map frame: d_map = to_map * d_world)
uniform mat3 to_map;
uniform sampler2DArray env_tex;       // padded map, NB layers (texture unit 0)
uniform vec2 env_size;                // (W, H) of the map
uniform sampler2DArray lut_tex;       // padded irradiance map over normals (unit 1)
uniform vec2 lut_size;
uniform sampler2DArray gloss_tex;     // atlas of the padded prefiltered levels (unit 2)
uniform vec2 gloss_atlas;             // atlas (width, height) in texels
uniform vec4 lev_rect[NLEV];          // per level: padded grid origin (x, y) and (W, H)
uniform float lev_sigma[NLEV];        // prefilter std per level (rad), level 0 = 0
uniform float per_octave;
uniform vec4 gbasis[4 * NR * NB];     // principal spectra: row k in gbasis[k * NB + i]
uniform float along_off[NALONG];      // lookups along the lobe (std units) and their weights
uniform float along_w[NALONG];
uniform float min_ratio;
uniform float horizon_ratio;
uniform vec4 sh[9 * NB];              // order-2 SH radiance coefficients (R&H order)

// ---- the shaded object's material (eq. 4-5)
uniform vec4 refl[NB];                // diffuse reflectance S
uniform float m_alpha;
uniform float m_beta;
uniform float m_chi;
uniform float m_n;
uniform vec4 moments[NTAB];           // gloss lobe (A, delta, var_t, var_b) at cos = 1 - x^2
uniform vec4 parity;

vec2 dir_to_uv(vec3 d) {
    float rho2 = d.x * d.x + d.z * d.z;
    bool small = rho2 < 1e-20;
    float rho = small ? 0.0 : sqrt(rho2);
    float theta = atan(rho, d.y);
    float phi = atan(small ? 0.0 : d.x, small ? 1.0 : -d.z);
    float u = phi * (0.5 / PI);
    if (u < 0.0) u += 1.0;
    return vec2(u, theta * (1.0 / PI));
}

// texel-space position in a padded grid of a (W, H) map whose bilinear filter is the lookup rule
vec2 grid_coord(vec2 uv, vec2 size) {
    float tx = uv.x * size.x - 0.5;
    float ty = uv.y * size.y - 0.5;
    float last = size.y - 1.0;
    ty = ty < 0.0 ? 2.0 * ty : (ty > last ? last + 2.0 * (ty - last) : ty);
    return vec2(tx, ty) + 1.5;
}

vec4 env_lookup(vec2 p, int i) {      // p = grid_coord(...) / (env_size + 2)
    return textureLod(env_tex, vec3(p, float(i)), 0.0);
}

vec4 level_lookup(int k, vec2 uv, int c) {
    vec4 r = lev_rect[k];
    vec2 p = (grid_coord(uv, r.zw) + r.xy) / gloss_atlas;
    return textureLod(gloss_tex, vec3(p, float(c)), 0.0);
}

float fresnel(float c, float n) {     // exact unpolarised dielectric Fresnel
    c = clamp(abs(c), 0.0, 1.0);
    float g = sqrt(n * n + c * c - 1.0);
    float a = (g - c) / (g + c);
    float b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0);
    return 0.5 * a * a * (1.0 + b * b);
}

float smootherstep(float x) {
    x = clamp(x, 0.0, 1.0);
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0);
}

vec4 interp_moments(float nv) {       // Catmull-Rom in x = sqrt(1 - cos), even/odd through 0
    float x = sqrt(clamp(1.0 - nv, 0.0, 1.0)) * float(NTAB - 1);
    int i = clamp(int(floor(x)), 0, NTAB - 2);
    float t = x - float(i);
    vec4 p0 = moments[abs(i - 1)] * (i >= 1 ? vec4(1.0) : parity);
    vec4 p1 = moments[i];
    vec4 p2 = moments[i + 1];
    vec4 p3 = moments[min(i + 2, NTAB - 1)];
    return p1 + 0.5 * t * (p2 - p0 + t * (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3
                                           + t * (3.0 * (p1 - p2) + p3 - p0)));
}

// gloss radiance per unit beta: the lobe albedo times the prefiltered map at NALONG directions
// along the lobe (split sum), in the map's principal spectra, then to bands
void gloss(vec3 N, vec3 V, out vec4 G[NB]) {
    for (int i = 0; i < NB; i++) G[i] = vec4(0.0);
    float nv_raw = dot(N, V);
    if (nv_raw <= 0.0) return;
    float nv = clamp(nv_raw, 0.0, 1.0);
    vec4 mom = interp_moments(nv);
    float var_t = max(mom.z, 1e-12);
    vec3 p = V - nv_raw * N;
    float p2 = dot(p, p);
    vec3 T;
    if (p2 > 1e-12) {
        T = p * inversesqrt(p2);
    } else {
        float s = N.z >= 0.0 ? 1.0 : -1.0;
        float a = -1.0 / (s + N.z);
        T = vec3(1.0 + s * N.x * N.x * a, s * N.x * N.y * a, -s * N.x);
    }
    float sr = sqrt(max(1.0 - nv * nv, 0.0));
    float sd = sin(mom.y), cd = cos(mom.y);
    vec3 R = nv * N - sr * T;
    vec3 P = -sr * N - nv * T;
    vec3 d = cd * R + sd * P;
    vec3 e1 = cd * P - sd * R;
    float var_n = max(max(mom.w, min_ratio * min_ratio * var_t), 1e-12);
    float spread = sqrt(max(var_t - var_n, 1e-12));
    float sigma0 = sqrt(var_n * (1.0 + var_n / 3.0));
    float s1 = lev_sigma[1];
    vec4 mean[NR];
    for (int c = 0; c < NR; c++) mean[c] = vec4(0.0);
    for (int k = 0; k < NALONG; k++) {
        float ang = along_off[k] * spread;
        vec3 dk = cos(ang) * d + sin(ang) * e1;
        float sigma = min(sigma0, horizon_ratio * max(dot(dk, N), 0.0));
        vec2 uv = dir_to_uv(to_map * dk);
        float t = log2(max(sigma, 1e-30) / s1) * per_octave;
        int lo = 0, hi = 1;
        float w;
        if (t < 0.0) {
            w = smootherstep(sigma / s1);
        } else {
            int kk = clamp(int(floor(t)), 0, NLEV - 3);
            lo = kk + 1;
            hi = kk + 2;
            float slo = lev_sigma[lo], shi = lev_sigma[hi];
            w = smootherstep((sigma * sigma - slo * slo) / (shi * shi - slo * slo));
        }
        for (int c = 0; c < NR; c++)
            mean[c] += along_w[k] * ((1.0 - w) * level_lookup(lo, uv, c)
                                     + w * level_lookup(hi, uv, c));
    }
    for (int c = 0; c < NR; c++) {
        vec4 a = mom.x * mean[c];
        for (int i = 0; i < NB; i++)
            G[i] += a.x * gbasis[(4 * c) * NB + i] + a.y * gbasis[(4 * c + 1) * NB + i]
                  + a.z * gbasis[(4 * c + 2) * NB + i] + a.w * gbasis[(4 * c + 3) * NB + i];
    }
}

// ---- spectra -> absolute XYZ -> display
uniform vec4 cmf[3 * NB];             // XYZ weights (683 lm/W * cmf * d_lambda) per band
uniform mat3 disp_m;                  // XYZ -> display linear RGB (exposure folded in)
uniform vec3 disp_off;
uniform int tone;                     // 0 sRGB, 1 gamma, 2 linear
uniform float tone_gamma;

vec3 spectra_to_xyz(vec4 L[NB]) {
    vec3 xyz = vec3(0.0);
    for (int i = 0; i < NB; i++)
        xyz += vec3(dot(cmf[i], L[i]), dot(cmf[NB + i], L[i]), dot(cmf[2 * NB + i], L[i]));
    return xyz;
}

vec3 encode(vec3 xyz) {
    vec3 x = clamp(disp_m * xyz - disp_off, 0.0, 1.0);
    if (tone == 2) return x;
    if (tone == 1) return pow(max(x, vec3(1e-12)), vec3(1.0 / tone_gamma));
    vec3 hi = 1.055 * pow(max(x, vec3(0.0031308)), vec3(1.0 / 2.4)) - 0.055;
    return mix(hi, 12.92 * x, lessThanEqual(x, vec3(0.0031308)));
}
"""

VS_MESH = """
#version 450
in vec3 in_pos;
in vec3 in_nrm;
uniform mat4 model;                   // world from object
uniform mat3 normal_matrix;           // inverse transpose of model's 3x3
uniform mat4 vp;                      // clip from world
out vec3 w_pos;
out vec3 w_nrm;
void main() {
    vec4 p = model * vec4(in_pos, 1.0);
    w_pos = p.xyz;
    w_nrm = normal_matrix * in_nrm;
    gl_Position = vp * p;
}
"""

# pass 1: sender j seen from the receiver i's centre (eq. 6's T_d and T_s), stored already
# weighted by the receiver's alpha_paper = alpha_i / pi and gamma_i (one texture set per pair)
FS_PASS1 = """
in vec3 w_pos;
in vec3 w_nrm;
uniform vec3 eye;                     // the receiver's centre
uniform float recv_alpha;             // alpha_i / pi
uniform float recv_gamma;             // gamma_i
layout(location = 0) out vec4 outs[NB];

vec4 irradiance_sh(vec3 n, int i) {   // Ramamoorthi & Hanrahan 2001, eq. 13
    vec4 L0 = sh[i], L1 = sh[NB + i], L2 = sh[2 * NB + i], L3 = sh[3 * NB + i];
    vec4 L4 = sh[4 * NB + i], L5 = sh[5 * NB + i], L6 = sh[6 * NB + i];
    vec4 L7 = sh[7 * NB + i], L8 = sh[8 * NB + i];
    float x = n.x, y = n.y, z = n.z;
    return 0.429043 * L8 * (x * x - y * y) + 0.743125 * L6 * z * z + 0.886227 * L0
         - 0.247708 * L6
         + 2.0 * 0.429043 * (L4 * x * y + L7 * x * z + L5 * y * z)
         + 2.0 * 0.511664 * (L3 * x + L1 * y + L2 * z);
}

void main() {
    vec3 n = normalize(w_nrm);
    vec3 v = normalize(eye - w_pos);
    float nv = dot(n, v);
    vec3 nm = to_map * n;
    vec4 G[NB];
    gloss(n, v, G);
    bool mirror = m_chi != 0.0 && nv > 0.0;
    vec2 pr = vec2(0.0);
    float kmirror = 0.0;
    if (mirror) {
        pr = grid_coord(dir_to_uv(to_map * (2.0 * nv * n - v)), env_size) / (env_size + 2.0);
        kmirror = m_chi * fresnel(nv, m_n);
    }
    for (int i = 0; i < NB; i++) {
        vec4 td = (m_alpha / PI) * refl[i] * irradiance_sh(nm, i);
        vec4 ts = m_beta * G[i];
        if (mirror) ts += kmirror * env_lookup(pr, i);
        outs[i] = recv_alpha * td + recv_gamma * (nv > 0.0 ? ts : vec4(0.0));
    }
}
"""

# pass 2: the camera's view of the objects (eq. 5 + eq. 6)
FS_PASS2 = """
in vec3 w_pos;
in vec3 w_nrm;
uniform vec3 eye;
uniform int use_ir;
uniform sampler2D ir_tex[NS * NB];    // per sender: its pass-1 texture set
uniform mat4 ir_vp[NS];               // per sender: the pass-1 camera (clip from world)
uniform vec3 ir_centre[NS];           // per sender: its centre
uniform float object_id;
out vec4 frag;

void main() {
    vec3 n = normalize(w_nrm);
    vec3 v = normalize(eye - w_pos);
    float nv = dot(n, v);
    n = normalize(n + max(0.01 - nv, 0.0) * v);   // silhouette: bend towards V (N.V = 0.01)
    nv = dot(n, v);
    vec4 G[NB];
    gloss(n, v, G);
    vec2 pn = grid_coord(dir_to_uv(to_map * n), lut_size) / (lut_size + 2.0);
    bool mirror = m_chi != 0.0;
    vec2 pr = vec2(0.0);
    float kmirror = 0.0;
    if (mirror) {
        pr = grid_coord(dir_to_uv(to_map * (2.0 * nv * n - v)), env_size) / (env_size + 2.0);
        kmirror = m_chi * fresnel(nv, m_n);
    }
    vec4 L[NB];
    for (int i = 0; i < NB; i++) {
        vec4 c = (m_alpha / PI) * refl[i] * textureLod(lut_tex, vec3(pn, float(i)), 0.0)
               + m_beta * G[i];
        if (mirror) c += kmirror * env_lookup(pr, i);
        L[i] = nv > 0.0 ? c : vec4(0.0);
    }
    if (use_ir != 0) {   // 2: the lookups on every fragment, weighted 0 outside the view
        for (int s = 0; s < NS; s++) {
            vec4 q = ir_vp[s] * vec4(w_pos, 1.0);
            vec2 ndc = q.xy / max(abs(q.w), 1e-12);
            bool seen = q.w > 0.0 && abs(ndc.x) <= 1.0 && abs(ndc.y) <= 1.0
                        && dot(n, ir_centre[s] - w_pos) > 0.0;
            if (!seen && use_ir == 1) continue;
            float k = seen ? 1.0 : 0.0;
            vec2 tc = clamp(0.5 * ndc + 0.5, 0.0, 1.0);
            for (int i = 0; i < NB; i++) L[i] += k * textureLod(ir_tex[s * NB + i], tc, 0.0);
        }
    }
    vec3 xyz = spectra_to_xyz(L);
#ifdef OUT_XYZ
    frag = vec4(xyz, object_id + 1.0);
#else
    frag = vec4(encode(xyz), 1.0);
#endif
}
"""

VS_BACKGROUND = """
#version 450
void main() {
    vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);
    gl_Position = vec4(p, 1.0, 1.0);
}
"""

# the environment through every pixel centre (no video), spectral lookup then XYZ
FS_BACKGROUND = """
uniform vec3 ray_a;                   // map-frame ray of NDC (x, y): x ray_a + y ray_b + ray_c
uniform vec3 ray_b;
uniform vec3 ray_c;
uniform vec2 viewport;
out vec4 frag;
void main() {
    vec2 ndc = 2.0 * gl_FragCoord.xy / viewport - 1.0;
    vec3 d = ndc.x * ray_a + ndc.y * ray_b + ray_c;
    vec2 p = grid_coord(dir_to_uv(d), env_size) / (env_size + 2.0);
    vec4 L[NB];
    for (int i = 0; i < NB; i++) L[i] = env_lookup(p, i);
    vec3 xyz = spectra_to_xyz(L);
#ifdef OUT_XYZ
    frag = vec4(xyz, 0.0);
#else
    frag = vec4(encode(xyz), 1.0);
#endif
}
"""


def source(body: str, *, nb: int, nr: int, nlev: int, nalong: int, ntab: int, ns: int,
           xyz: bool = False) -> str:
    """A fragment shader's full source: :data:`COMMON` (with the sizes filled in) + ``body``.
    ``xyz``: write absolute XYZ (and object id + 1, 0 for the background, in alpha) to a float
    target instead of display RGB."""
    head = COMMON.replace("{defines}", "#define OUT_XYZ" if xyz else "")
    for key, val in (("nb", nb), ("nr", nr), ("nlev", nlev), ("nalong", nalong),
                     ("ntab", ntab), ("ns", max(ns, 1))):
        head = head.replace("{" + key + "}", str(int(val)))
    return head + body
