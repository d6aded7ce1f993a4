"""Make measurements/sessions/any_shape_spots/: path-traced spectroradiometer readings of the cup
and the torus of configs/any_shape.toml (meshes, benchmark environment), for fitting objects that
are not spheres.

The readings are rendered by the Mitsuba reference (spectral_fit.validation.reference: the
package's whole material model as one BSDF, path depth 16, band trick) and read by its simulated
SR-3A (1 nm output, 5 nm band-pass, repeatability 0.4 %, floor 5e-4 of the session's peak, gain
jitter 0.2 %, 3 repeats: the simulator's defaults). The true materials are the config's; the
session's start values are set away from them (``START``) so that the fit does not begin at the
answer.

Spots (instrument 0.30-0.40 m from each aim point, 1° field), chosen as a person with a
spectroradiometer would, plus the hard ones:

* cup (12): outside facing the instrument at ~0°, 30° and 50°; a grazing view (70°, 0.2° field);
  the lamp's highlight on the outer wall and one 8° around the wall from it (the wall's normals
  are all perpendicular to the axis, which leans 25° towards the camera, so the lamp is mirrored
  only to a viewer below the cup: seen from behind it, 28° down, at ~75°, 0.2° field); the
  lamp's glint on the rounded lip (0.2° field); two on the outer wall facing the torus (through
  the gap from the front-right; from the right past the torus); inside: the inner back wall
  seen over the lip, an inner side wall, the floor seen down the axis.
* torus (11): the face towards the instrument at 0°, 35° and 55°; a grazing view (70°, 0.2°
  field); the lamp's highlight and the sky's; two inside the hole (the inner equator, its
  normal towards the hole's centre, seen through the hole 42° off its normal); two on the side
  facing the cup; one on the underside.

Every aim point is checked by ray casting (spectral_fit.fitting.cast_rays through a hierarchy
of both world meshes): the central ray from the instrument's position must first hit the
named object's front within 0.5 mm of the aim, and every one of 16 x 16 rays over the
measuring field (the disc the simulator averages) must hit the same object.

    python scripts/make_any_shape_session.py --check          # spots, visibility, gloss shares
    python scripts/make_any_shape_session.py --mc 256,1024,4096,16384   # Monte Carlo noise
    python scripts/make_any_shape_session.py                 # render (16384 spp), write

Monte Carlo noise of a reading (8 seeds, depth 16): median 0.59 % at 256 spp, 0.22 % at 1024,
0.13 % at 4096, 0.05 % (max 0.064 %) at 16384, the default; nearly common to a reading's bands
(every band triple follows the same paths). Rendering the session: ~8 min on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

CONFIG = ROOT / "configs" / "any_shape.toml"
OUT = ROOT / "measurements" / "sessions" / "any_shape_spots"
SCENE_REF = "../../../configs/any_shape.toml"

LAMP = np.array([-0.45, 0.55, 0.70]) / np.linalg.norm([-0.45, 0.55, 0.70])  # docs/benchmark.md
ZENITH = np.array([0.0, 1.0, 0.0])
INSTRUMENT = (0.0, 0.03, 0.05)  # default position: reads the white standard from 0.33 m
WHITE = {"position": [0.0, -0.01, -0.275], "normal": [0.0, 0.0, 1.0], "reflectance": 0.98,
         "radius": 0.02}
# the fit's start values (the config's materials are the truth)
START = {"cup": {"alpha": 0.8, "beta": 0.6, "chi": 0.03, "mu": 0.1, "n": 1.6},
         "torus": {"alpha": 0.8, "beta": 0.6, "chi": 0.03, "mu": 0.15, "n": 1.42}}
# cup profile (scripts/make_meshes.py): outer radius, wall, height, inner floor height
CUP_R, CUP_WALL, CUP_H, CUP_BASE = 0.03, 0.004, 0.07, 0.006
TOR_R, TOR_r = 0.035, 0.014


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _mirror(light: np.ndarray, n: np.ndarray) -> np.ndarray:
    return _unit(2.0 * np.dot(n, light) * n - light)


def _tilt(n: np.ndarray, towards: np.ndarray, deg: float) -> np.ndarray:
    """n rotated by ``deg`` towards the direction ``towards``."""
    t = towards - np.dot(towards, n) * n
    t = t / np.linalg.norm(t)
    a = math.radians(deg)
    return _unit(math.cos(a) * n + math.sin(a) * t)


class Frames:
    """World <- object transforms of the scene's objects."""

    def __init__(self, scene):
        self.m = {o.name: o.model_matrix() for o in scene.objects}

    def point(self, name: str, p) -> np.ndarray:
        m = self.m[name]
        return m[:3, :3] @ np.asarray(p, np.float64) + m[:3, 3]

    def normal(self, name: str, n) -> np.ndarray:
        m = self.m[name]
        return _unit(np.linalg.inv(m[:3, :3]).T @ np.asarray(n, np.float64))

    def local_dir(self, name: str, d) -> np.ndarray:
        m = self.m[name]
        return _unit(m[:3, :3].T @ np.asarray(d, np.float64))


