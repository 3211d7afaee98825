"""Make a synthetic capture folder (DESIGN section 1) with ground truth in gt/.

Examples:
  python -m recon synth captures/demo --preset demo        (the bundled CI capture)
  python -m recon synth /tmp/blob --views 40 --res 256 --format dng --object blob --seed 0
  python -m recon synth /tmp/torus --object torus --no-cameras --masks
  python -m recon synth /tmp/phone --preset phone --ambient 0     (a phone's JPEGs, no ambient light)
  python -m recon synth /tmp/mug --scene tabletop --object mug --views 24 --res 256 --format exr
      (the object on a textured table, cameras on hand-held rings above it; gt/masks, gt/plane.json)
  python -m recon synth /tmp/bell --scene tabletop --object bell --palette glaze --no-pattern --wall 0.5 \
      --lamps 0.3 --closeups 0.15      (what makes tabletop masks hard: bench/masks.py)
"""

from __future__ import annotations

import argparse
import logging

from recon import sections
from recon.synth.capture import FORMATS, PRESETS, SCENES, SynthSettings, make_capture
from recon.synth.settings import TABLES
from recon.synth.imaging import TONE_CURVES
from recon.synth.shapes import OBJECT_KINDS

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out_dir", help="capture folder to write (replaced if it exists)")
    p.add_argument("--preset", choices=sorted(PRESETS), help="start from these settings")
    p.add_argument("--object", choices=OBJECT_KINDS)
    p.add_argument("--views", type=int, dest="n_views", help="number of photos")
    p.add_argument("--res", type=int, dest="width",
                   help="image width in pixels (height = 3/4 of it unless --height)")
    p.add_argument("--height", type=int)
    p.add_argument("--fov", type=float, help="horizontal field of view, degrees")
    p.add_argument("--distance", type=float, help="camera distance from the object center")
    p.add_argument("--format", choices=FORMATS)
    p.add_argument("--spp", type=int, help="samples per pixel")
    p.add_argument("--seed", type=int)
    p.add_argument("--light-intensity", type=float, dest="light_intensity")
    p.add_argument("--exposure-variation", type=float, dest="exposure_variation",
                   help="per-view exposure offsets in stops (DNG)")
    p.add_argument("--mesh-level", type=int, dest="mesh_level", help="20 * 4**level faces")
    p.add_argument("--texture-size", type=int, dest="texture_size")
    p.add_argument("--albedo", type=float, help="constant grey diffuse albedo instead of the pattern")
    p.add_argument("--specular", type=float, help="constant specular albedo (0 = purely diffuse object)")
    p.add_argument("--roughness", type=float, help="constant roughness instead of the three sectors")
    p.add_argument("--scale", type=float, help="scene scale (object and cameras; light scaled by scale^2)")
    p.add_argument("--scene", choices=SCENES, help="void (the object alone), tabletop (on a table) or tabletop_void "
                   "(the tabletop object and cameras without the table)")
    p.add_argument("--elevations", type=float, nargs=2, dest="elevation_range", metavar=("LOW", "HIGH"),
                   help="tabletop: camera elevations above the table, degrees")
    p.add_argument("--rings", type=int, help="tabletop: number of rings of views")
    p.add_argument("--background", type=float,
                   help="tabletop: albedo of the far backdrop (0: black beyond the table)")
    p.add_argument("--table-texture-size", type=int, dest="table_texture_size")
    p.add_argument("--table", choices=TABLES, help="tabletop: the table top, wood (textured) or plain (a light "
                   "laminate with almost no texture)")
    p.add_argument("--marker-square", type=float, dest="marker_square",
                   help="tabletop: print a ChArUco mat with squares of this side under the object")
    v = p.add_argument_group("scene variations that make masks hard (each off by default)")
    v.add_argument("--palette", help="the object's colours: default, wood (the table's), glaze, dark")
    v.add_argument("--no-pattern", dest="texture_pattern", action="store_false", default=None,
                   help="no fine albedo pattern (plain colour regions, little texture)")
    v.add_argument("--wall", type=float, help="tabletop/stand: albedo of a wall behind the object (0: none)")
    v.add_argument("--wall-distance", type=float, dest="wall_distance", help="the wall's distance, x --distance")
    v.add_argument("--lamps", type=float, help="tabletop/stand: two room lamps, this fraction of the flash "
                   "irradiance at the object")
    v.add_argument("--closeups", type=float, help="tabletop/stand: share of views taken closer (the frame cuts "
                   "the object)")
    v.add_argument("--closeup-distance", type=float, dest="closeup_distance", help="their distance, x the view's")
    v.add_argument("--stand-height", type=float, dest="stand_height", help="stand scene: the pole's length")
    v.add_argument("--stand-base", type=float, dest="stand_base", help="stand scene: the base's albedo")
    g = p.add_argument_group("a phone's imaging (recon.synth.imaging; each effect off by default)")
    g.add_argument("--flash-offset", type=float, nargs=3, dest="flash_offset", metavar=("X", "Y", "Z"),
                   help="flash position in camera coordinates (object units; x right, y down, z forward)")
    g.add_argument("--ambient", type=float, help="ambient light: fraction of the flash irradiance at the object")
    g.add_argument("--exposure-jitter", type=float, dest="exposure_jitter",
                   help="per-view exposure error the EXIF does not record, standard deviation in stops")
    g.add_argument("--wb-jitter", type=float, dest="wb_jitter",
                   help="per-view white-balance error, standard deviation of the channel log gains")
    g.add_argument("--falloff", type=float, nargs=2, metavar=("K1", "K2"),
                   help="radial lens falloff 1 + K1 r^2 + K2 r^4 (r = 1 in the corners)")
    g.add_argument("--tone-curve", dest="tone_curve", choices=TONE_CURVES,
                   help="format jpg: the camera's tone curve (recon.synth.imaging; none = plain sRGB)")
    g.add_argument("--tone-contrast", type=float, dest="tone_contrast", help="the S-curve's exponent")
    g.add_argument("--jpeg-quality", type=int, dest="jpeg_quality")
    g.add_argument("--falloff-gainmap", dest="falloff_gainmap", action="store_true", default=None,
                   help="format dng: the DNG carries the falloff's correction as an OpcodeList3 GainMap")
    p.add_argument("--cameras", dest="write_cameras", action="store_true", default=None,
                   help="write the top-level cameras.json")
    p.add_argument("--no-cameras", dest="write_cameras", action="store_false",
                   help="leave the top-level cameras.json out (the pipeline runs SfM)")
    p.add_argument("--state-light", dest="state_light", action="store_true", default=None,
                   help="state the flash's intensity (cameras.json light.intensity, capture.yaml "
                        "light_intensity), as a calibrated flash would; by default the pipeline estimates it")
    p.add_argument("--masks", dest="write_masks", action="store_true", default=None)
    p.add_argument("--no-masks", dest="write_masks", action="store_false")
    p.add_argument("--gt-linear", dest="write_gt_linear", action="store_true", default=None)
    p.add_argument("--no-gt-linear", dest="write_gt_linear", action="store_false")
    p.add_argument("--noise", dest="noise", action="store_true", default=None)
    p.add_argument("--no-noise", dest="noise", action="store_false")


