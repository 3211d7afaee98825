"""Benchmark: the surface guard's check (recon.optimize.guard) on a 20k-face mesh.

The optimizer runs one check per geometry step (``SurfaceGuard.new_bad_faces``, pipelined in a
worker thread); it must stay well below a render + backward at 256^2 (about 0.6 s on 2 cores,
docs/STACK.md), or it becomes the loop's bottleneck. This used to be a unit test with a
wall-time bound (0.5 s per check), which a busy machine can break without any change to the
code; here it is a measurement, with the bound as a warning and the exit status.

Run: ``.venv/bin/python bench/guard_speed.py`` (a few seconds); ``--repeat N`` checks per
measurement, ``--bound S`` seconds per check above which it exits 1.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from recon.optimize.guard import SurfaceGuard  # noqa: E402
from recon.optimize.regularizers import MeshTopology  # noqa: E402
from recon.synth.shapes import icosphere  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--level", type=int, default=5, help="icosphere subdivisions (5: 20,480 faces)")
    ap.add_argument("--repeat", type=int, default=5, help="checks per measurement")
    ap.add_argument("--bound", type=float, default=0.5, help="seconds per check above which to exit 1")
    a = ap.parse_args(argv)
    mesh = icosphere(a.level)
    v, f = mesh.v_pos * 0.5, mesh.t_pos_idx
    g = SurfaceGuard(f, MeshTopology.from_faces(f, len(v)), v)
    g.new_bad_faces(v)  # warm-up (first-call allocations)
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    for _ in range(a.repeat):
        g.new_bad_faces(v)
    wall = (time.perf_counter() - t0) / a.repeat
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (cpu1.ru_utime - cpu0.ru_utime + cpu1.ru_stime - cpu0.ru_stime) / a.repeat
    load = os.getloadavg()[0]
    print(f"faces={len(f)} per_check_wall_s={wall:.4f} per_check_cpu_s={cpu:.4f} load1={load:.2f} "  # noqa: T201
          f"bound_s={a.bound}")
    if wall > a.bound:
        print(f"slower than {a.bound} s per check (load {load:.1f}: measure again on an idle machine)",  # noqa: T201
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
