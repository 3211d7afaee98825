"""PyTorch bridge: a ``torch.autograd.Function`` around :meth:`CollocatedRenderer.render_batch`.

Inputs are copied into drjit tensors (so later in-place changes of the torch tensors cannot
alter what the backward pass reads); gradients come back through ``dr.backward`` from the
output's incoming gradient.
"""

from __future__ import annotations

import torch


def camera_table_torch(K: torch.Tensor, world_to_camera: torch.Tensor) -> torch.Tensor:
    """(B, 24) camera table (Kinv, R_w2c, t_w2c, center per view; as
    :func:`recon.render.rays.camera_table`) from (B, 3, 3) ``K`` and (B, 3|4, 4)
    ``world_to_camera``, differentiable in both."""
    R = world_to_camera[:, :3, :3]
    t = world_to_camera[:, :3, 3]
    center = -(R.transpose(1, 2) @ t[..., None])[..., 0]
    return torch.cat([torch.linalg.inv(K).reshape(-1, 9), R.reshape(-1, 9), t, center], dim=1)


class RenderFunction(torch.autograd.Function):
    """``apply(renderer, cameras, light_intensity, seed, v_pos, diffuse, specular, roughness,
    camera_table=None, lighting=(flash_offset, ambient))`` -> (B, h, w, 3) float32 tensor."""

    @staticmethod
    def forward(ctx, renderer, cameras, light_intensity, seed, v_pos, diffuse, specular, roughness,
                camera_table=None, lighting=(None, 0.0)):
        dr, mi = renderer.dr, renderer.mi
        inputs = []
        for t in (v_pos, diffuse, specular, roughness):
            x = mi.TensorXf(t.detach().to(torch.float32).contiguous().clone())
            if t.requires_grad:
                dr.enable_grad(x)
            inputs.append(x)
        table = None
        if camera_table is not None:
            table = mi.Float(camera_table.detach().to(torch.float32).reshape(-1).contiguous().clone())
            if camera_table.requires_grad:
                dr.enable_grad(table)
        inputs.append(table)
        out = renderer.render_batch(*inputs[:4], cameras, light_intensity, seed, camera_table=table,
                                    flash_offset=lighting[0], ambient=lighting[1])
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
        grads = [None] * 5
        if dr.grad_enabled(out):
            dr.set_grad(out, mi.TensorXf(grad_out.detach().to(torch.float32).contiguous().clone()))
            dr.enqueue(dr.ADMode.Backward, out)
            dr.traverse(dr.ADMode.Backward)
            for k, x in enumerate(inputs):
                if x is not None and dr.grad_enabled(x):
                    grads[k] = dr.grad(x).torch().clone().to(ctx.device)
        if grads[4] is not None:
            grads[4] = grads[4].reshape(-1, 24)
        return (None, None, None, None, *grads, None)
