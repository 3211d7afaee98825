"""Decoding one photo into linear Rec.709 before the capture's exposure scale.

RAW (DNG specification 1.6, chapter 6): rawpy/LibRaw applies the LinearizationTable, subtracts
the black level and demosaics in the camera's native space (no white balance, no colour
conversion, linear 16-bit output scaled so the white level is 65535). When the DNG carries
GainMaps in OpcodeList2, the CFA is first mapped here to the DNG's linear reference values
(``(raw - black) / (white - black)`` per CFA site, clipped to [0, 1]), multiplied by the gains
and handed back to LibRaw as 16-bit data with black 0 and white 65535; OpcodeList3 GainMaps
multiply the demosaiced camera RGB. The DNG DefaultCrop is then applied and the capture's camera -> Rec.709 matrix (:mod:`recon.linearize.color`) converts
the colours. Clipped pixels are found on the RAW values before demosaicing: any sample in the
pixel's neighbourhood at or above ``black + saturation_threshold * (white - black)``.
JPEG/PNG: the sRGB decoding; a pixel with a channel at the largest code value is clipped.
EXR: unchanged, nothing clipped.
"""

from __future__ import annotations

import logging

import numpy as np

from recon.io.images import ImageError, read_exr, read_ldr_codes, srgb_codes_to_linear
from recon.linearize.metadata import View
from recon.linearize.opcodes import apply_gain_maps
from recon.linearize.settings import LinearizeError, LinearizeSettings

log = logging.getLogger(__name__)


