"""Differentiable rendering under a collocated point light (DESIGN section 3).

Public API: :class:`RenderSettings`, :class:`CollocatedRenderer` (``render``, ``render_batch``,
``render_torch``), :class:`RenderError`. Typical use in an optimizer::

    r = CollocatedRenderer(mesh.t_pos_idx, mesh.v_tex, mesh.t_tex_idx, RenderSettings(spp=4))
    img = r.render_torch(v_pos, diffuse, specular, roughness, cameras, light_intensity, seed)
    # img: (B, h, w, 3) linear radiance; autograd reaches v_pos and the three maps

Topology is fixed per renderer: make a new one after remeshing. The renderer's parts:
:mod:`recon.render.collocated` (the renderer and its control flow), :mod:`recon.render.settings`,
:mod:`recon.render.rays` (camera table, rays, tracing, the flash's position),
:mod:`recon.render.shading` (the hit and the BRDF's drjit copies), :mod:`recon.render.boundary`
(the edge-sampled silhouette term), :mod:`recon.render.edges` (silhouette edges),
:mod:`recon.render.torch_bridge` (autograd). Other modules: :mod:`recon.render.mitsuba_scene`
(the same scene with Mitsuba's integrators, for comparisons), :mod:`recon.render.mitsuba_bsdf`
(the forward reference plugin), :mod:`recon.render.envmap` (environment relighting).
"""

from recon.render.collocated import CollocatedRenderer, RenderError, RenderSettings, camera_table

__all__ = ["CollocatedRenderer", "RenderError", "RenderSettings", "camera_table"]