def cup_outer(phi_deg: float, y: float):
    c, s = math.cos(math.radians(phi_deg)), math.sin(math.radians(phi_deg))
    return (CUP_R * c, y, CUP_R * s), (c, 0.0, s)


def cup_inner(phi_deg: float, y: float):
    r = CUP_R - CUP_WALL
    c, s = math.cos(math.radians(phi_deg)), math.sin(math.radians(phi_deg))
    return (r * c, y, r * s), (-c, 0.0, -s)


def cup_floor(x: float = 0.0, z: float = 0.0):
    return (x, CUP_BASE, z), (0.0, 1.0, 0.0)


def torus_point(u: float, v: float):
    """Local point and normal at ring angle u, tube angle v (radians; v = 0 outer equator,
    pi/2 top, pi inner equator facing the hole)."""
    nrm = np.array([math.cos(v) * math.cos(u), math.sin(v), math.cos(v) * math.sin(u)])
    ring = np.array([math.cos(u), 0.0, math.sin(u)])
    return TOR_R * ring + TOR_r * nrm, nrm


def torus_with_normal(local_n: np.ndarray, outer: bool = True):
    """The torus point whose normal is ``local_n`` (on the outer half, or the inner one)."""
    n = _unit(local_n)
    v = math.asin(float(np.clip(n[1], -1, 1)))
    u = math.atan2(n[2], n[0])
    if not outer:
        v, u = math.pi - v, u + math.pi
    return torus_point(u, v)


