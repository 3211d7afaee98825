"""12-megapixel phone-sized photos through every stage: disk, peak memory and wall time per stage.

    .venv/bin/python bench/large_photos.py --out bench/out/large            # make, run, tabulate
    .venv/bin/python bench/large_photos.py --out bench/out/large --table-only

1. Makes ``<out>/captures/phone12`` (only when missing): ``python -m recon synth --object blob
   --views 24 --res 4032 --format png8 --spp 4 --no-cameras --no-masks --seed 1`` (4032 x 3024,
   the object in the void), then re-encodes each photo as a JPEG (quality 92) with the EXIF a
   phone writes (ExposureTime 1/60, FNumber 1.8, ISO 100, FocalLengthIn35mmFilm from the true
   focal length), so the pipeline sees what a phone gives: JPEGs, no cameras, no masks.
2. Runs ``snakemake --cores 2 all --config captures=<out>/captures results=<out>/results
   preset=draft`` (skipped with ``--table-only``).
3. Prints one Markdown table: per stage the disk of ``results/<capture>/<stage>/``, the peak RSS
   and wall time from the stage's ``benchmarks/<stage>.tsv``; and, for the linear images, the same
   capture linearized at full size (``linearize.max_size: 0``, the behaviour before it existed)
   for comparison (``--no-full`` skips that run: minutes).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from recon.stages import NAMES

REPO = Path(__file__).resolve().parent.parent
STAGES = NAMES


def make_capture(captures: Path) -> Path:
    """The 12-MP JPEG capture (made once)."""
    from PIL import Image

    cap = captures / "phone12"
    if (cap / "images").is_dir() and any((cap / "images").glob("*.jpg")):
        return cap
    subprocess.run([sys.executable, "-m", "recon", "synth", str(cap), "--object", "blob", "--views", "24",
                    "--res", "4032", "--format", "png8", "--spp", "4", "--no-cameras", "--no-masks",
                    "--seed", "1"], check=True, cwd=REPO)
    frame = json.loads((cap / "gt" / "cameras.json").read_text())["frames"][0]
    f35 = frame["K"][0][0] * np.hypot(36, 24) / np.hypot(frame["width"], frame["height"])
    for png in sorted((cap / "images").glob("*.png")):
        exif = Image.Exif()
        ifd = exif.get_ifd(0x8769)  # ExposureTime, FNumber, ISO, FocalLengthIn35mmFilm
        ifd[0x829A], ifd[0x829D], ifd[0x8827], ifd[0xA405] = 1 / 60, 1.8, 100, int(round(f35))
        with Image.open(png) as im:
            im.convert("RGB").save(png.with_suffix(".jpg"), quality=92, exif=exif)
        png.unlink()
    return cap


def disk_mb(path: Path) -> float:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 2**20 if path.exists() else 0.0


def benchmark(results: Path, stage: str) -> dict | None:
    tsv = results / "benchmarks" / f"{stage}.tsv"
    if not tsv.is_file():
        return None
    with tsv.open() as f:
        row = list(csv.DictReader(f, delimiter="\t"))[-1]
    return {"s": float(row["s"]), "max_rss": float(row["max_rss"])}


def full_size_linear(cap: Path, out: Path) -> dict:
    """Linearize the capture at full size in a child process: disk, peak RSS, wall time."""
    code = ("import sys; from recon.linearize import linearize_capture, LinearizeSettings; "
            "linearize_capture(sys.argv[1], sys.argv[2], LinearizeSettings(max_size=0))")
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code, str(cap), str(out)], check=True, cwd=REPO)
    wall = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024  # kB -> MB (Linux)
    return {"disk_mb": disk_mb(out), "s": wall, "max_rss": rss}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "out" / "large")
    ap.add_argument("--table-only", action="store_true", help="tabulate an existing run")
    ap.add_argument("--no-full", action="store_true", help="skip the full-size linearize comparison")
    args = ap.parse_args(argv)
    captures, results_root = args.out / "captures", args.out / "results"
    cap = make_capture(captures)
    if not args.table_only:
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        subprocess.run([str(REPO / ".venv" / "bin" / "snakemake"), "--cores", "2", "all", "--config",
                        f"captures={captures}", f"results={results_root}", "preset=draft"],
                       check=True, cwd=REPO, env=env)
    res = results_root / cap.name
    n = len(list((cap / "images").glob("*.jpg")))
    lin = json.loads((res / "linear" / "linear.json").read_text())
    print(f"{n} JPEGs of {lin['source_width']}x{lin['source_height']} ({disk_mb(cap / 'images'):.0f} MB), "  # noqa: T201
          f"linear images {lin['width']}x{lin['height']}\n")
    print("| stage | disk (MB) | peak RSS (MB) | wall (s) |\n|---|---|---|---|")  # noqa: T201
    total = 0.0
    for stage in STAGES:
        b = benchmark(res, stage)
        if b is None:
            continue
        mb = disk_mb(res / stage)
        total += mb
        print(f"| {stage} | {mb:.0f} | {b['max_rss']:.0f} | {b['s']:.1f} |")  # noqa: T201
    print(f"| all (`results/{cap.name}/`) | {disk_mb(res):.0f} | | |")  # noqa: T201
    if (res / "poses" / "undistorted").is_dir():
        print(f"\n`poses/undistorted/` (half floats): {disk_mb(res / 'poses' / 'undistorted'):.0f} MB")  # noqa: T201
    if not args.no_full:
        full_dir = args.out / "linear_full"
        shutil.rmtree(full_dir, ignore_errors=True)
        f = full_size_linear(cap, full_dir)
        print(f"\nlinearize at full size (max_size 0): {f['disk_mb']:.0f} MB, peak RSS {f['max_rss']:.0f} MB, "  # noqa: T201
              f"{f['s']:.1f} s")


if __name__ == "__main__":
    main()
