"""Benchmark: our collocated renderer against Mitsuba's direct_projective and direct.

The paper's Table 1 setup: 512 x 512, 4 spp, a ~20k-face mesh (here a bumpy sphere with
self-occluding silhouettes, in front of a lit backdrop so the boundary term matters).
For each method it measures forward + backward time (loss = sum(w * image), gradients w.r.t.
the vertex positions) and the error of its directional derivatives against central finite
differences of a high-spp (stratified) forward render:

    rel_err(direction) = sqrt(mean over runs of (g_run - g_fd)^2) / |g_fd|

(bias and noise of ONE 4-spp gradient), averaged over three directions (a translation, a
scale about the object's center, a smooth normal displacement field). Prints per-method
numbers, ratios, and as its last line

    speedup_vs_direct_projective=<x> grad_rel_err=<ours> grad_rel_err_projective=<theirs>

Run: ``.venv/bin/python bench/render.py`` (about 2-3 minutes on 2 cores);
``--quick`` for a smaller run (256^2, fewer repetitions).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from recon.io.cameras import Camera, intrinsics, look_at  # noqa: E402
from recon.render import CollocatedRenderer, RenderSettings  # noqa: E402
from recon.render.mitsuba_scene import MitsubaScene  # noqa: E402


def bumpy_sphere(n_lon: int, n_lat: int):
    """Welded UV sphere with radial bumps: (v_pos, t_pos_idx, v_tex, t_tex_idx)."""
    theta = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    phi = np.linspace(0.0, 2 * np.pi, n_lon + 1)[:-1]
    T, P = np.meshgrid(theta, phi, indexing="ij")
    r = 1.0 + 0.18 * np.sin(4 * T) * np.cos(5 * P) + 0.06 * np.sin(9 * P + 2 * T)
    ring = np.stack([r * np.sin(T) * np.cos(P), r * np.sin(T) * np.sin(P), r * np.cos(T)], -1)
    v = np.concatenate([[[0, 0, 1]], ring.reshape(-1, 3), [[0, 0, -1]]])
    south = len(v) - 1

    def pid(i, j):
        return 1 + i * n_lon + (j % n_lon)

    uu, vv = np.meshgrid(np.linspace(0, 1, n_lon + 1), 1.0 - np.linspace(0, 1, n_lat + 1))
    t = np.stack([uu.ravel(), vv.ravel()], 1)

    def tid(row, j):
        return row * (n_lon + 1) + j

    f, ft = [], []
    for j in range(n_lon):
        f += [[0, pid(0, j), pid(0, j + 1)], [south, pid(n_lat - 2, j + 1), pid(n_lat - 2, j)]]
        ft += [[tid(0, j), tid(1, j), tid(1, j + 1)],
               [tid(n_lat, j), tid(n_lat - 1, j + 1), tid(n_lat - 1, j)]]
        for i in range(n_lat - 2):
            a, b, c, d = pid(i, j), pid(i + 1, j), pid(i + 1, j + 1), pid(i, j + 1)
            ta, tb, tc, td = tid(i + 1, j), tid(i + 2, j), tid(i + 2, j + 1), tid(i + 1, j + 1)
            f += [[a, b, c], [a, c, d]]
            ft += [[ta, tb, tc], [ta, tc, td]]
    return v, np.array(f), t, np.array(ft)


def make_scene(res: int):
    v, f, _, _ = bumpy_sphere(128, 80)
    # Per-vertex UVs (a projection, no seam): Mitsuba's mesh then has no vertices split at a
    # UV seam, whose open edges its projective integrator mishandles (see the report).
    t = np.stack([0.5 + 0.5 * np.arctan2(v[:, 1], v[:, 0]) / np.pi, 0.5 + 0.4 * v[:, 2]], 1)
    ft = f.copy()
    n_obj = len(v)
    # backdrop plane y = 2 facing -y, 2 x 2 quads
    s = np.linspace(-5, 5, 3)
    X, Z = np.meshgrid(s, s, indexing="xy")
    bv = np.stack([X.ravel(), np.full(X.size, 2.0), Z.ravel()], 1)
    bt = np.stack([(X.ravel() + 5) / 10, (Z.ravel() + 5) / 10], 1)
    bf = []
    for i in range(2):
        for j in range(2):
            a = i * 3 + j
            bf += [[a, a + 1, a + 4], [a, a + 4, a + 3]]
    bf = np.array(bf)
    v_all = np.concatenate([v, bv])
    f_all = np.concatenate([f, bf + len(v)])
    t_all = np.concatenate([t, bt])
    ft_all = np.concatenate([ft, bf + len(t)])
    rng = np.random.default_rng(0)
    n = 512
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    diffuse = 0.45 + 0.25 * np.stack([np.sin(i / 23.0), np.cos(j / 31.0), np.sin((i + j) / 41.0)], -1)
    diffuse = np.clip(diffuse + 0.05 * rng.random((n, n, 3)), 0.05, 0.95).astype(np.float32)
    specular = np.full((n, n, 1), 0.25, np.float32)
    roughness = (0.35 + 0.15 * np.sin(i / 50.0)[..., None]).astype(np.float32)
    cam = Camera("bench.png", res, res, intrinsics(res, res, 40.0),
                 look_at((0.6, -3.6, 0.9), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)))
    x = np.arange(res) / res
    w = ((0.5 + x[None, :, None] + 0.3 * x[:, None, None]) * np.array([1.0, 0.8, 0.6])).astype(np.float32)
    # directions: translation, scale about the center, smooth normal displacement (object only)
    dirs = {}
    d = np.zeros_like(v_all)
    d[:n_obj, 0] = 1.0
    dirs["translate_x"] = d
    d = np.zeros_like(v_all)
    d[:n_obj] = v
    dirs["scale"] = d
    nrm = v / np.linalg.norm(v, axis=1, keepdims=True)
    field = np.sin(2.0 * v[:, 0] + 1.0) * np.cos(1.5 * v[:, 2]) + 0.5 * np.sin(3.0 * v[:, 1])
    d = np.zeros_like(v_all)
    d[:n_obj] = nrm * field[:, None]
    dirs["normal_field"] = d
    return dict(v=v_all, f=f_all, t=t_all, ft=ft_all, diffuse=diffuse, specular=specular,
                roughness=roughness, cam=cam, w=w, dirs=dirs)


def out(line: str) -> None:
    """One line of benchmark output on stdout (this is a script, not the library)."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _loss_grad(render, mi, dr, sc, seed, shift: float = 0.0):
    """(vertex gradient (V, 3) numpy, seconds for forward + backward).

    ``shift`` moves the mesh (along x) so that every timed call sees new vertex positions,
    as in an optimization: all methods then rebuild their ray-tracing BVH.
    """
    v = mi.TensorXf((sc["v"] + np.array([shift, 0.0, 0.0])).astype(np.float32))
    dr.enable_grad(v)
    w = mi.Float(sc["w"].reshape(-1))
    dr.eval(v, w)
    dr.sync_thread()
    t0 = time.perf_counter()
    img = render(v, seed)
    loss = dr.sum(img.array * w)
    dr.backward(loss)
    g = dr.grad(v).numpy()
    dt = time.perf_counter() - t0
    return g, dt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=512)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=7, help="timed runs per method (after warm-up)")
    ap.add_argument("--grad-runs", type=int, default=4, help="gradient runs per method for the error")
    ap.add_argument("--fd-spp", type=int, default=256)
    ap.add_argument("--edge-spp", type=float, default=None,
                    help="edge samples per pixel (default: RenderSettings's)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--variant", default=None)
    args = ap.parse_args(argv)
    if args.quick:
        args.res, args.repeat, args.grad_runs, args.fd_spp = 256, 3, 3, 256
    sc = make_scene(args.res)
    light = 12.0
    out(f"scene: {len(sc['f'])} faces, {len(sc['v'])} vertices, {args.res}^2, {args.spp} spp")

    edge = {} if args.edge_spp is None else {"edge_samples_per_pixel": args.edge_spp}
    ours = CollocatedRenderer(sc["f"], sc["t"], sc["ft"],
                              RenderSettings(spp=args.spp, boundary="edge", variant=args.variant,
                                             **edge))
    interior = CollocatedRenderer(sc["f"], sc["t"], sc["ft"],
                                  RenderSettings(spp=args.spp, boundary="none", variant=args.variant))
    mi, dr = ours.mi, ours.dr
    proj = MitsubaScene(ours, "direct_projective")
    direct = MitsubaScene(ours, "direct")
    maps = (sc["diffuse"], sc["specular"], sc["roughness"])
    cams = [sc["cam"]]
    methods = {
        "ours (edge sampling)": lambda v, s: ours.render_batch(v, *maps, cams, light, s),
        "ours (interior only)": lambda v, s: interior.render_batch(v, *maps, cams, light, s),
        "mitsuba direct_projective": lambda v, s: proj.render(v, *maps, cams, light, s, args.spp),
        "mitsuba direct (interior only)": lambda v, s: direct.render(v, *maps, cams, light, s,
                                                                     args.spp),
    }

    # ---- reference: finite differences of a high-spp stratified forward
    fd_r = CollocatedRenderer(sc["f"], sc["t"], sc["ft"],
                              RenderSettings(spp=args.fd_spp, boundary="none", variant=args.variant))
    t0 = time.perf_counter()
    fd = {}
    for name, d in sc["dirs"].items():
        h = 5e-3
        vals = []
        for s in (1.0, -1.0):
            img = fd_r.render(sc["v"] + s * h * d, *maps, cams, light, 0)[0].numpy()
            vals.append(float((img.astype(np.float64) * sc["w"]).sum()))
        fd[name] = (vals[0] - vals[1]) / (2 * h)
    out(f"finite differences ({args.fd_spp} spp, h = 5e-3): "
          + ", ".join(f"{k} {v:.4g}" for k, v in fd.items())
          + f"  [{time.perf_counter() - t0:.1f} s]")

    # ---- timing: warm-up, then round-robin so every method sees the same machine load
    times = {name: [] for name in methods}
    for render in methods.values():
        _loss_grad(render, mi, dr, sc, 1000, shift=1e-4)  # kernel compilation
    for k in range(args.repeat):
        for name, render in methods.items():
            times[name].append(_loss_grad(render, mi, dr, sc, 2000 + k, shift=1e-4 * (k + 2))[1])
    # ---- gradient error against finite differences
    results = {}
    for name, render in methods.items():
        grads = [_loss_grad(render, mi, dr, sc, k)[0] for k in range(args.grad_runs)]
        errs = {}
        for dname, d in sc["dirs"].items():
            g = np.array([float((gr * d).sum()) for gr in grads])
            errs[dname] = float(np.sqrt(np.mean((g - fd[dname]) ** 2)) / abs(fd[dname]))
        t_med = float(np.median(times[name]))
        results[name] = (t_med, float(np.mean(list(errs.values()))), errs)
        out(f"{name:32s} fwd+bwd {1000 * t_med:8.1f} ms (min {1000 * min(times[name]):.1f})  "
              f"grad rel err {results[name][1]:.4f}  ("
              + ", ".join(f"{k} {v:.3f}" for k, v in errs.items()) + ")")

    # Ratios per round (the methods of one round ran back to back, under the same load),
    # then the median over rounds: robust to a machine whose load changes during the run.
    t = {name: np.array(v) for name, v in times.items()}
    ours, interior = t["ours (edge sampling)"], t["ours (interior only)"]
    proj, direct = t["mitsuba direct_projective"], t["mitsuba direct (interior only)"]
    e_ours = results["ours (edge sampling)"][1]
    e_proj = results["mitsuba direct_projective"][1]
    speedup = float(np.median(proj / ours))
    out(f"ratios (median over rounds): ours / ours interior-only = "
        f"{np.median(ours / interior):.2f}, ours / mitsuba direct = {np.median(ours / direct):.2f}, "
        f"mitsuba direct_projective / ours = {speedup:.1f}")
    out(f"speedup_vs_direct_projective={speedup:.2f} grad_rel_err={e_ours:.4f} "
        f"grad_rel_err_projective={e_proj:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