def design(scene) -> list[dict]:
    """The spots: id, object, region, aim, normal, view direction V (towards the instrument),
    distance, field angle."""
    fr = Frames(scene)
    front = _unit([0.0, 0.05, 1.0])
    spots: list[dict] = []

    def add(sid, obj, region, local, v, d=0.35, field=1.0):
        p, n = local
        aim = fr.point(obj, p)
        nw = fr.normal(obj, n)
        spots.append({"id": sid, "object": obj, "region": region, "aim": aim, "normal": nw,
                      "V": _unit(v), "distance": d, "field": field})

    # ---- cup: outside, facing the instrument at different angles
    # local +z is the side towards the camera (tilted 25° down with the cup's axis)
    n_front = fr.normal("cup", (0, 0, 1))
    add("cup_front", "cup", "outer", cup_outer(92.5, 0.04), n_front, 0.33)
    add("cup_oblique_30", "cup", "outer", cup_outer(117.5, 0.045),
        _tilt(fr.normal("cup", cup_outer(117.5, 0.045)[1]), _unit([0.0, 0.0, 1.0]), 30.0), 0.36)
    add("cup_oblique_50", "cup", "outer", cup_outer(62.5, 0.02),
        _tilt(fr.normal("cup", cup_outer(62.5, 0.02)[1]), _unit([-0.3, 0.4, 1.0]), 50.0), 0.38)
    # grazing (70°): the 0.2° field keeps the stretched footprint (1.2 x 3.5 mm) on the wall
    add("cup_grazing", "cup", "outer", cup_outer(152.5, 0.04),
        _tilt(fr.normal("cup", cup_outer(152.5, 0.04)[1]), _unit([0.1, 0.0, 1.0]), 70.0), 0.35,
        field=0.2)
    # the lamp's highlight on the outer wall: the walls' normals are all perpendicular to the
    # axis, which leans 25° towards the camera, so the lamp (up, behind the camera) is mirrored
    # to a viewer below the cup; the least steep one is behind it, on the side away from the
    # torus (the wall's height that keeps the footprint on it)
    best = None
    for phi in np.arange(181.25, 270.0, 2.5):
        v = _mirror(LAMP, fr.normal("cup", cup_outer(float(phi), 0.04)[1]))
        if best is None or v[1] > best[0]:
            best = (float(v[1]), float(phi))
    phi_l = best[1]
    n_l = fr.normal("cup", cup_outer(phi_l, 0.04)[1])
    # (0.2° field: the footprint seen at ~75° stays on the wall)
    add("cup_lamp", "cup", "outer", cup_outer(phi_l, 0.04), _mirror(LAMP, n_l), 0.34, field=0.2)
    add("cup_lamp_off", "cup", "outer", cup_outer(phi_l + 8.0, 0.04), _mirror(LAMP, n_l), 0.34,
        field=0.2)
    # the lamp's glint on the rounded lip, seen from the front (0.2° field: 1.2 mm)
    v_g = _unit([0.1, 0.15, 1.0])
    n_g = fr.local_dir("cup", _unit(LAMP + v_g))
    phi_g = math.atan2(n_g[2], n_g[0])
    t_g = math.atan2(n_g[1], math.hypot(n_g[0], n_g[2]))
    rl = 0.5 * CUP_WALL
    rr = CUP_R - rl + rl * math.cos(t_g)
    p_g = (rr * math.cos(phi_g), CUP_H - rl + rl * math.sin(t_g), rr * math.sin(phi_g))
    add("cup_lip_glint", "cup", "outer", (p_g, n_g), v_g, 0.32, field=0.2)
    # outer wall facing the torus (+x): through the gap from the front-right, and from the right
    # past the torus (behind it)
    add("cup_gap_0", "cup", "facing_torus", cup_outer(7.5, 0.025), _unit([0.7, 0.1, 1.0]), 0.35)
    add("cup_gap_1", "cup", "facing_torus", cup_outer(2.5, 0.052), _unit([1.0, 0.3, -0.2]),
        0.37)
    # inside: the inner back wall seen over the lip, an inner side wall, the floor down the axis
    axis = fr.normal("cup", (0, 1, 0))
    add("cup_inner_back", "cup", "inside", cup_inner(267.5, 0.05),
        _unit(_tilt(axis, fr.normal("cup", (0, 0, 1)), 30.0)), 0.33)
    add("cup_inner_side", "cup", "inside", cup_inner(182.5, 0.04),
        _unit(_tilt(axis, fr.normal("cup", (1, 0, 0)), 25.0)), 0.34)
    add("cup_floor", "cup", "inside", cup_floor(0.001, -0.004), axis, 0.36)

    # ---- torus: local +y is its axis (towards the camera, up and to the left, the cup's side)
    ax = fr.normal("torus", (0, 1, 0))

    def u_towards(d) -> float:  # ring angle of the part of the ring towards world direction d
        loc = fr.local_dir("torus", d)
        return math.atan2(loc[2], loc[0]) + 0.02  # off the mesh's vertex columns

    # the face towards the instrument at 0°, 35°, 55°
    p, n = torus_point(u_towards((0, -1, 0)), math.radians(85))
    add("torus_front", "torus", "outer", (p, n), fr.normal("torus", n), 0.33)
    p, n = torus_point(u_towards((1, 0, 0)), math.radians(45))
    add("torus_oblique_35", "torus", "outer", (p, n),
        _tilt(fr.normal("torus", n), front, 35.0), 0.36)
    p, n = torus_point(u_towards((1, 0, 0)), math.radians(15))
    add("torus_oblique_55", "torus", "outer", (p, n),
        _tilt(fr.normal("torus", n), _unit([0.2, 0.0, 1.0]), 55.0), 0.38)
    # grazing (70°, 0.2° field): the outer equator on the side away from the cup
    p, n = torus_point(u_towards((1, 0, 0)), math.radians(-15))
    add("torus_grazing", "torus", "outer", (p, n),
        _tilt(fr.normal("torus", n), _unit([0.0, 0.1, 1.0]), 70.0), 0.35, field=0.2)
    # highlights: the lamp and the sky's zenith mirrored to a viewer in front
    v_l = _unit([0.25, 0.05, 1.0])
    add("torus_lamp", "torus", "outer",
        torus_with_normal(fr.local_dir("torus", _unit(LAMP + v_l))), v_l, 0.34)
    v_s = _unit([0.1, 0.3, 1.0])
    add("torus_sky", "torus", "outer",
        torus_with_normal(fr.local_dir("torus", _unit(ZENITH + v_s))), v_s, 0.36)
    # inside the hole: the inner equator (its normal towards the hole's centre) at the top and
    # at the left of the ring, seen through the hole 50° off the axis
    for k, d in enumerate(((0, 1, 0), (-1, 0, 0))):
        p, n = torus_point(u_towards(d), math.radians(182.5))
        add(f"torus_hole_{k}", "torus", "hole", (p, n),
            _tilt(ax, fr.normal("torus", n), 50.0), 0.35)
    # facing the cup (-x): the outer half's normal towards -x, seen from the front-left
    for k, (dn, vv) in enumerate((((-1.0, 0.0, 0.3), (-0.5, 0.1, 1.0)),
                                  ((-1.0, -0.4, 0.3), (-0.3, -0.2, 1.0)))):
        add(f"torus_gap_{k}", "torus", "facing_cup",
            torus_with_normal(fr.local_dir("torus", _unit(dn))), _unit(vv), 0.35 + 0.02 * k)
    p, n = torus_with_normal(fr.local_dir("torus", _unit([0.2, -1.0, 0.5])))
    add("torus_under", "torus", "outer", (p, n), _unit([0.1, -0.5, 1.0]), 0.35)
    for s in spots:
        s["position"] = s["aim"] + s["distance"] * s["V"]
    return spots


