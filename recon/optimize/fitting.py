"""Every fit but the main loop's, in one function: full-batch Adam with rates decaying tenfold.

The main loop (:mod:`recon.optimize.run`, :mod:`recon.optimize.iteration`) has its own schedule (stages, views sampled per
iteration, the surface guard). Every other fit of the optimize stage is :func:`fit`:

- :func:`recon.optimize.material.fit_model`: a material model's maps on a fixed G-buffer;
- :func:`recon.optimize.imaging.fit_imaging`: the maps and a phone's imaging terms;
- :func:`recon.optimize.imaging._heldout_gains`: the held-out views' exposure gains;
- :func:`recon.optimize.cameras.align_views`: the held-out views' poses on the renderer.

Each step evaluates the image term (eq. 6), adds the priors, sums them with their weights in
:func:`recon.optimize.objective.total` and takes an Adam step at the base rates times
:func:`decay`; ``project`` (if given) keeps the parameters in range after each step.
"""

from __future__ import annotations

from typing import Callable

import torch

from recon.optimize import objective


def decay(it: int, n: int) -> float:
    """The rate factor of step ``it`` of ``n``: 1 at the first step, 1/10 at the last."""
    return 0.1 ** (it / max(n - 1, 1))


def fit(groups: list[dict], n: int, image_term: Callable[[int], torch.Tensor], weights: dict[str, float],
        priors: Callable[[], dict[str, torch.Tensor]] | None = None, project: Callable[[], None] | None = None,
        betas: tuple[float, float] = (0.9, 0.999), final_loss: bool = True) -> torch.Tensor:
    """``n`` Adam steps on ``objective.total({"render": image_term(it), **priors()}, weights)``.

    Parameters
    ----------
    groups : Adam's parameter groups, each with its base ``lr`` (decayed by :func:`decay`).
    n : the number of steps (0: none).
    image_term : ``image_term(it)``, the image term (eq. 6) of step ``it`` (a scalar tensor).
    weights : each term's weight (the image term's is ``weights["render"]``).
    priors : the other terms (each name in :data:`recon.optimize.objective.TERMS`), evaluated
        after the image term of each step, not after the last.
    project : called after each step.
    final_loss : evaluate the image term once more after the last step (and return it).

    Returns
    -------
    The image term after the last step (``final_loss``), else that of the last step (NaN when
    ``n`` is 0); detach it before keeping it.
    """
    opt = torch.optim.Adam(groups, betas=betas)
    base = [g["lr"] for g in opt.param_groups]
    loss = torch.tensor(float("nan"))
    for it in range(n + 1 if final_loss else n):
        loss = image_term(it)
        if it == n:
            break
        terms = {"render": loss, **(priors() if priors is not None else {})}
        total = objective.total(terms, weights, dtype=None)
        for g, lr in zip(opt.param_groups, base, strict=True):
            g["lr"] = lr * decay(it, n)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        if project is not None:
            project()
    return loss
