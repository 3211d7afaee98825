"""The imaging terms inside the coarse-to-fine loop (``imaging.loop: select``): the terms the
imaging selection chose on the coarse model (:func:`recon.optimize.imaging_select.select_for_loop`)
applied to the loop's rendered images and refined with the shape. The scene side (flash offset,
ambient light) goes to the renderer, the camera side (exposure gains, falloff, tone curve) is
:func:`recon.optimize.formation.camera_response`: the one image formation of the G-buffer fits
and held-out scorers too."""

from __future__ import annotations

import numpy as np
import torch

from recon.optimize.formation import ImagingModel, ImagingParams, camera_response, image_radius2, renderer_lighting


class LoopImaging:
    """The imaging terms chosen on the coarse model, inside the coarse-to-fine loop
    (``imaging.loop: select``): the flash offset and the ambient light go to the renderer as
    fixed values (:meth:`lighting`), the exposure gains, falloff and tone curve act on the
    rendered images (:meth:`apply`) and are refined with the shape (rate ``lr``; 0: fixed).

    ``params`` is None until the selection ran (the stages before it render the ideal formation).
    ``shared_from``: another run's loop imaging whose choice this run takes instead of selecting
    again (:meth:`share`): the camera refinement's paired runs, identical up to the selection.
    ``exposure``: (training views,) their recorded exposures relative to the reference (the
    views of :func:`recorded_exposures`; None: all 1), where the tone curve acts.
    """

    def __init__(self, lr: float, exposure_prior: float, shared_from: "LoopImaging | None" = None,
                 exposure: np.ndarray | None = None):
        self.exposure = None if exposure is None else torch.as_tensor(np.asarray(exposure, np.float32))
        self.lr = float(lr)
        self.exposure_prior = float(exposure_prior)
        self.shared_from = shared_from
        self.params: ImagingParams | None = None
        self.evidence: dict | None = None
        self.adopted: ImagingParams | None = None  # the values as chosen (before the loop refines them)
        self.opt: torch.optim.Optimizer | None = None
        self._r2: dict = {}

    @property
    def active(self) -> bool:
        return self.params is not None

    def adopt(self, params: ImagingParams | None, evidence: dict) -> None:
        """Take the selection's fitted terms (None: nothing chosen, the ideal formation stays)."""
        self.evidence = evidence
        self.params = params
        self.adopted = None if params is None else params.clone()
        self.opt = None
        if params is not None and self.lr > 0:
            groups = [g for g in params.groups(self.lr) if g["params"][0] is not params.offset_raw
                      and g["params"][0] is not params.ambient_raw]
            if groups:
                self.opt = torch.optim.Adam(groups)
                for g in self.opt.param_groups:
                    g["base_lr"] = g["lr"]

    def share(self) -> bool:
        """Adopt ``shared_from``'s choice and its values as chosen, if it has chosen (False: it
        has not, select anew)."""
        src = self.shared_from
        if src is None or src.evidence is None:
            return False
        self.adopt(None if src.adopted is None else src.adopted.clone(), {**src.evidence, "shared": True})
        return True

    def lighting(self) -> dict:
        """Renderer keywords: ``flash_offset`` (camera coordinates) and ``ambient`` (fixed;
        :func:`recon.optimize.formation.renderer_lighting`)."""
        return renderer_lighting(self.params)

    def apply(self, img: torch.Tensor, idx, gains: torch.Tensor | None = None,
              exposure: torch.Tensor | None = None) -> torch.Tensor:
        """(B, h, w, 3) rendered radiance of the training views ``idx`` -> predicted photo
        (:func:`recon.optimize.formation.camera_response`).
        ``gains``: (B,) exposure gains of these images instead of the training views' (views
        outside the training set, e.g. held-out views with their own fitted gains).
        ``exposure``: (B,) recorded exposures of these images relative to the reference (where
        the tone curve acts, :func:`recon.optimize.formation.apply_tone`); default:
        ``self.exposure[idx]`` for training views (``gains`` None), else 1."""
        p = self.params
        if p is None:
            return img
        m = p.model
        idx_t = torch.as_tensor(np.asarray(idx), dtype=torch.long)
        view = torch.arange(int(img.shape[0])) if gains is not None else idx_t
        r2 = None
        if m.has("falloff"):
            h, w = int(img.shape[1]), int(img.shape[2])
            if (h, w) not in self._r2:
                self._r2[(h, w)] = image_radius2(h, w)
            r2 = self._r2[(h, w)]
        e = None
        if m.has("tone"):
            if exposure is None and gains is None and self.exposure is not None:
                exposure = self.exposure[idx_t]
            e = None if exposure is None else torch.as_tensor(exposure, dtype=img.dtype).reshape(-1, 1, 1)
        return camera_response(img, p, view.reshape(-1, 1, 1), r2, e, gains)

    def prior(self) -> torch.Tensor:
        """The exposure prior (0 without that term)."""
        return torch.zeros(()) if self.params is None else self.params.prior(self.exposure_prior)

    def zero_grad(self) -> None:
        if self.opt is not None:
            self.opt.zero_grad(set_to_none=True)

    def step(self, factor: float) -> None:
        if self.opt is not None:
            for g in self.opt.param_groups:
                g["lr"] = g["base_lr"] * factor
            self.opt.step()

    @torch.no_grad()
    def report(self) -> dict:
        out = {"evidence": self.evidence, "chosen": [] if self.params is None else list(self.params.model.terms)}
        if self.params is not None:
            out["values_after_loop"] = self.params.report()
        return out

    def state(self) -> dict:
        p = self.params
        return {"evidence": self.evidence,
                "params": None if p is None else {
                    "terms": list(p.model.terms), "n_views": int(p.log_gain.shape[0]), "length": p.length,
                    "tone_scale": p.tone_scale, "knots": int(p.tone_raw.shape[0]), "tone_gain": p.tone_gain,
                    "offset_given": None if p.offset_given is None else p.offset_given.tolist(),
                    "tensors": {k: getattr(p, k).detach().clone() for k in
                                ("offset_raw", "log_gain", "ambient_raw", "falloff_k", "tone_raw", "tone_log_gain")}},
                "optimizer": None if self.opt is None else self.opt.state_dict()}

    def load(self, state: dict) -> None:
        sp = state["params"]
        params = None
        if sp is not None:
            # a state saved before the tone curve's input scale existed: c = 1, not fitted
            params = ImagingParams(ImagingModel(tuple(sp["terms"])), sp["n_views"], sp["length"], sp["tone_scale"],
                                   sp["offset_given"], sp["knots"], tone_gain=bool(sp.get("tone_gain", False)))
            with torch.no_grad():
                for k, v in sp["tensors"].items():
                    getattr(params, k).copy_(v)
        self.adopt(params, state["evidence"])
        if self.opt is not None and state.get("optimizer") is not None:
            self.opt.load_state_dict(state["optimizer"])
            for g in self.opt.param_groups:
                g.setdefault("base_lr", g["lr"])