def check_visibility(scene, spots: list[dict], pixels: int = 16) -> list[dict]:
    """Ray casting against both world meshes: the central ray's first hit (object, distance
    from the aim), the share of the field's rays (the simulator's 16 x 16 disc) that hit the
    spot's object, and the view angle at the aim."""
    from spectral_fit.fitting import cast_rays, scene_triangles
    from spectral_fit.geometry import build_bvh

    names = [o.name for o in scene.objects]
    verts, norms, tris, owner = scene_triangles([o.make_mesh(world=True)
                                                 for o in scene.objects])
    bvh = build_bvh(verts, tris)
    c = (np.arange(pixels) + 0.5) / pixels * 2.0 - 1.0
    gx, gy = np.meshgrid(c, c)
    disc = gx**2 + gy**2 <= 1.0
    out = []
    for s in spots:
        pos, aim = np.asarray(s["position"]), np.asarray(s["aim"])
        d = _unit(aim - pos)
        upv = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.99 else np.array([0.0, 0.0, 1.0])
        right = _unit(np.cross(d, upv))
        up = np.cross(right, d)
        th = math.tan(math.radians(0.5 * s["field"]))
        dirs = [d] + [_unit(d + th * (x * right + y * up)) for x, y in
                      zip(gx[disc], gy[disc], strict=True)]
        dirs = np.asarray(dirs)
        obj, pts, _ = cast_rays(bvh, pos, dirs, verts, norms, tris, owner, chunk=256)
        centre_obj = names[obj[0]] if obj[0] >= 0 else None
        miss = (float(abs(np.linalg.norm(pts[0] - pos) - np.linalg.norm(aim - pos)))
                if centre_obj else float("inf"))
        share = float(np.mean(obj[1:] == names.index(s["object"])))
        cos_v = float(np.dot(s["normal"], s["V"]))
        out.append({"id": s["id"], "hit": centre_obj, "miss_mm": 1e3 * miss,
                    "field_share": share, "view_deg": math.degrees(math.acos(min(1, cos_v)))})
    return out


