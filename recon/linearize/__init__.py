"""Stage 'linearize': a capture's photos to scene-linear Rec.709 images on one common scale.

Input: ``<capture>/images/`` (DESIGN section 1). Output, written atomically as one folder
(DESIGN section 2)::

    <out_dir>/<stem>.exr           float32 (H, W, 3) linear Rec.709 (D65 white)
    <out_dir>/<stem>.sat.png       clipped-pixel mask (255 = clipped: never use in a loss)
    <out_dir>/preview/<stem>.jpg   sRGB preview, one gain for the whole capture
    <out_dir>/linear.json          per-image metadata (see :func:`linearize_capture`)

The scale of the output
-----------------------
Every view is scaled to the capture's reference exposure ``H_ref`` (by default the median over
the views of ``H = exposure_time * iso / 100 / f_number**2``) by the factor ``H_ref / H``. For
RAW files, 1.0 is the level of a neutral (white-balanced grey) surface whose brightest RAW
channel just reaches the white level at ``H_ref``: the camera-to-XYZ matrix is normalized so
that the camera neutral with largest channel 1 maps to Y = 1 (the DNG convention for
ForwardMatrix, applied to the ColorMatrix path too). For JPEG/PNG, 1.0 is the largest code
value at ``H_ref``; EXR files pass through unchanged (scale 1).

RAW pipeline (DNG specification 1.6, chapter 6)
-----------------------------------------------
rawpy/LibRaw applies the LinearizationTable, subtracts the black level and demosaics in the
camera's native space (no white balance, no colour conversion, linear 16-bit output scaled so
the white level is 65535). GainMap opcodes (a phone's lens-shading correction) are applied
where the DNG puts them: OpcodeList2 on the linear CFA values before demosaicing, OpcodeList3
on the demosaiced camera RGB (:mod:`~recon.linearize.opcodes`); other opcodes are named in a
warning and in ``linear.json``. The DNG DefaultCrop is then applied. The camera neutral (one for the
whole capture: the median AsShotNeutral, or fixed multipliers) and the DNG colour tags
(ColorMatrix1/2 interpolated by the white's colour temperature, CameraCalibration,
AnalogBalance, ForwardMatrix when present) give camera -> XYZ; a Bradford adaptation takes the
scene white (or D50 for ForwardMatrix) to D65, then XYZ -> linear Rec.709. Clipped pixels are
found on the RAW values before demosaicing: any sample in the pixel's neighbourhood at or above
``black + saturation_threshold * (white - black)``.

Modules
-------
:mod:`~recon.linearize.settings` (:class:`LinearizeSettings`, :class:`LinearizeError`),
:mod:`~recon.linearize.metadata` (what each photo's file says: exposure, focal length, the RAW
colour tags, read through :mod:`recon.io.dng`), :mod:`~recon.linearize.opcodes` (DNG opcode
lists: GainMaps applied), :mod:`~recon.linearize.color` (camera colour to Rec.709),
:mod:`~recon.linearize.decode` (one photo's pixels), :mod:`~recon.linearize.stage`
(:func:`linearize_capture`: one white balance and one scale for the capture, the outputs).
"""

from recon.linearize.color import camera_to_rec709
from recon.linearize.metadata import exposure_value
from recon.linearize.settings import DEMOSAIC_ALGORITHMS, WHITE_BALANCE_MODES, LinearizeError, LinearizeSettings
from recon.linearize.stage import linearize_capture, list_images

__all__ = ["DEMOSAIC_ALGORITHMS", "WHITE_BALANCE_MODES", "LinearizeError", "LinearizeSettings", "camera_to_rec709",
           "exposure_value", "linearize_capture", "list_images"]