def _decode_raw(view: View, settings: LinearizeSettings) -> tuple[np.ndarray, np.ndarray, dict]:
    """Camera-native linear (H, W, 3) float32 (1 = white level), clipped mask (H, W), levels."""
    import rawpy

    path = view.path
    try:
        with rawpy.imread(str(path)) as raw:
            raw_visible = raw.raw_image_visible.copy()
            colors = raw.raw_colors_visible.copy()
            black = np.asarray(raw.black_level_per_channel, dtype=np.float64)
            white = libraw_white = float(raw.white_level)
            cam_white = raw.camera_white_level_per_channel
            if cam_white is not None and min(cam_white) > 0:
                white = min(white, float(min(cam_white)))
            if view.linearization_table_max is not None:
                white = min(white, float(view.linearization_table_max))
            if white <= black.max():
                raise LinearizeError(f"{path}: white level {white} is not above the black level {black}")
            clipped, levels16 = None, {}
            if view.opcodes.stage2 and raw_visible.ndim == 2:
                # OpcodeList2 GainMaps act on the linear reference values (DNG stage 2): map the
                # CFA to [0, 1] here, apply them, and hand LibRaw the result as 16-bit data with
                # black 0 and white 65535 (LibRaw applies no opcode itself)
                stage2, clipped = _stage2(raw_visible, colors, black, white, view, settings)
                raw.raw_image_visible[:] = np.rint(stage2 * 65535.0).astype(np.uint16)
                levels16 = {"user_black": 0, "user_cblack": [0, 0, 0, 0], "user_sat": 65535}
            rgb16 = raw.postprocess(
                demosaic_algorithm=getattr(rawpy.DemosaicAlgorithm, settings.demosaic.upper()),
                output_color=rawpy.ColorSpace.raw,
                use_camera_wb=False,
                use_auto_wb=False,
                user_wb=[1.0, 1.0, 1.0, 1.0],
                no_auto_bright=True,
                no_auto_scale=False,
                gamma=(1, 1),
                output_bps=16,
                user_flip=0,
                adjust_maximum_thr=0.0,
                highlight_mode=rawpy.HighlightMode.Clip,
                fbdd_noise_reduction=rawpy.FBDDNoiseReductionMode.Off,
                **levels16,
            )
    except rawpy.LibRawError as e:
        raise LinearizeError(
            f"{path}: the RAW data cannot be decoded ({type(e).__name__}: {e}); the file is "
            "truncated or corrupt: copy it from the camera again or remove it from images/"
        ) from e
    if rgb16.shape[:2] != raw_visible.shape[:2]:
        raise LinearizeError(
            f"{path}: demosaiced size {rgb16.shape[:2]} differs from the RAW size "
            f"{raw_visible.shape[:2]}; this RAW layout is not supported"
        )
    # clipped samples, on RAW values before demosaicing
    if clipped is not None:
        pass  # found with the stage-2 values
    elif raw_visible.ndim == 3:  # LinearRaw: all channels per pixel
        thr = black[: raw_visible.shape[2]] + settings.saturation_threshold * (white - black[: raw_visible.shape[2]])
        clipped = np.any(raw_visible >= thr, axis=2)
    else:
        black_px = black[np.clip(colors, 0, 3)]
        clipped = raw_visible >= black_px + settings.saturation_threshold * (white - black_px)
    if settings.saturation_radius > 0 and clipped.any():
        import cv2

        k = 2 * settings.saturation_radius + 1
        clipped = cv2.dilate(clipped.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    if levels16:  # the stage-2 data: black 0, white 65535
        cam = rgb16.astype(np.float32) * np.float32(1.0 / 65535.0)
    else:
        # LibRaw scales (raw - black) by 65535 / (its white level - black); rescale so that the
        # effective white level (a LinearizationTable may end below WhiteLevel) is 1
        libraw_white = float(libraw_white)
        b = float(np.mean(black))
        cam = rgb16.astype(np.float32) * np.float32((libraw_white - b) / (white - b) / 65535.0)
    if view.opcodes.stage2 and raw_visible.ndim == 3:
        # LinearRaw: stage 2 has the three planes and no demosaicing follows; LibRaw clipped at 1
        apply_gain_maps(cam, view.opcodes.stage2)
        clipped |= np.any(cam >= settings.saturation_threshold, axis=2)
    if view.opcodes.stage3:  # OpcodeList3: on the demosaiced camera RGB, before the DefaultCrop
        apply_gain_maps(cam, view.opcodes.stage3)
    if view.default_crop is not None:
        x, y, w, h = view.default_crop
        H, W = cam.shape[:2]
        if x < 0 or y < 0 or w <= 0 or h <= 0 or x + w > W or y + h > H:
            raise LinearizeError(
                f"{path}: DefaultCrop (origin {x},{y}, size {w}x{h}) does not fit the {W}x{H} image"
            )
        cam = cam[y : y + h, x : x + w]
        clipped = clipped[y : y + h, x : x + w]
    levels = {"black_level": black.tolist(), "white_level": white}
    return np.ascontiguousarray(cam), clipped, levels


def _stage2(raw_visible: np.ndarray, colors: np.ndarray, black: np.ndarray, white: float, view: View,
            settings: LinearizeSettings) -> tuple[np.ndarray, np.ndarray]:
    """The CFA as DNG linear reference values in [0, 1] with the OpcodeList2 GainMaps applied,
    and the clipped samples: saturated on the sensor, or brought to the white level by a gain
    (the SDK clips there)."""
    black_px = black[np.clip(colors, 0, 3)].astype(np.float32)
    x = (raw_visible.astype(np.float32) - black_px) / (np.float32(white) - black_px)
    np.clip(x, 0.0, 1.0, out=x)
    clipped = x >= settings.saturation_threshold
    apply_gain_maps(x, view.opcodes.stage2)
    clipped |= x >= settings.saturation_threshold
    return x, clipped


def _as_rgb(img: np.ndarray) -> np.ndarray:
    if img.shape[2] <= 2:  # gray, gray + alpha
        return np.repeat(img[:, :, :1], 3, axis=2)
    return img[:, :, :3]


def _warn_alpha(path, img: np.ndarray, opaque: float = 1.0) -> float:
    """Warn, naming the file, when a PNG's alpha channel is not fully opaque: the pipeline reads
    colour only (the object's mask comes from masks/<stem>.png or is derived from the photo).
    ``opaque``: the alpha of an opaque pixel (255 for 8-bit codes). Returns the transparent
    fraction (alpha < opaque / 2)."""
    if img.shape[2] not in (2, 4):
        return 0.0
    alpha = img[:, :, -1]
    if np.all(alpha >= opaque):
        return 0.0
    transparent = float(np.mean(alpha < 0.5 * opaque))
    log.warning(
        "%s: its alpha channel is ignored (%.1f%% of the pixels transparent): only the colour is used, "
        "including where alpha hides it; if the alpha marks the object, save it as masks/%s.png "
        "(nonzero = object) and export the photo without alpha",
        path, 100 * transparent, path.stem,
    )
    return transparent


def decode_view(view: View, settings: LinearizeSettings, matrix: np.ndarray | None) -> tuple:
    """Linear Rec.709 (H, W, 3) float32 before the exposure scale, clipped mask, levels."""
    if view.kind == "raw":
        cam, clipped, levels = _decode_raw(view, settings)
        rgb = cam.reshape(-1, 3) @ matrix.T.astype(np.float32)
        return rgb.reshape(cam.shape).astype(np.float32), clipped, levels
    if view.kind == "ldr":
        try:
            codes, bits = read_ldr_codes(view.path)  # 8-bit codes: a quarter of the floats' memory
        except ImageError as e:
            raise LinearizeError(str(e)) from e
        _warn_alpha(view.path, codes, 2**bits - 1)
        codes = _as_rgb(codes)
        clipped = np.any(codes == 2**bits - 1, axis=2)
        return srgb_codes_to_linear(codes, bits), clipped, {"bits": bits}
    try:
        img = _as_rgb(read_exr(view.path))
    except ImageError as e:
        raise LinearizeError(str(e)) from e
    if not np.all(np.isfinite(img)):
        raise LinearizeError(f"{view.path}: the EXR contains NaN or Inf values; fix the file")
    return img.astype(np.float32), np.zeros(img.shape[:2], bool), {}