def gloss_shares(scene, spots: list[dict]) -> dict[str, dict[str, float]]:
    """Under the package's forward model: the share of each reading (luminance) that the gloss
    lobe (beta), the mirror (chi), and the Fresnel/n dependence carry at the true materials."""
    from spectral_fit.color import xyz_weights
    from spectral_fit.fitting import simulate_readings

    sp = [{"object": s["object"], "aim": s["aim"], "position": s["position"],
           "field_angle_deg": s["field"]} for s in spots]
    truth = {o.name: {p: float(getattr(o.material, p))
                      for p in ("alpha", "beta", "chi", "mu", "n", "gamma")}
             for o in scene.objects}
    wy = xyz_weights(scene.wavelengths)[:, 1]

    def lum(params):
        return np.asarray(simulate_readings(scene, sp, params=params), np.float64) @ wy

    base = lum(truth)
    nob = lum({k: v | {"beta": 0.0} for k, v in truth.items()})
    chi = lum({k: v | {"chi": 0.02} for k, v in truth.items()})
    mu = lum({k: v | {"mu": v["mu"] * 1.03} for k, v in truth.items()})
    n2 = lum({k: v | {"n": v["n"] + 0.02} for k, v in truth.items()})
    return {s["id"]: {"gloss": float(1 - nob[i] / base[i]),
                      "chi_0.02": float(chi[i] / base[i] - 1),
                      "mu_3%": float(mu[i] / base[i] - 1),
                      "n_0.02": float(n2[i] / base[i] - 1)} for i, s in enumerate(spots)}


def specs(spots: list[dict]):
    from spectral_fit.validation.reference.instrument import ReadingSpec

    return [ReadingSpec(id=s["id"], object=s["object"], aim=tuple(map(float, s["aim"])),
                        position=tuple(map(float, s["position"])),
                        field_angle_deg=float(s["field"])) for s in spots]