def settings_from_args(args: argparse.Namespace) -> SynthSettings:
    """The preset (or the defaults) updated with every option given on the command line (each
    option's ``dest`` is the name of its setting, in whichever section: recon.sections.replace)."""
    base = PRESETS[args.preset] if args.preset else SynthSettings()
    names = sections.flatten(base)
    changes = {k: v for k, v in vars(args).items() if k in names and v is not None}
    if "width" in changes and "height" not in changes:
        changes["height"] = int(round(changes["width"] * 3 / 4 / 2)) * 2
    return sections.replace(base, **changes)


def command_line(args: argparse.Namespace) -> str:
    """The shortest command line that gives the same settings (recorded in gt/)."""
    base = sections.flatten(PRESETS[args.preset] if args.preset else SynthSettings())
    s = sections.flatten(settings_from_args(args))
    opts = {"object": "--object", "n_views": "--views", "width": "--res", "height": "--height",
            "fov": "--fov", "distance": "--distance", "format": "--format", "spp": "--spp",
            "seed": "--seed", "light_intensity": "--light-intensity",
            "exposure_variation": "--exposure-variation", "mesh_level": "--mesh-level",
            "texture_size": "--texture-size", "albedo": "--albedo", "specular": "--specular",
            "roughness": "--roughness", "scale": "--scale", "scene": "--scene", "rings": "--rings",
            "background": "--background", "table_texture_size": "--table-texture-size", "table": "--table",
            "marker_square": "--marker-square", "ambient": "--ambient", "exposure_jitter": "--exposure-jitter",
            "wb_jitter": "--wb-jitter", "tone_curve": "--tone-curve", "tone_contrast": "--tone-contrast",
            "jpeg_quality": "--jpeg-quality", "palette": "--palette", "wall": "--wall",
            "wall_distance": "--wall-distance", "lamps": "--lamps", "closeups": "--closeups",
            "closeup_distance": "--closeup-distance", "stand_height": "--stand-height",
            "stand_base": "--stand-base"}
    flags = {"write_cameras": "cameras", "write_masks": "masks", "write_gt_linear": "gt-linear",
             "noise": "noise", "falloff_gainmap": "falloff-gainmap", "state_light": "state-light"}
    parts = ["python -m recon synth", str(args.out_dir)]
    if args.preset:
        parts += ["--preset", args.preset]
    for key, flag in opts.items():
        if s[key] != base[key] or (key == "height" and s["width"] != base["width"]):
            parts += [flag, str(s[key])]
    for key, flag in (("elevation_range", "--elevations"), ("flash_offset", "--flash-offset"),
                      ("falloff", "--falloff")):
        if s[key] != base[key]:
            parts += [flag, *map(str, s[key])]
    if not s["texture_pattern"] and base["texture_pattern"]:
        parts.append("--no-pattern")
    for key, name in flags.items():
        if s[key] != base[key]:
            parts.append(f"--{name}" if s[key] else f"--no-{name}")
    return " ".join(parts)


def run(args: argparse.Namespace) -> int:
    settings = settings_from_args(args)
    log.info("settings: %s", settings)
    make_capture(args.out_dir, settings, command=command_line(args))
    return 0
