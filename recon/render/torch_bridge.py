"""PyTorch bridge: a ``torch.autograd.Function`` around :meth:`CollocatedRenderer.render_batch`.

Inputs are copied into drjit tensors (so later in-place changes of the torch tensors cannot
alter what the backward pass reads); gradients come back through ``dr.backward`` from the
output's incoming gradient.
"""

from __future__ import annotations

import torch


class RenderFunction(torch.autograd.Function):
    """``apply(renderer, cameras, light_intensity, seed, v_pos, diffuse, specular, roughness)``
    -> (B, h, w, 3) float32 tensor."""

    @staticmethod
    def forward(ctx, renderer, cameras, light_intensity, seed, v_pos, diffuse, specular, roughness):
        dr, mi = renderer.dr, renderer.mi
        inputs = []
        for t in (v_pos, diffuse, specular, roughness):
            x = mi.TensorXf(t.detach().to(torch.float32).contiguous().clone())
            if t.requires_grad:
                dr.enable_grad(x)
            inputs.append(x)
        out = renderer.render_batch(*inputs, cameras, light_intensity, seed)
        ctx.renderer = renderer
        ctx.dr_inputs = inputs
        ctx.dr_out = out
        ctx.device = v_pos.device
        return out.torch().clone().to(v_pos.device)

    @staticmethod
    def backward(ctx, grad_out):
        renderer, inputs, out = ctx.renderer, ctx.dr_inputs, ctx.dr_out
        dr, mi = renderer.dr, renderer.mi
        ctx.dr_inputs = ctx.dr_out = None
        grads = [None] * 4
        if dr.grad_enabled(out):
            dr.set_grad(out, mi.TensorXf(grad_out.detach().to(torch.float32).contiguous().clone()))
            dr.enqueue(dr.ADMode.Backward, out)
            dr.traverse(dr.ADMode.Backward)
            for k, x in enumerate(inputs):
                if dr.grad_enabled(x):
                    grads[k] = dr.grad(x).torch().clone().to(ctx.device)
        return (None, None, None, None, *grads)