def monte_carlo(spots: list[dict], spp_list: list[int], seeds: int = 8) -> dict:
    """Relative Monte Carlo noise of each reading (depth 16) at each spp: ``seeds`` renders with
    different seeds of one band triple (450, 550, 650 nm; every band triple is traced along the
    same paths, so a reading's Monte Carlo error is nearly common to its bands: a gain error),
    the sample standard deviation over seeds / the mean, RMS over the three bands."""
    from spectral_fit.io import load_scene
    from spectral_fit.validation.reference.instrument import Spectroradiometer, render_readings

    scene3 = load_scene(CONFIG, lambda d: d.setdefault("spectral", {}).update(
        start_nm=450.0, end_nm=650.0, step_nm=100.0))
    inst = Spectroradiometer(position=INSTRUMENT)
    sp = specs(spots)
    out: dict = {"seeds": seeds, "bands_nm": [450.0, 550.0, 650.0], "spp": {}}
    for spp in spp_list:
        t0 = time.perf_counter()
        r = np.stack([render_readings(scene3, sp, inst, spp=spp, depths=(16,), seed=k)
                      ["readings"][0] for k in range(seeds)])
        rel = r.std(0, ddof=1) / r.mean(0)
        rms = np.sqrt(np.mean(rel**2, axis=1))
        out["spp"][str(spp)] = {s["id"]: float(rms[i]) for i, s in enumerate(spots)}
        print(f"MC {spp} spp: median {100 * np.median(rms):.3f} %, max {100 * rms.max():.3f} % "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return out


def write(scene, spots: list[dict], spp: int, out: Path, mc: dict | None) -> None:
    from spectral_fit.validation.reference.instrument import Spectroradiometer
    from spectral_fit.validation.reference.instrument import simulate_readings as sim

    inst = Spectroradiometer(position=INSTRUMENT)
    manifest = sim(scene, out, instrument=inst, spots=specs(spots), spp=spp, white=WHITE,
                   scene_ref=SCENE_REF, progress=print)
    text = manifest.read_text()
    text = text.replace("field_angle_deg = 1.0\n", "field_angle_deg = 1.0\nbandwidth_nm = 5.0\n",
                        1)
    # the readings inside the cup and between the objects carry the model's own error (its
    # interreflection is a few per cent off there): estimated by the fit
    text += '\n[model_error]\ninterreflection = "auto"\n'
    for name, st in START.items():
        vals = ", ".join(f"{k} = {v!r}" for k, v in st.items())
        text += f"\n[objects.{name}]\nstart = {{ {vals} }}\n"
    manifest.write_text(text)
    truth = json.loads((out / "truth.json").read_text())
    truth["params"] = {o.name: {p: float(getattr(o.material, p)) for p in
                                ("alpha", "beta", "chi", "mu", "n", "gamma")}
                       for o in scene.objects}
    truth["start"] = START
    truth["independent"] = True
    truth["generator"] = (f"scripts/make_any_shape_session.py (spectral_fit.validation.reference."
                          f"instrument.simulate_readings, {spp} spp, path depth 16)")
    truth["regions"] = {s["id"]: s["region"] for s in spots}
    if mc is not None:
        truth["monte_carlo"] = mc
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    print(f"wrote {out}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=16384)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--check", action="store_true", help="spots and checks only, no render")
    ap.add_argument("--gloss", action="store_true", help="with --check: the gloss shares")
    ap.add_argument("--mc", default="", metavar="SPP[,SPP...]",
                    help="measure the Monte Carlo noise at these spp (8 seeds), then stop")
    ap.add_argument("--mc-json", type=Path, default=Path("/tmp/any_shape_spots_mc.json"),
                    help="where --mc writes its result; read into truth.json when present")
    args = ap.parse_args(argv)

    from spectral_fit.io import load_scene

    scene = load_scene(CONFIG)
    spots = design(scene)
    vis = check_visibility(scene, spots)
    bad = []
    for s, v in zip(spots, vis, strict=True):
        ok = v["hit"] == s["object"] and v["miss_mm"] < 0.5 and v["field_share"] == 1.0
        print(f"{s['id']:22s} {s['region']:13s} view {v['view_deg']:5.1f}°  d "
              f"{s['distance']:.2f} m  hit {v['hit']!s:6s} off {v['miss_mm']:6.2f} mm  field "
              f"{100 * v['field_share']:5.1f} %  pos "
              f"[{', '.join(f'{x:+.3f}' for x in s['position'])}]" + ("" if ok else "  <-- BAD"))
        if not ok:
            bad.append(s["id"])
    if bad:
        print(f"not visible or field off the object: {bad}")
        return 1
    if args.check:
        if args.gloss:
            for k, g in gloss_shares(scene, spots).items():
                print(f"{k:22s} " + "  ".join(f"{a} {100 * b:+6.2f} %" for a, b in g.items()))
        return 0
    if args.mc:
        mc = monte_carlo(spots, [int(x) for x in args.mc.split(",")])
        args.mc_json.write_text(json.dumps(mc, indent=1) + "\n")
        for k in mc["spp"][args.mc.split(",")[-1]]:
            print(f"{k:22s} " + "  ".join(f"{100 * v[k]:.3f} %" for v in mc["spp"].values()))
        return 0
    mc = json.loads(args.mc_json.read_text()) if args.mc_json.is_file() else None
    t0 = time.perf_counter()
    write(scene, spots, args.spp, args.out, mc)
    print(f"rendered and written in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
